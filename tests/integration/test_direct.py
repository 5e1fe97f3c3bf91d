"""The direct transport over real processes: same stream as ZeroMQ, faults, hostile bytes."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from agent_client.conformance.checks import PASS, run_checks
from agent_client.drivers.idm import IDMDriver
from agent_client.errors import ServerError, ServerLost, ServerTimeout
from agent_client.transport import connect
from agent_client.transport.direct import DirectChannel
from protocol.codec import decode_reply, encode
from protocol.messages import Close, Error, Hello, Observation, Reset, Step, Welcome
from protocol.transport.direct import LENGTH, frame, preamble
from protocol.version import PROTOCOL_VERSION
from tests.agent_client.conformance.test_checks import CHECKS
from tests.conftest import sim_server

DIRECT = "direct://127.0.0.1:0"


def drive(address: str, scenario: str, seed: int, steps: int) -> list[bytes]:
    """IDM with a lane change now and then; the observations' wire bytes."""
    with connect(address, timeout_s=60.0) as connection:
        connection.hello()
        obs = connection.request(Reset(scenario, seed), timeout_s=120.0)
        assert isinstance(obs, Observation)
        stream, driver = [encode(obs)], IDMDriver()
        for seq in range(1, steps + 1):
            change = (1 if obs.ego.lane == 0 else -1) if seq % 41 == 7 else 0
            obs = connection.request(Step(seq, driver.act(obs)[0], change))
            assert isinstance(obs, Observation)
            stream.append(encode(obs))
            if obs.terminated or obs.truncated:
                break
    return stream


@pytest.mark.sumo
def test_direct_and_zeromq_carry_the_same_stream(scenario_cache: Path) -> None:
    with (
        sim_server("--backend", "sumo", cache_dir=scenario_cache, bind=DIRECT) as direct,
        sim_server("--backend", "sumo", cache_dir=scenario_cache) as zeromq,
    ):
        assert direct.address.startswith("direct://127.0.0.1:")
        for scenario, seed in (("cf", 3), ("cflc", 5)):
            assert drive(direct.address, scenario, seed, 300) == drive(
                zeromq.address, scenario, seed, 300
            )


@pytest.mark.sumo
def test_the_sumo_server_conforms_over_direct(scenario_cache: Path) -> None:
    with sim_server("--backend", "sumo", cache_dir=scenario_cache, bind=DIRECT) as server:
        report = run_checks(server.address, "cflc", timeout_s=30.0)
        assert {r.name: r.status for r in report.results} == dict.fromkeys(CHECKS, PASS), (
            report.format_table()
        )


def owner_with_an_episode(address: str) -> DirectChannel:
    """A client that said hello and reset `cf`: the simulator's owner."""
    owner = DirectChannel(address, timeout_s=10.0)
    owner.hello()
    owner.request(Reset("cf", 1))
    return owner


def test_a_lost_reply_is_retried_on_a_fresh_connection_without_advancing_twice() -> None:
    with sim_server("--backend", "fake", bind=DIRECT) as server:
        channel = DirectChannel(server.address, timeout_s=10.0)
        channel.hello()
        channel.request(Reset("cf", 1))
        first = channel.request(Step(1, 0.5))
        channel.send(Step(2, 0.5))
        channel.drop()  # the reply to step 2 is lost with the connection
        again = channel.request(Step(2, 0.5))  # Lazy Pirate: same routing id, fresh socket
        assert isinstance(first, Observation) and isinstance(again, Observation)
        assert again.seq == 2
        assert again.time == pytest.approx(first.time + 0.1)  # step 2 ran once, not twice
        assert channel.request(Step(2, 0.5)) == again  # answered from the cache
        third = channel.request(Step(3, 0.5))
        assert isinstance(third, Observation)
        assert third.time == pytest.approx(first.time + 2 * 0.1)  # advanced once per step
        channel.close()


def hello_when_free(channel: DirectChannel, within_s: float) -> float:
    """Say hello until it is not `busy`; the seconds it took."""
    started = time.monotonic()
    while True:
        try:
            channel.hello()
            return time.monotonic() - started
        except ServerError as exc:
            if exc.code != "busy" or time.monotonic() - started > within_s:
                raise
            time.sleep(0.01)


def test_a_second_client_is_busy_and_takes_over_once_the_first_is_gone() -> None:
    with sim_server("--backend", "fake", bind=DIRECT) as server:
        owner = owner_with_an_episode(server.address)
        other = DirectChannel(server.address, timeout_s=10.0)
        with pytest.raises(ServerError) as refused:
            other.hello()
        assert refused.value.code == "busy"
        owner.close()  # its connection closes: the simulator is free at once
        assert hello_when_free(other, 5.0) < 1.0
        other.close()


def test_a_reconnecting_owner_replaces_its_open_connection_and_keeps_the_simulator() -> None:
    with sim_server("--backend", "fake", bind=DIRECT) as server:
        owner = owner_with_an_episode(server.address)
        step_1 = owner.request(Step(1, 0.5))
        old_socket = owner._sock
        assert old_socket is not None
        again = DirectChannel(server.address, timeout_s=10.0)
        again.routing_id = owner.routing_id  # the same client on a fresh connection
        assert again.request(Step(1, 0.5)) == step_1  # the cached reply: the step did not repeat
        old_socket.settimeout(5.0)
        assert old_socket.recv(1) == b""  # the server closed the replaced connection
        with DirectChannel(server.address, timeout_s=10.0) as stranger:
            with pytest.raises(ServerError) as refused:
                stranger.hello()
            assert refused.value.code == "busy"  # the handover did not free the simulator
        assert isinstance(again.request(Step(2, 0.5)), Observation)
        owner.close()
        again.close()


def test_a_closing_stranger_does_not_free_the_owners_simulator() -> None:
    with sim_server("--backend", "fake", bind=DIRECT) as server:
        owner = owner_with_an_episode(server.address)
        with (
            DirectChannel(server.address, timeout_s=10.0) as stranger,
            pytest.raises(ServerError),
        ):
            stranger.hello()
        with DirectChannel(server.address, timeout_s=10.0) as third:
            with pytest.raises(ServerError) as refused:
                third.hello()
            assert refused.value.code == "busy"
        assert isinstance(owner.request(Step(1, 0.0)), Observation)
        owner.close()


def read_until_closed(sock: socket.socket) -> int:
    """Bytes received until the peer closes (EOF or reset); a timeout fails the test."""
    total = 0
    try:
        while chunk := sock.recv(1 << 16):
            total += len(chunk)
    except ConnectionResetError:
        pass
    return total


def test_a_client_that_never_reads_cannot_stall_the_owner() -> None:
    with sim_server("--backend", "fake", bind=DIRECT) as server:
        owner = owner_with_an_episode(server.address)
        host, port = server.address.removeprefix("direct://").rsplit(":", 1)
        flood = frame(encode(Hello(PROTOCOL_VERSION, "flood"))) * 3000  # ~3000 replies queued
        with socket.create_connection((host, int(port)), timeout=5.0) as greedy:
            greedy.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            greedy.sendall(preamble(b"greedy") + flood)
            slowest = 0.0
            for seq in range(1, 201):
                started = time.monotonic()
                assert isinstance(owner.request(Step(seq, 0.0), timeout_s=5.0), Observation)
                slowest = max(slowest, time.monotonic() - started)
            assert slowest < 1.0
        owner.close()
        assert server.process.poll() is None


def test_unread_replies_beyond_the_cap_close_that_connection() -> None:
    with sim_server("--backend", "fake", bind=DIRECT) as server:
        with DirectChannel(server.address, timeout_s=10.0) as first:
            welcome_bytes = len(frame(encode(first.hello())))
            first.request(Close())
        assert 3000 * welcome_bytes > 2 * 1024 * 1024
        host, port = server.address.removeprefix("direct://").rsplit(":", 1)
        flood = frame(encode(Hello(PROTOCOL_VERSION, "flood"))) * 3000
        with socket.create_connection((host, int(port)), timeout=10.0) as greedy:
            greedy.sendall(preamble(b"greedy") + flood)
            assert read_until_closed(greedy) < 3000 * welcome_bytes  # cut off, not all answered
        with DirectChannel(server.address, timeout_s=10.0) as channel:
            assert hello_when_free(channel, 5.0) < 1.0  # the greedy client's session is gone


def test_silent_connections_cannot_lock_the_owner_out() -> None:
    with sim_server("--backend", "fake", bind=DIRECT) as server:
        owner = owner_with_an_episode(server.address)
        host, port = server.address.removeprefix("direct://").rsplit(":", 1)
        idle = [socket.create_connection((host, int(port)), timeout=5.0) for _ in range(80)]
        try:
            for seq in range(1, 4):
                assert isinstance(owner.request(Step(seq, 0.0)), Observation)
            owner.drop()  # Lazy Pirate reconnect while the server is full of idle sockets
            assert isinstance(owner.request(Step(4, 0.0)), Observation)
            nameless = idle[-1]  # a connection that never sent its preamble is closed in ~5 s
            nameless.settimeout(10.0)
            started = time.monotonic()
            assert read_until_closed(nameless) == 0
            assert time.monotonic() - started < 9.0
        finally:
            for sock in idle:
                sock.close()
        owner.close()


def test_a_request_waits_for_a_server_that_is_still_starting(tmp_path: Path) -> None:
    probe = socket.socket()
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    channel = DirectChannel(f"direct://127.0.0.1:{port}", timeout_s=30.0)
    channel.send(Hello(PROTOCOL_VERSION, "early"))  # nobody listens yet: kept for later
    with sim_server("--backend", "fake", bind=f"direct://127.0.0.1:{port}"):
        assert isinstance(channel.receive(), Welcome)
    channel.close()
    lonely = DirectChannel(f"direct://127.0.0.1:{port}", timeout_s=0.3)
    with pytest.raises(ServerTimeout, match="cannot connect"):
        lonely.hello()


def test_both_ends_refuse_non_loopback_addresses() -> None:
    from sim_server.backends.fake import FakeBackend
    from sim_server.serve.direct import DirectServer
    from sim_server.session import Session

    session = Session(FakeBackend())
    with pytest.raises(ValueError, match="loopback"):
        DirectServer(session, "direct://0.0.0.0:0")
    with pytest.raises(ValueError, match="one machine only"):
        DirectChannel("direct://192.0.2.1:5556")


def test_a_killed_server_is_reported_at_once(tmp_path: Path) -> None:
    with sim_server("--backend", "fake", bind=DIRECT) as server:
        channel = DirectChannel(server.address, timeout_s=30.0)
        channel.hello()
        channel.request(Reset("cf", 1))
        channel.send(Step(1, 0.0))
        channel.receive()
        server.process.send_signal(signal.SIGKILL)
        server.process.wait(timeout=10)
        started = time.monotonic()
        with pytest.raises((ServerLost, ServerTimeout)):
            channel.request(Step(2, 0.0))
        assert time.monotonic() - started < 5.0  # not the 30 s deadline
        channel.close()


def test_a_frozen_server_times_out_within_the_deadline() -> None:
    with sim_server("--backend", "fake", bind=DIRECT) as server:
        channel = DirectChannel(server.address, timeout_s=10.0)
        channel.hello()
        os.kill(server.process.pid, signal.SIGSTOP)
        try:
            started = time.monotonic()
            with pytest.raises(ServerTimeout):
                channel.request(Reset("cf", 1), timeout_s=1.0)
            assert time.monotonic() - started < 3.0
        finally:
            os.kill(server.process.pid, signal.SIGCONT)
        channel.close()


def test_hostile_bytes_close_that_connection_and_the_server_goes_on() -> None:
    with sim_server("--backend", "fake", bind=DIRECT) as server:
        host, port = server.address.removeprefix("direct://").rsplit(":", 1)
        attacks = [
            b"GET / HTTP/1.1\r\nHost: x\r\n\r\n",  # not our preamble
            preamble(b"evil") + LENGTH.pack(1 << 30),  # a 1 GiB frame announced
            preamble(b"evil") + frame(b"\xc1\xff\x00garbage"),  # answered with an error
            os.urandom(4096),
        ]
        answers = []
        for attack in attacks:
            with socket.create_connection((host, int(port)), timeout=5.0) as raw:
                raw.sendall(attack)
                raw.shutdown(socket.SHUT_WR)
                answer = b""
                while chunk := raw.recv(65536):  # the server closes: EOF, not a hang
                    answer += chunk
                answers.append(answer)
        assert answers[0] == answers[1] == answers[3] == b""  # dropped without a word
        (size,) = LENGTH.unpack_from(answers[2])
        error = decode_reply(answers[2][LENGTH.size :])
        assert size == len(answers[2]) - LENGTH.size
        assert isinstance(error, Error) and error.code == "decode_error"
        with DirectChannel(server.address, timeout_s=10.0) as channel:
            assert isinstance(channel.hello(), Welcome)
            assert isinstance(channel.request(Reset("cf", 2)), Observation)
        assert server.process.poll() is None


def test_the_error_reply_to_garbage_is_a_protocol_error() -> None:
    with (
        sim_server("--backend", "fake", bind=DIRECT) as server,
        DirectChannel(server.address, timeout_s=10.0) as channel,
    ):
        reply = channel.exchange_raw(b"\xc1")
        assert reply.TYPE == "error"
        assert channel.request(Hello(PROTOCOL_VERSION, "after-garbage")).TYPE == "welcome"


@pytest.mark.parametrize(
    ("arguments", "complaint"),
    [
        (["--bind", "direct://0.0.0.0:0"], "loopback addresses only"),
        (["--bind", "tcp://127.0.0.1:0", "--spin-us", "10"], "direct:// addresses only"),
    ],
)
def test_direct_usage_errors(arguments: list[str], complaint: str) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "sim_server.cli", "--backend", "fake", *arguments],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert result.returncode == 2
    assert complaint in result.stderr


def test_keys_are_refused_for_direct() -> None:
    from protocol.transport.security import ClientCredentials

    fake_keys = ClientCredentials.__new__(ClientCredentials)
    with pytest.raises(ValueError, match="no CURVE"):
        connect("direct://127.0.0.1:1", credentials=fake_keys)


@pytest.mark.sumo
def test_agent_client_drives_over_direct(scenario_cache: Path) -> None:
    with sim_server("--backend", "sumo", cache_dir=scenario_cache, bind=DIRECT) as server:
        result = subprocess.run(
            [sys.executable, "-m", "agent_client.cli.main", "drive", "--server", server.address,
             "--scenario", "cflc", "--policy", "idm", "--episodes", "1", "--seed", "2", "--json"],
            capture_output=True, text=True, timeout=300, check=False,
        )  # fmt: skip
    assert result.returncode == 0, result.stderr
    (episode,) = [json.loads(line) for line in result.stdout.splitlines()]
    assert episode["collisions"] == 0
    assert episode["reason"] == "end_of_road"
