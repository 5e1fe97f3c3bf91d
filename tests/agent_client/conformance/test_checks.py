"""The conformance kit against in-process servers: a correct one passes, each broken one fails.

The servers are our `Session` with the fake backend behind a ZeroMQ ROUTER in a thread; each
broken variant rewrites frames to break exactly one rule of docs/protocol.md.
"""

from __future__ import annotations

import json
import math
import threading
from collections.abc import Iterator
from dataclasses import replace
from typing import Any

import msgpack
import pytest
import zmq

from agent_client.cli.main import main
from agent_client.conformance import FAIL, PASS, WARN, ConformanceReport, run_checks
from protocol.codec import decode_reply, decode_request, encode
from protocol.errors import ProtocolError
from protocol.messages import Close, Hello, Message, Observation, Reset, Step
from protocol.transport.zeromq import bind_router, connect_req
from protocol.version import PROTOCOL_VERSION
from sim_server.backends.fake import FakeBackend
from sim_server.session import Session

CHECKS = [
    "handshake", "version_refusal", "schema", "reset", "step", "reconnect", "termination",
    "bad_requests", "determinism", "close",
]  # fmt: skip


class ToyServer:
    """A conforming server in a thread; subclasses override `answer` to break one rule."""

    def __init__(self) -> None:
        self.session = Session(FakeBackend())
        self._context: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
        self._socket, endpoint = bind_router(self._context, "tcp://127.0.0.1:0")
        self.address = str(endpoint)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        """The reply frame, or None to stay silent."""
        return self.session.handle(peer, frame)

    def _serve(self) -> None:
        while not self._stop.is_set():
            if not self._socket.poll(20):
                continue
            frames = self._socket.recv_multipart()
            reply = self.answer(frames[0], frames[-1])
            if reply is not None:
                self._socket.send_multipart([*frames[:-1], reply])

    def __enter__(self) -> ToyServer:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self._socket.close(linger=0)
        self._context.term()


def request_of(frame: bytes) -> Message | None:
    try:
        return decode_request(frame)
    except ProtocolError:
        return None


def rewrite_observation(reply: bytes, **changes: Any) -> bytes:
    obs = decode_reply(reply)
    return encode(replace(obs, **changes)) if isinstance(obs, Observation) else reply


class NoRetryCache(ToyServer):
    """A retried step advances the simulation instead of replaying the cached reply."""

    def __init__(self) -> None:
        super().__init__()
        self.offset = self.last_seq = 0

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        request = request_of(frame)
        if isinstance(request, Hello | Reset):
            self.offset = self.last_seq = 0
        if not isinstance(request, Step):
            return super().answer(peer, frame)
        if request.seq == self.last_seq > 0:
            self.offset += 1
        reply = self.session.handle(peer, encode(replace(request, seq=request.seq + self.offset)))
        if isinstance(decode_reply(reply), Observation):
            self.last_seq = request.seq
        return rewrite_observation(reply, seq=request.seq)


class NaNSpeed(ToyServer):
    """Observations carry a NaN ego speed."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        reply = self.session.handle(peer, frame)
        wire = msgpack.unpackb(reply, raw=False)
        if wire["type"] != "observation":
            return reply
        wire["ego"]["speed"] = math.nan
        return msgpack.packb(wire, use_bin_type=True)


class WrongSeq(ToyServer):
    """Step replies carry the next seq instead of the step's own."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        reply = self.session.handle(peer, frame)
        request = request_of(frame)
        if isinstance(request, Step):
            return rewrite_observation(reply, seq=request.seq + 1)
        return reply


class IgnoresSeed(ToyServer):
    """Every reset runs with seed 0: deterministic, but the seed makes no difference."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        request = request_of(frame)
        if isinstance(request, Reset) and request.seed is not None and 0 <= request.seed < 2**31:
            frame = encode(replace(request, seed=0))
        return self.session.handle(peer, frame)


class WrongErrorCode(ToyServer):
    """Reports invalid_number as invalid_message."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        reply = self.session.handle(peer, frame)
        return reply.replace(b"invalid_number", b"invalid_message")


class NoVersionCheck(ToyServer):
    """Welcomes any protocol version."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        if isinstance(request_of(frame), Hello):
            frame = encode(Hello(PROTOCOL_VERSION))
        return self.session.handle(peer, frame)


class SilentOnGarbage(ToyServer):
    """Never answers a frame that is not msgpack."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        try:
            msgpack.unpackb(frame)
        except ValueError:
            return None
        return self.session.handle(peer, frame)


class UnclippedAcceleration(ToyServer):
    """Reports the requested acceleration as applied, far beyond the announced bounds."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        reply = self.session.handle(peer, frame)
        obs = decode_reply(reply)
        if not isinstance(obs, Observation):
            return reply
        action = replace(obs.action, acceleration=obs.action.requested_acceleration)
        return encode(replace(obs, action=action))


def statuses(report: ConformanceReport) -> dict[str, str]:
    return {result.name: result.status for result in report.results}


@pytest.fixture
def toy() -> Iterator[ToyServer]:
    with ToyServer() as server:
        yield server


def test_a_conforming_server_passes_every_check(toy: ToyServer) -> None:
    report = run_checks(toy.address, timeout_s=5.0)
    assert [r.name for r in report.results] == CHECKS
    assert statuses(report) == dict.fromkeys(CHECKS, PASS), report.format_table()
    assert report.exit_code == 0
    assert toy.session.owner is None  # the kit left the server free


def test_cli_prints_json_and_exits_0(toy: ToyServer, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", "--server", toy.address, "--json", "--timeout", "5"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["ok"] is True
    assert report["scenario"] == "cf"
    assert [c["name"] for c in report["checks"]] == CHECKS
    assert all(c["detail"] for c in report["checks"])


def test_cli_prints_a_table(toy: ToyServer, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", "--server", toy.address, "--scenario", "cf"]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0].split() == ["check", "result", "detail"]
    assert "CONFORMS - 10 passed, 0 warnings, 0 failed" in out


@pytest.mark.parametrize(
    ("server_class", "failing"),
    [
        (NoRetryCache, "step"),
        (NaNSpeed, "schema"),
        (WrongSeq, "step"),
        (WrongErrorCode, "bad_requests"),
        (NoVersionCheck, "version_refusal"),
        (SilentOnGarbage, "bad_requests"),
        (UnclippedAcceleration, "step"),
    ],
)
def test_a_broken_server_fails_its_check_and_exit_1(
    server_class: type[ToyServer], failing: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with server_class() as server:
        report = run_checks(server.address, timeout_s=1.0)
    assert statuses(report)[failing] == FAIL, report.format_table()
    assert report.exit_code == 1
    with server_class() as server:
        assert main(["check", "--server", server.address, "--timeout", "1"]) == 1
    assert any(line.split()[:2] == [failing, FAIL] for line in capsys.readouterr().out.splitlines())


def test_details_name_the_fault() -> None:
    with NoRetryCache() as server:
        detail = {r.name: r.detail for r in run_checks(server.address, timeout_s=2.0).results}
    assert "retry" in detail["step"]
    with SilentOnGarbage() as server:
        detail = {r.name: r.detail for r in run_checks(server.address, timeout_s=0.5).results}
    assert detail["bad_requests"].startswith("garbage bytes: no reply from")
    assert "within 0.5 s" in detail["bad_requests"]


def test_a_server_that_ignores_seeds_gets_a_warning_not_a_failure() -> None:
    with IgnoresSeed() as server:
        report = run_checks(server.address, timeout_s=5.0)
    assert statuses(report)["determinism"] == WARN
    assert "seeds seem ignored" in report.results[CHECKS.index("determinism")].detail
    assert report.exit_code == 0


def test_unreachable_server_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", "--server", "tcp://127.0.0.1:1", "--timeout", "0.5"]) == 2
    assert "no reply from tcp://127.0.0.1:1 within 0.5 s" in capsys.readouterr().err
    assert main(["check", "--server", "tcp://127.0.0.1:1", "--timeout", "0.5", "--json"]) == 2
    assert json.loads(capsys.readouterr().out)["ok"] is False


def test_busy_server_and_bad_arguments_exit_2(
    toy: ToyServer, capsys: pytest.CaptureFixture[str]
) -> None:
    context: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
    other = connect_req(context, toy.address)
    try:
        for message in (Hello(PROTOCOL_VERSION), None, Close()):
            if message is None:
                assert main(["check", "--server", toy.address, "--timeout", "2"]) == 2
                assert "busy with another client" in capsys.readouterr().err
                continue
            other.send(encode(message))
            assert other.poll(5000)
            other.recv()
    finally:
        other.close(linger=0)
        context.term()
    assert main(["check", "--server", "localhost:5555"]) == 2
    assert "expected tcp://HOST:PORT" in capsys.readouterr().err
    assert main(["check", "--server", toy.address, "--scenario", "nowhere"]) == 2
    assert "offers no scenario 'nowhere'; offered: cf" in capsys.readouterr().err
    assert toy.session.owner is None
