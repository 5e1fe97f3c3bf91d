"""Every client wait ends within its deadline whatever a server sends, and Ctrl-C ends it at once.

Against misbehaving servers of both transports: one that drops the REQ envelope's request-id
frame, one that answers twice, one that answers late, one that answers another request's seq,
and (direct://) one silent, one that stops mid-frame and one that announces a frame over the cap.
The commands are run in subprocesses and interrupted with SIGINT once the server has seen
their first request.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from agent_client.cli.main import main
from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import InvalidReply, MalformedReply, ServerTimeout
from agent_client.transport import DirectChannel, ZmqChannel, connect
from protocol.messages import Hello, Observation, Reset, Step, Welcome
from protocol.version import PROTOCOL_VERSION
from tests.agent_client.conformance.toys import (
    AnswersAnotherSeq,
    AnswersLate,
    AnswersTwice,
    DropsRequestId,
    ToyServer,
    zero_reward,
)
from tests.agent_client.transport.servers import DirectToy, elapsed_since, wait_until

ROOT = Path(__file__).resolve().parents[3]
ACTION = {"acceleration": np.zeros(1, np.float32), "lane_change": 0}


def env_at(address: str, timeout_s: float = 1.0) -> RemoteEnv:
    return RemoteEnv(
        address, "cf", reward=zero_reward, timeout_s=timeout_s, reset_timeout_s=timeout_s
    )


# --------------------------------------------------------------------------- the request-id hang


def test_a_reply_without_the_request_id_times_out_and_says_why() -> None:
    with DropsRequestId() as server, ZmqChannel(server.address, 0.5) as channel:
        start = time.monotonic()
        with pytest.raises(ServerTimeout, match="without this request's id") as caught:
            channel.request(Hello(PROTOCOL_VERSION))
        assert elapsed_since(start) < 1.5
        assert "request-id frame" in str(caught.value)
        assert channel.discarded >= 1


@pytest.mark.parametrize(
    ("command", "status"),
    [(["drive", "--episodes", "1"], 2), (["check"], 1)],
    ids=["drive", "check"],
)
def test_commands_end_on_a_server_that_drops_the_request_id(
    command: list[str], status: int, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 14: `check --timeout 3` and `drive --timeout 3` waited forever."""
    with DropsRequestId() as server:
        start = time.monotonic()
        assert (
            main([command[0], "--server", server.address, "--timeout", "3", *command[1:]]) == status
        )
        assert elapsed_since(start) < 8.0
    out = capsys.readouterr()
    assert "request-id frame" in out.out + out.err


# --------------------------------------------------------------------------- ZeroMQ


def test_a_second_reply_is_never_taken_for_the_next_one() -> None:
    with AnswersTwice() as server:
        env = env_at(server.address)
        try:
            _, info = env.reset(seed=1)
            assert info["observation"].seq == 0
            for seq in range(1, 6):
                *_, info = env.step(ACTION)
                assert info["observation"].seq == seq
        finally:
            env.close()


def test_a_late_reply_is_dropped_and_the_retry_answered() -> None:
    with AnswersLate() as server, ZmqChannel(server.address, 0.5) as channel:
        channel.request(Hello(PROTOCOL_VERSION))
        channel.request(Reset("cf", 1))
        for seq in (1, 2):
            channel.request(Step(seq, 0.0))
        start = time.monotonic()
        with pytest.raises(ServerTimeout):
            channel.request(Step(3, 0.0))
        assert elapsed_since(start) < 1.0
        retried = channel.request(Step(3, 0.0), timeout_s=5.0)  # Lazy Pirate: ask again
        following = channel.request(Step(4, 0.0))
        assert isinstance(retried, Observation) and retried.seq == 3
        assert isinstance(following, Observation) and following.seq == 4


@pytest.mark.parametrize("toy", [AnswersAnotherSeq, "direct"], ids=["zmq", "direct"])
def test_the_reply_to_another_step_is_an_invalid_reply(toy: type[ToyServer] | str) -> None:
    server = DirectToy("another_seq") if toy == "direct" else toy()  # type: ignore[operator]
    with server:
        env = env_at(server.address)
        try:
            env.reset(seed=1)
            env.step(ACTION)
            with pytest.raises(InvalidReply) as caught:
                env.step(ACTION)
        finally:
            env.close()
    error = caught.value
    assert (error.field, error.value) == ("observation.seq", 1)
    assert "the reply to step 2" in error.rule and server.address in str(error)


# --------------------------------------------------------------------------- direct://


def test_direct_a_second_reply_is_refused_before_the_next_request() -> None:
    with DirectToy("twice") as server, DirectChannel(server.address, 1.0) as channel:
        assert isinstance(channel.request(Hello(PROTOCOL_VERSION)), Welcome)
        time.sleep(0.2)  # the second reply arrives while no request is in flight
        with pytest.raises(MalformedReply, match="while no request was in flight"):
            channel.request(Reset("cf", 1))
        assert isinstance(channel.request(Hello(PROTOCOL_VERSION)), Welcome)  # a fresh start


def test_direct_two_replies_read_at_once_are_refused() -> None:
    with (
        DirectToy("twice_at_once") as server,
        DirectChannel(server.address, 1.0) as channel,
        pytest.raises(MalformedReply, match="2 replies to one request"),
    ):
        channel.request(Hello(PROTOCOL_VERSION))


def test_direct_a_late_reply_is_not_the_answer_to_the_retry() -> None:
    with DirectToy("late") as server, DirectChannel(server.address, 0.5) as channel:
        channel.request(Hello(PROTOCOL_VERSION))
        channel.request(Reset("cf", 1))
        for seq in (1, 2):
            channel.request(Step(seq, 0.0))
        start = time.monotonic()
        with pytest.raises(ServerTimeout):
            channel.request(Step(3, 0.0))
        assert elapsed_since(start) < 1.0
        retried = channel.request(Step(3, 0.0), timeout_s=5.0)  # a fresh connection
        assert isinstance(retried, Observation) and retried.seq == 3
        following = channel.request(Step(4, 0.0))
        assert isinstance(following, Observation) and following.seq == 4


@pytest.mark.parametrize(
    ("behaviour", "error"),
    [("silent", ServerTimeout), ("partial", ServerTimeout), ("huge", MalformedReply)],
)
def test_direct_every_wait_ends_within_its_deadline(behaviour: str, error: type[Exception]) -> None:
    with DirectToy(behaviour) as server, connect(server.address, 0.5) as channel:
        start = time.monotonic()
        with pytest.raises(error):
            channel.request(Hello(PROTOCOL_VERSION))
        assert elapsed_since(start) < 1.5


# --------------------------------------------------------------------------- Ctrl-C


class Silent(ToyServer):
    """Reads every request, answers none; `received` is the tests' readiness signal."""

    def __init__(self) -> None:
        super().__init__()
        self.received = threading.Event()

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        self.received.set()
        return None


@pytest.fixture
def silent_zmq() -> Iterator[Silent]:
    with Silent() as server:
        yield server


@pytest.mark.parametrize(
    "command",
    [
        ["drive", "--episodes", "1"],
        ["check", "--reset-timeout", "600"],
        ["calibrate-idm", "--out", "never.json"],
        ["drive", "--episodes", "1", "--transport-direct"],
    ],
    ids=["drive", "check", "calibrate-idm", "drive-direct"],
)
def test_ctrl_c_ends_a_command_waiting_for_a_silent_server(
    command: list[str], silent_zmq: Silent, tmp_path: Path
) -> None:
    direct = "--transport-direct" in command
    command = [c for c in command if c != "--transport-direct"]
    with DirectToy("silent") as silent_direct:
        server = silent_direct if direct else silent_zmq
        process = subprocess.Popen(
            [sys.executable, "-m", "agent_client.cli.main", command[0], "--server",
             server.address, "--timeout", "600", *command[1:]],
            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
        )  # fmt: skip
        try:
            wait_until(server.received, 60.0)  # the command is waiting for its first reply
            start = time.monotonic()
            process.send_signal(signal.SIGINT)
            out, err = process.communicate(timeout=10)
            assert elapsed_since(start) < 3.0, err
        finally:
            if process.poll() is None:
                process.kill()
                process.wait(timeout=10)
    assert process.returncode == 130, out + err
