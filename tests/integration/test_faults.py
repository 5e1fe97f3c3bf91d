"""Faults over real processes: killed and frozen learners, frozen and restarted servers.

Every process is started with a readiness line and cleaned up; a frozen process (SIGSTOP) is
what a hung host looks like on the wire: its ZeroMQ I/O thread stops answering heartbeats.
"""

from __future__ import annotations

import csv
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import zmq

from agent_client.defaults import RESET_TIMEOUT_S, STEP_TIMEOUT_S
from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import ServerError, ServerLost, ServerTimeout
from agent_client.transport import ZmqChannel
from protocol.codec import encode
from protocol.messages import Close, Error, Welcome
from protocol.transport.zeromq import HEARTBEAT_TIMEOUT_MS
from tests.conftest import sim_server, wait_for_line

# A learner that opens an episode, takes a few steps, says so, then goes quiet the way a long
# gradient update does: its main thread is busy, ZeroMQ's I/O thread still answers heartbeats.
LEARNER = """
import sys, time
from agent_client.envs.remote_env import RemoteEnv
env = RemoteEnv(sys.argv[1], "cf", reward=lambda *_: 0.0)
env.reset(seed=1)
for _ in range(3):
    env.step({"acceleration": [0.0], "lane_change": 0})
print("stepping", flush=True)
time.sleep(120)
"""


@contextmanager
def learner(address: str) -> Iterator[subprocess.Popen[str]]:
    process = subprocess.Popen(
        [sys.executable, "-c", LEARNER, address], stdout=subprocess.PIPE, text=True
    )
    try:
        wait_for_line(process, "stepping", 60.0)
        yield process
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGCONT)
            process.kill()
        process.wait(timeout=10)
        assert process.stdout is not None
        process.stdout.close()


def seconds_until_served(address: str, limit_s: float) -> float:
    """How long until a new client's hello is welcomed (retrying while the server is busy).

    The client then says goodbye, so the server is free again when this returns (a socket just
    closed frees it only once the server has seen the disconnect: a race with the next hello).
    """
    started = time.monotonic()
    with ZmqChannel(address, timeout_s=limit_s) as connection:
        while True:
            try:
                assert isinstance(connection.hello(), Welcome)
                break
            except ServerError as exc:
                if exc.code != "busy" or time.monotonic() - started > limit_s:
                    raise
                time.sleep(0.05)
        waited = time.monotonic() - started
        connection.request(Close())
        return waited


FREED_BY_THE_DISCONNECT_S = 0.4 * HEARTBEAT_TIMEOUT_MS / 1000
"""Well before the heartbeat timeout could free a session (2 s of 5): the server saw the
connection close (what it must do for a killed learner), not a peer that went silent. Measured
here: at most 4 ms over 40 killed learners."""


def is_busy(address: str) -> bool:
    with ZmqChannel(address, timeout_s=5.0) as connection:
        try:
            connection.hello()
        except ServerError as exc:
            return exc.code == "busy"
        return False


def test_a_killed_learner_frees_the_server_at_once() -> None:
    with sim_server("--backend", "fake") as server, learner(server.address) as process:
        assert is_busy(server.address)
        process.kill()
        process.wait(timeout=10)
        assert seconds_until_served(server.address, 10.0) < FREED_BY_THE_DISCONNECT_S


# A learner killed while its last request is in flight: the server reads that request and the
# news of the closed connection together, in either order.
DYING_MID_REQUEST = """
import os, signal, sys
from agent_client.transport import ZmqChannel
from protocol.messages import Reset, Step
connection = ZmqChannel(sys.argv[1], timeout_s=30.0)
connection.hello()
connection.request(Reset("cf", 1))
for seq in range(1, 4):
    connection.request(Step(seq, 0.0))
connection.send(Step(4, 0.0))
os.kill(os.getpid(), signal.SIGKILL)
"""


def test_a_learner_killed_mid_request_frees_the_server_every_time() -> None:
    with sim_server("--backend", "fake") as server:
        for _ in range(20):  # the two orders are a race: try it often
            doomed = subprocess.run(
                [sys.executable, "-c", DYING_MID_REQUEST, server.address],
                timeout=60, check=False, capture_output=True, text=True,
            )  # fmt: skip
            # it got to its last request (a learner refused as busy would exit with an error)
            assert doomed.returncode == -signal.SIGKILL, doomed.stderr
            assert seconds_until_served(server.address, 10.0) < FREED_BY_THE_DISCONNECT_S


def test_a_busy_learner_keeps_its_session_and_a_frozen_one_loses_it() -> None:
    with (
        sim_server("--backend", "fake", "--heartbeat-timeout", "1") as server,
        learner(server.address) as process,
    ):
        time.sleep(2.5)  # longer than the heartbeat timeout, shorter than the session timeout
        assert is_busy(server.address)  # a long "gradient update" is not a dead learner
        process.send_signal(signal.SIGSTOP)  # frozen: heartbeats go unanswered
        waited = seconds_until_served(server.address, 15.0)
        assert 0.5 < waited < 6.0


def test_a_frozen_server_is_reported_lost_long_before_the_step_timeout() -> None:
    with sim_server("--backend", "fake") as server:
        env = RemoteEnv(server.address, "cf", reward=lambda *_: 0.0, timeout_s=60.0)
        try:
            env.reset(seed=1)
            server.process.send_signal(signal.SIGSTOP)
            started = time.monotonic()
            with pytest.raises(ServerLost):
                env.step({"acceleration": np.zeros(1), "lane_change": 0})
            assert time.monotonic() - started < 15.0  # the heartbeat timeout (5 s) + slack
        finally:
            server.process.send_signal(signal.SIGCONT)
            env.close()


def test_a_slow_step_is_not_a_lost_server() -> None:
    # A simulator whose step takes longer than the heartbeat timeout: its main thread is busy,
    # its ZeroMQ I/O thread still answers PINGs, so the client waits for the reply.
    context = zmq.Context()
    router = context.socket(zmq.ROUTER)
    router.setsockopt(zmq.LINGER, 0)
    router.bind("tcp://127.0.0.1:*")
    address = router.getsockopt_string(zmq.LAST_ENDPOINT)

    def slow_server() -> None:
        if router.poll(10_000):
            *envelope, _ = router.recv_multipart()
            time.sleep(2.5)  # the "step"
            router.send_multipart([*envelope, encode(Error("busy", "slow, but alive"))])

    thread = threading.Thread(target=slow_server, daemon=True)
    thread.start()
    try:
        with ZmqChannel(address, timeout_s=30.0, heartbeat_timeout_s=1.0) as connection:
            started = time.monotonic()
            reply = connection.exchange(Close())
            assert isinstance(reply, Error) and reply.message == "slow, but alive"
            assert time.monotonic() - started >= 2.5
    finally:
        thread.join(timeout=15)
        router.close(linger=0)
        context.term()


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def rows(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        return []
    with path.open() as handle:
        return list(csv.DictReader(handle))


def wait_for_rows(path: Path, count: int, process: subprocess.Popen[str], limit_s: float) -> None:
    deadline = time.monotonic() + limit_s
    while len(rows(path)) < count:
        assert process.poll() is None, "training stopped early"
        assert time.monotonic() < deadline, f"fewer than {count} episodes in {limit_s} s"
        time.sleep(0.2)


def test_training_survives_a_server_restart_and_keeps_its_progress(tmp_path: Path) -> None:
    address = f"tcp://127.0.0.1:{free_port()}"
    out = tmp_path / "run"
    command = [
        sys.executable, "-m", "agent_client.cli.main", "train", "--server", address,
        "--out", str(out), "--episodes", "6", "--quiet", "--retry-for", "60",
        "--set", "eval_every=0", "--set", "learner.learning_starts=50", "--set", "checkpoint_every=1", "--set", "learner.compile=false",
        "--option", "length=300.0",
    ]  # fmt: skip
    with sim_server("--backend", "fake", bind=address) as first:
        trainer = subprocess.Popen(
            command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
        )
        try:
            wait_for_rows(out / "episodes.csv", 2, trainer, 120.0)
            first.process.kill()  # the simulator dies mid-run
            first.process.wait(timeout=10)
        except BaseException:
            trainer.kill()
            raise
    with sim_server("--backend", "fake", bind=address):  # and comes back on the same address
        try:
            _, stderr = trainer.communicate(timeout=180)
        finally:
            if trainer.poll() is None:
                trainer.kill()
                trainer.communicate()
    assert trainer.returncode == 0, stderr
    logged = rows(out / "episodes.csv")
    assert [int(r["episode"]) for r in logged] == list(range(1, 7))
    steps = [int(r["global_step"]) for r in logged]
    assert steps == sorted(steps) and len(set(steps)) == len(steps)
    from agent_client.rl.checkpoint import load_checkpoint

    progress = load_checkpoint(out / "checkpoint.pt")["progress"]
    assert progress["reconnects"] >= 1
    assert progress["global_step"] >= steps[-1]


# --------------------------------------------------------------------------- slow resets


@pytest.mark.slow
@pytest.mark.parametrize("scheme", ["tcp", "direct"])
def test_a_reset_slower_than_the_step_deadline_is_waited_for_by_default(scheme: str) -> None:
    """A large network's reset takes longer than a step may: the reset has its own deadline."""
    with sim_server("--backend", "fake", bind=f"{scheme}://127.0.0.1:0") as server:
        env = RemoteEnv(server.address, "cf", reward=lambda *_: 0.0)
        try:
            assert env.timeout_s == STEP_TIMEOUT_S < RESET_TIMEOUT_S == env.reset_timeout_s
            started = time.monotonic()
            _, info = env.reset(seed=1, options={"reset_seconds": STEP_TIMEOUT_S + 1.0})
            assert time.monotonic() - started > STEP_TIMEOUT_S
            assert info["observation"].seq == 0
        finally:
            env.close()


@pytest.mark.parametrize("scheme", ["tcp", "direct"])
def test_a_late_reply_names_the_live_server_and_the_deadline_to_raise(scheme: str) -> None:
    with sim_server("--backend", "fake", bind=f"{scheme}://127.0.0.1:0") as server:
        env = RemoteEnv(server.address, "cf", reward=lambda *_: 0.0, reset_timeout_s=0.5)
        try:
            with pytest.raises(ServerTimeout) as late:
                env.reset(seed=1, options={"reset_seconds": 2.0})
            message = str(late.value)
            assert f"{server.address} is up" in message and "--reset-timeout" in message
            assert "is sim-server running" not in message
            env.reset_timeout_s = 10.0
            _, info = env.reset(seed=2)  # the server goes on serving once it is done
            assert info["observation"].seq == 0
        finally:
            env.close()


def test_a_server_that_never_answered_may_be_down() -> None:
    with socket.socket() as unused:
        unused.bind(("127.0.0.1", 0))
        address = f"tcp://127.0.0.1:{unused.getsockname()[1]}"
    channel = ZmqChannel(address, timeout_s=0.3)
    try:
        with pytest.raises(ServerTimeout, match="is sim-server running and reachable"):
            channel.hello()
    finally:
        channel.close()
