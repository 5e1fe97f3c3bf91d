"""Fuzzing live peers: hostile input gets one documented reply (server) or a clear error (client).

Server side: hypothesis draws sequences of requests (random bytes, truncated, trailing and deeply
nested msgpack, oversized and multi-part frames, wrong types, NaN/inf, extreme numbers, unknown
types, valid requests in any order with any seq) and sends them over a DEALER socket, which,
unlike REQ, would also see a second reply. A model of the session (docs/protocol.md §3) predicts
every reply; a frame that the shared codec refuses must be refused with the codec's code.
Afterwards the server serves a normal episode, is alive and its memory has not grown.

Client side: a malicious server thread answers with garbage, wrong types, NaN, huge or
multi-part frames, pickles or nothing; `ZmqChannel` and `RemoteEnv` raise `MalformedReply`,
`ServerError` or `ServerTimeout`, and never hang.
"""

from __future__ import annotations

import math
import pickle
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
import zmq
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import (
    MalformedReply,
    ServerError,
    ServerLost,
    ServerTimeout,
    ServerUnavailable,
)
from agent_client.transport import ZmqChannel
from protocol.codec import decode_reply, decode_request, encode
from protocol.errors import ErrorCode, ProtocolError
from protocol.messages import (
    Bye,
    Close,
    Error,
    Hello,
    Observation,
    OptionValue,
    Reset,
    Step,
    Welcome,
)
from protocol.schema import OBSERVATION_FIELDS, fields_for
from protocol.transport.zeromq import SOCKET_MAX_BYTES
from protocol.version import PROTOCOL_VERSION
from tests.agent_client.conformance.toys import zero_reward
from tests.conftest import RunningServer, sim_server

REPLY_TIMEOUT_MS = 10_000
DOCUMENTED_CODES = {code.value for code in ErrorCode}
EXTREME_INTS = [2**63 - 1, -(2**63), 2**64 - 1, 2**31, -1, 0]
EXTREME_FLOATS = [1e308, -1e308, 5e-324, -0.0, math.nan, math.inf, -math.inf]
RSS_GROWTH_LIMIT_KB = 50 * 1024

# --------------------------------------------------------------------------- the wire


class Wire:
    """A DEALER socket that talks like REQ but notices a missing or a second reply."""

    def __init__(self, address: str) -> None:
        self.context: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
        self.socket = self.context.socket(zmq.DEALER)
        self.socket.setsockopt(zmq.LINGER, 0)
        self.socket.connect(address)
        self.sent = 0
        self.history: deque[str] = deque(maxlen=8)

    def send(self, parts: list[bytes]) -> None:
        self.history.append(repr(parts)[:300])
        self.socket.send_multipart([b"", *parts])
        self.sent += 1

    def receive(self) -> bytes:
        assert self.socket.poll(REPLY_TIMEOUT_MS), f"no reply within {REPLY_TIMEOUT_MS} ms"
        frames = self.socket.recv_multipart()
        assert len(frames) == 2 and frames[0] == b"", f"reply is not one frame: {frames!r:.200}"
        return frames[1]

    def exchange(self, parts: list[bytes]) -> bytes:
        self.send(parts)
        try:
            reply = self.receive()
        except AssertionError as exc:
            raise AssertionError(f"{exc}; request: {parts!r:.300}") from None
        assert not self.socket.poll(0), "a second reply to one request"
        return reply

    def close(self) -> None:
        self.socket.close(linger=0)
        self.context.term()


def pack(message: dict[Any, Any]) -> bytes:
    return msgpack.packb(message, use_bin_type=True)


def drain_log(server: RunningServer) -> deque[str]:
    """Read the server's stderr in a thread and keep its tail.

    conftest's `sim_server` pipes stderr but reads it only at the end: a server that logs more
    than a pipe holds (64 kB; a hello logs the client's name) blocks in write() and stops
    answering.
    """
    tail: deque[str] = deque(maxlen=50)
    stream = server.process.stderr
    if stream is None:
        return tail

    def pump() -> None:
        try:
            for line in stream:
                tail.append(line)
        except (OSError, ValueError):  # the fixture closed the pipe
            return

    threading.Thread(target=pump, daemon=True).start()
    return tail


def rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS line")


# --------------------------------------------------------------------------- the model


@dataclass
class EpisodeModel:
    last_seq: int
    last_reply: bytes
    running: bool


UNKNOWN = EpisodeModel(-1, b"", False)
"""After a reset the backend refused: the old episode may or may not be over."""


@dataclass
class SessionModel:
    """What the server must answer next, from docs/protocol.md §3 and the shared codec."""

    welcome: Welcome
    owner: bool = False
    episode: EpisodeModel | None = None
    replies: dict[str, int] = field(default_factory=dict)

    @property
    def scenarios(self) -> dict[str, dict[str, OptionValue]]:
        return {s.name: s.options for s in self.welcome.scenarios}

    def next_seq(self) -> int:
        episode = self.episode
        return 1 if episode is None or episode is UNKNOWN else episode.last_seq + 1

    def judge(self, parts: list[bytes], data: bytes) -> None:
        reply = decode_reply(data)  # a server's reply always decodes
        self.count(reply.code if isinstance(reply, Error) else reply.TYPE)
        if isinstance(reply, Error):
            assert reply.code in DOCUMENTED_CODES, reply
            assert reply.code not in ("busy", "simulator_error", "insertion_failed"), reply
        if len(parts) != 1:
            return expect(reply, ErrorCode.DECODE_ERROR)
        try:
            request = decode_request(parts[0], self.welcome.max_frame_bytes)
        except ProtocolError as exc:
            return expect(reply, exc.code)
        if isinstance(request, Hello):
            if request.protocol[0] != PROTOCOL_VERSION[0]:
                return expect(reply, ErrorCode.VERSION_MISMATCH)
            # a client older than 1.6 is announced the flat vector of its version (§4.6)
            fields = fields_for(request.protocol)
            assert data == encode(replace(self.welcome, observation_fields=fields))
            self.owner, self.episode = True, None
        elif not self.owner:
            expect(reply, ErrorCode.OUT_OF_ORDER)
        elif isinstance(request, Close):
            assert isinstance(reply, Bye), reply
            self.owner, self.episode = False, None
        elif isinstance(request, Reset):
            self._judge_reset(request, reply, data)
        elif isinstance(request, Step):
            self._judge_step(request, reply, data)

    def _judge_reset(self, request: Reset, reply: object, data: bytes) -> None:
        refusals = set()
        options = self.scenarios.get(request.scenario)
        if options is None:
            refusals.add(ErrorCode.UNKNOWN_SCENARIO)
        elif any(not option_fits(options, k, v) for k, v in request.options.items()):
            refusals.add(ErrorCode.INVALID_OPTION)
        if request.seed is not None and not 0 <= request.seed < 2**31:
            refusals.add(ErrorCode.INVALID_NUMBER)
        if refusals:  # refused by the protocol layer: the running episode is untouched
            assert isinstance(reply, Error) and reply.code in refusals, (request, reply)
            return
        if isinstance(reply, Error):  # a value out of the simulator's range
            assert reply.code == ErrorCode.INVALID_OPTION.value, (request, reply)
            self.episode = UNKNOWN
            return
        assert isinstance(reply, Observation) and reply.seq == 0, (request, reply)
        assert not (reply.terminated or reply.truncated), reply
        self.episode = EpisodeModel(0, data, True)

    def _judge_step(self, request: Step, reply: object, data: bytes) -> None:
        episode = self.episode
        if episode is None:
            return expect(reply, ErrorCode.OUT_OF_ORDER)
        if episode is UNKNOWN:
            if isinstance(reply, Observation):
                assert reply.seq == request.seq, (request, reply)
            else:
                assert isinstance(reply, Error) and reply.code in ("out_of_order", "sequence_error", "invalid_number"), reply  # fmt: skip
            return None
        if request.seq == episode.last_seq > 0:
            assert data == episode.last_reply, "a retried step must get the cached reply"
            self.count("retried step")
            return None
        if request.seq == episode.last_seq == 0 and data == episode.last_reply:
            return None  # a retried reset: the spec allows either answer
        if not episode.running:
            return expect(reply, ErrorCode.OUT_OF_ORDER)
        if request.seq != episode.last_seq + 1:
            return expect(reply, ErrorCode.SEQUENCE_ERROR)
        if request.lane_change not in (-1, 0, 1):
            return expect(reply, ErrorCode.INVALID_NUMBER)
        assert isinstance(reply, Observation) and reply.seq == request.seq, (request, reply)
        schema = self.welcome.action
        applied = reply.action.acceleration
        assert schema.acceleration_min - 1e-9 <= applied <= schema.acceleration_max + 1e-9
        episode.last_seq, episode.last_reply = request.seq, data
        episode.running = not (reply.terminated or reply.truncated)
        if not episode.running:
            self.count(f"episode end: {reply.reason}")
        return None

    def count(self, label: str) -> None:
        self.replies[label] = self.replies.get(label, 0) + 1


def expect(reply: object, code: ErrorCode) -> None:
    assert isinstance(reply, Error), f"expected error {code.value}, got {reply}"
    assert reply.code == code.value, f"expected {code.value}, got {reply.code}: {reply.message}"


def option_fits(options: dict[str, OptionValue], name: str, value: OptionValue) -> bool:
    """Name and type of an option as the server checks them (an int is a float)."""
    if name not in options:
        return False
    default = options[name]
    if default is None:
        return True
    if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
        return True
    return type(value) is type(default)


# --------------------------------------------------------------------------- strategies

SAFE_OPTIONS: dict[str, st.SearchStrategy[OptionValue]] = {
    # Values a simulator can run quickly; absurdly large ones are a separate test below.
    "decision_interval": st.sampled_from([0.1, 0.2, 0.5, 1.0, 1, 0.0, -1.0, 0.15]),
    "max_episode_time": st.one_of(st.floats(0.1, 5.0), st.sampled_from([-1e308, 0.0, 1e308])),
    "length": st.one_of(st.floats(10.0, 1000.0), st.sampled_from([-1.0, 0.0])),
    "stop_speed": st.floats(-1e308, 5.0),
    "stop_gap": st.floats(-1.0, 50.0),
    "stop_patience": st.floats(-1.0, 5.0),
    "report_ceiling": st.booleans(),
    "warmup": st.sampled_from([0.0, 5.0, 30.0, -1.0]),
    "ego_driver": st.sampled_from(["agent", "sumo", "robot"]),
    "sigma": st.sampled_from([0.0, 0.5, 1.0, 2.0]),
}
"""Option values (including ones a server must refuse) that never take long to simulate."""

ANY_SCALAR = st.one_of(
    st.none(),
    st.booleans(),
    st.sampled_from(EXTREME_INTS),
    st.integers(-5, 5),
    st.sampled_from(EXTREME_FLOATS),
    st.floats(),
    st.text(max_size=8),
    st.binary(max_size=8),
    st.builds(msgpack.ExtType, st.integers(0, 127), st.binary(max_size=4)),
)
ANY_VALUE = st.recursive(
    ANY_SCALAR,
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=4), inner, max_size=3),
    max_leaves=6,
)  # fmt: skip


def modest(value: Any) -> bool:
    """False for a huge number a server accepts, then simulates for ages or overflows on."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return True
    if isinstance(value, int) and value >= 2**63:
        return True  # not an int64: refused by the codec
    return not (math.isfinite(value) and abs(value) > 100)  # -1e308 overflows too


OPTION_NOISE = ANY_SCALAR.filter(modest)
"""Option values of any type, but no absurdly large ones (see test_an_absurd_option_value...)."""


@st.composite
def valid_request(draw: st.DrawFn, model: SessionModel) -> dict[str, Any]:
    """A well-typed request; its values may still be wrong for the moment (seq, order...)."""
    # Mostly the next request of a normal session, so that episodes run; anything else too.
    if not model.owner:
        likely = ["hello"] * 6
    elif model.episode is None or model.episode is UNKNOWN or not model.episode.running:
        likely = ["reset"] * 6
    else:
        likely = ["step"] * 12
    kind = draw(st.sampled_from([*likely, "hello", "reset", "step", "step", "close"]))
    if kind == "hello":
        major = draw(st.sampled_from([PROTOCOL_VERSION[0]] * 4 + [0, 2, -1, 2**63 - 1]))
        minor = draw(st.sampled_from([PROTOCOL_VERSION[1], 7, -(2**63)]))
        return {"type": "hello", "protocol": [major, minor], "client": draw(st.text(max_size=20))}
    if kind == "reset":
        names = [*model.scenarios, "", "no-such-scenario", "x" * 4096]
        scenario = draw(st.sampled_from(names[:1] * 4 + names))
        offered = model.scenarios.get(scenario, {})
        known = sorted(name for name in SAFE_OPTIONS if name in offered)
        chosen = draw(st.lists(st.sampled_from(known), max_size=3, unique=True)) if known else []
        options: dict[str, Any] = {name: draw(SAFE_OPTIONS[name]) for name in chosen}
        if draw(st.integers(0, 9)) == 0:
            options[draw(st.sampled_from([*offered, "no_such_option"]))] = draw(OPTION_NOISE)
        # No `None` seed: the server draws a random one for it, which makes the episode, and so
        # Hypothesis's replay of a failing example, nondeterministic. tests/sim_server covers it.
        seed = draw(st.one_of(st.integers(0, 2**31 - 1), st.sampled_from(EXTREME_INTS)))
        return {"type": "reset", "scenario": scenario, "seed": seed, "options": options}
    if kind == "step":
        nxt = model.next_seq()
        seq = draw(
            st.one_of(
                st.just(nxt), st.just(nxt), st.just(nxt), st.just(nxt - 1),
                st.integers(nxt - 3, nxt + 3), st.sampled_from(EXTREME_INTS[:2]),
            )
        )  # fmt: skip
        acceleration = draw(
            st.one_of(
                st.floats(-10.0, 10.0),
                st.floats(allow_nan=False, allow_infinity=False),
                st.sampled_from([1000.0, -1000.0, 2**63 - 1, -(2**63), 1e308, -1e308, 3]),
            )
        )
        lane = draw(st.one_of(st.sampled_from([-1, 0, 0, 0, 1]), st.integers(-3, 3), st.sampled_from(EXTREME_INTS)))  # fmt: skip
        return {"type": "step", "seq": seq, "acceleration": acceleration, "lane_change": lane}
    return {"type": "close"}


def nested(depth: int, inner: bytes, as_map: bool) -> bytes:
    """`depth` levels of one-element arrays (or maps) around `inner`, as raw msgpack."""
    return (b"\x81\xa1k" if as_map else b"\x91") * depth + inner


Frames = list[bytes]
HostileKind = Callable[[st.DrawFn, dict[str, Any], bytes, "SessionModel"], Frames]


def _raw_bytes(
    draw: st.DrawFn, request: dict[str, Any], frame: bytes, model: SessionModel
) -> Frames:
    return [draw(st.binary(max_size=300))]


def _truncated(
    draw: st.DrawFn, request: dict[str, Any], frame: bytes, model: SessionModel
) -> Frames:
    return [frame[: draw(st.integers(0, len(frame) - 1))]]


def _trailing(
    draw: st.DrawFn, request: dict[str, Any], frame: bytes, model: SessionModel
) -> Frames:
    return [frame + draw(st.binary(min_size=1, max_size=8))]


def _nested(draw: st.DrawFn, request: dict[str, Any], frame: bytes, model: SessionModel) -> Frames:
    depth = draw(st.sampled_from([1, 10, 100, 1000, 5000, 30_000]))
    body = nested(depth, b"\x01", draw(st.booleans()))
    key = draw(st.sampled_from(["protocol", "x", "options", "acceleration"]))
    head = pack({k: v for k, v in request.items() if k != key})
    count = len(msgpack.unpackb(head)) + 1
    return [bytes([0x80 | count]) + head[1:] + pack(key) + body]


def _oversized(
    draw: st.DrawFn, request: dict[str, Any], frame: bytes, model: SessionModel
) -> Frames:
    limit = model.welcome.max_frame_bytes
    size = draw(st.sampled_from([limit + 1, limit + 1000, 2 * limit, 1024 * 1024]))
    if draw(st.booleans()):
        return [b"\xc1" * size]
    padded = pack({**request, "padding": ""})
    return [pack({**request, "padding": "x" * (size - len(padded) + 2)})]


def _wrong_type(
    draw: st.DrawFn, request: dict[str, Any], frame: bytes, model: SessionModel
) -> Frames:
    key = draw(st.sampled_from([*request, "type"]))
    return [pack({**request, key: draw(ANY_VALUE)})]


def _number(draw: st.DrawFn, request: dict[str, Any], frame: bytes, model: SessionModel) -> Frames:
    value = draw(st.sampled_from(EXTREME_INTS + EXTREME_FLOATS))
    if request["type"] == "reset":
        return [pack({**request, "seed": value})]
    if request["type"] == "hello":
        return [pack({**request, "protocol": [value, 0]})]
    key = draw(st.sampled_from(["seq", "acceleration", "lane_change"]))
    return [pack({"type": "step", "seq": 1, "acceleration": 0.0, key: value})]


def _unknown_type(
    draw: st.DrawFn, request: dict[str, Any], frame: bytes, model: SessionModel
) -> Frames:
    name = draw(st.one_of(st.text(max_size=12), st.sampled_from(["welcome", "observation", "error", "bye", "HELLO", "x" * 5000])))  # fmt: skip
    return [pack({**request, "type": name})]


def _multipart(
    draw: st.DrawFn, request: dict[str, Any], frame: bytes, model: SessionModel
) -> Frames:
    return draw(st.lists(st.binary(max_size=20), min_size=0, max_size=3).filter(lambda p: len(p) != 1))  # fmt: skip


def _odd_encoding(
    draw: st.DrawFn, request: dict[str, Any], frame: bytes, model: SessionModel
) -> Frames:
    choice = draw(st.integers(0, 2))
    if choice == 0:
        return [pack({"type": request["type"].encode(), **{k: v for k, v in request.items() if k != "type"}})]  # fmt: skip
    if choice == 1:
        return [pack({1: 2, "type": request["type"]})]
    return [pack({**request, "type": request["type"], "protocol": msgpack.ExtType(1, b"\x01")})]


HOSTILE_KINDS: dict[str, HostileKind] = {
    "bytes": _raw_bytes,
    "truncated": _truncated,
    "trailing": _trailing,
    "nested": _nested,
    "oversized": _oversized,
    "wrong_type": _wrong_type,
    "number": _number,
    "unknown_type": _unknown_type,
    "multipart": _multipart,
    "odd_encoding": _odd_encoding,
}


@st.composite
def hostile_input(draw: st.DrawFn, model: SessionModel) -> Frames:
    """The parts of one ZeroMQ message: usually one frame; the codec judges most of them."""
    kind = draw(st.sampled_from(["valid"] * 8 + list(HOSTILE_KINDS)))
    request = draw(valid_request(model))
    frame = pack(request)
    if kind == "valid":
        return [frame]
    return HOSTILE_KINDS[kind](draw, request, frame, model)


# --------------------------------------------------------------------------- server fuzz


def welcome_of(address: str) -> Welcome:
    with ZmqChannel(address, timeout_s=30.0) as connection:
        welcome = connection.hello()
        connection.request(Close())
    return welcome


def normal_episode(address: str, scenario: str) -> None:
    """Hello, reset, 20 steps, close: the server still serves a client normally."""
    with ZmqChannel(address, timeout_s=30.0) as connection:
        connection.hello()
        obs = connection.request(Reset(scenario, 5), timeout_s=120.0)
        assert isinstance(obs, Observation) and obs.seq == 0
        for seq in range(1, 21):
            obs = connection.request(Step(seq, 0.2))
            assert isinstance(obs, Observation) and obs.seq == seq
            if obs.terminated or obs.truncated:
                break
        assert isinstance(connection.request(Close()), Bye)


def flood(wire: Wire, model: SessionModel, address: str, count: int) -> None:
    """Pipelined hellos (no waiting), then a second client while the first owns the server."""
    for _ in range(count):
        wire.send([encode(Hello(PROTOCOL_VERSION))])
    replies = [wire.receive() for _ in range(count)]
    assert set(replies) == {encode(model.welcome)}
    model.owner, model.episode = True, None
    intruder = Wire(address)
    try:
        reply = decode_reply(intruder.exchange([encode(Hello(PROTOCOL_VERSION))]))
        assert isinstance(reply, Error) and reply.code == "busy", reply
    finally:
        intruder.close()
    model.judge([encode(Close())], wire.exchange([encode(Close())]))


def fuzz_server(server: RunningServer, examples: int, scenario: str) -> dict[str, Any]:
    """Run the property on a live server; return what was tried and measured."""
    log = drain_log(server)
    model = SessionModel(welcome_of(server.address))
    normal_episode(server.address, scenario)  # warm up before measuring memory
    rss_before = rss_kb(server.process.pid)
    wire = Wire(server.address)
    drawn = [0]  # inputs drawn by hypothesis (the wire also counts syncs and the flood)
    started = time.monotonic()

    @settings(
        max_examples=examples,
        derandomize=True,
        database=None,
        deadline=None,
        suppress_health_check=list(HealthCheck),
    )
    @given(data=st.data())
    def property_(data: st.DataObject) -> None:
        close = [encode(Close())]
        decode_reply(wire.exchange(close))  # a known state: no session
        model.owner, model.episode = False, None
        for _ in range(data.draw(st.integers(1, 16), label="length")):
            parts = data.draw(hostile_input(model))
            model.judge(parts, wire.exchange(parts))
            drawn[0] += 1

    try:
        property_()
        flood(wire, model, server.address, 300)
        lingering = wire.socket.poll(200)
    except BaseException:
        print("".join(["\nlast requests:\n", *(f"  {r}\n" for r in wire.history)]))
        print("".join(["server log (tail):\n", *log]))
        raise
    finally:
        wire.close()
    assert not lingering, "a reply nobody asked for"
    normal_episode(server.address, scenario)
    assert server.process.poll() is None, "the server died"
    rss_after = rss_kb(server.process.pid)
    return {
        "inputs": drawn[0],
        "requests": wire.sent,
        "seconds": time.monotonic() - started,
        "rss_before_kb": rss_before,
        "rss_after_kb": rss_after,
        "replies": dict(sorted(model.replies.items())),
    }


def report(name: str, stats: dict[str, Any]) -> None:
    print(
        f"\n{name}: {stats['inputs']} fuzzed inputs ({stats['requests']} requests in all) in "
        f"{stats['seconds']:.1f} s; "
        f"RSS {stats['rss_before_kb'] / 1024:.1f} -> {stats['rss_after_kb'] / 1024:.1f} MB; "
        f"replies {stats['replies']}"
    )


def test_fuzz_the_fake_server() -> None:
    with sim_server("--backend", "fake") as server:
        stats = fuzz_server(server, examples=450, scenario="cf")
    report("fake server", stats)
    assert stats["inputs"] >= 2000
    assert stats["rss_after_kb"] - stats["rss_before_kb"] < RSS_GROWTH_LIMIT_KB
    assert {"welcome", "observation", "bye"} <= set(stats["replies"])
    assert len(set(stats["replies"]) & DOCUMENTED_CODES) >= 8  # the fuzz reached most codes


@pytest.mark.sumo
def test_fuzz_the_sumo_server(sumo_server: RunningServer) -> None:
    stats = fuzz_server(sumo_server, examples=100, scenario="cflc")
    report("SUMO server", stats)
    assert stats["inputs"] >= 400
    assert stats["rss_after_kb"] - stats["rss_before_kb"] < RSS_GROWTH_LIMIT_KB
    assert {"welcome", "observation", "bye"} <= set(stats["replies"])


ABSURD_OPTIONS = [
    pytest.param("fake", {"decision_interval": 1e9}, id="fake-decision_interval-1e9"),
    pytest.param("fake", {"decision_interval": 1e308}, id="fake-decision_interval-1e308"),
    pytest.param("fake", {"length": 1e308, "max_episode_time": 0.1}, id="fake-length-1e308"),
    pytest.param("sumo", {"warmup": 1e7}, id="sumo-warmup-1e7", marks=pytest.mark.sumo),
]


@pytest.mark.parametrize(("backend", "options"), ABSURD_OPTIONS)
def test_an_absurd_option_value_is_refused_or_served_promptly(
    backend: str, options: dict[str, OptionValue], scenario_cache: Path
) -> None:
    with sim_server("--backend", backend, cache_dir=scenario_cache) as server:
        wire = Wire(server.address)
        try:
            wire.exchange([encode(Hello(PROTOCOL_VERSION))])
            wire.send([encode(Reset("cf", 1, options))])
            assert wire.socket.poll(5000), "no reply to the reset within 5 s"
            reply = decode_reply(wire.receive())
            if isinstance(reply, Observation):
                wire.send([encode(Step(1, 0.0))])
                assert wire.socket.poll(5000), "no reply to the first step within 5 s"
                step = decode_reply(wire.receive())
                assert isinstance(step, Observation), step  # not an internal simulator_error
            else:
                assert isinstance(reply, Error) and reply.code == "invalid_option", reply
        finally:
            wire.close()
            server.process.kill()  # ours; it may be stuck in the simulation loop


# --------------------------------------------------------------------------- client fuzz

CLIENT_TIMEOUT_S = 0.3
CLEAR_ERRORS = (MalformedReply, ServerError, ServerUnavailable)


class EvilServer:
    """A ROUTER in a thread that answers each request with the next scripted reply.

    A scripted reply is a list of frames, or None for silence. `close` always gets `bye`, so
    that clients can say goodbye quickly.
    """

    def __init__(self) -> None:
        self._context: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
        self._socket = self._context.socket(zmq.ROUTER)
        self._socket.setsockopt(zmq.LINGER, 0)
        self._socket.setsockopt(zmq.ROUTER_HANDOVER, 1)  # required of servers: docs/protocol.md
        self._socket.bind("tcp://127.0.0.1:*")
        self.address = self._socket.getsockopt_string(zmq.LAST_ENDPOINT)
        self._script: deque[list[bytes] | None] = deque()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def play(self, *replies: list[bytes] | None) -> None:
        with self._lock:
            self._script.clear()
            self._script.extend(replies)

    def _serve(self) -> None:
        while not self._stop.is_set():
            if not self._socket.poll(20):
                continue
            frames = self._socket.recv_multipart()
            envelope, body = frames[:-1], frames[-1]
            if body == encode(Close()):
                self._socket.send_multipart([*envelope, encode(Bye())])
                continue
            with self._lock:
                reply = self._script.popleft() if self._script else None
            if reply is not None:
                self._socket.send_multipart([*envelope, *reply])

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self._socket.close(linger=0)
        self._context.term()


@pytest.fixture(scope="module")
def evil() -> Iterator[EvilServer]:
    server = EvilServer()
    yield server
    server.close()


def _fake_frames() -> tuple[bytes, bytes]:
    """A correct welcome and first observation, as the evil server's templates."""
    from sim_server.backends.fake import FAKE_OPTIONS, FakeBackend

    backend = FakeBackend()
    welcome = Welcome(
        PROTOCOL_VERSION, "evil", backend.name, backend.version, backend.scenarios(),
        OBSERVATION_FIELDS, backend.action_schema, backend.sensor_range, 65536,
    )  # fmt: skip
    return encode(welcome), encode(backend.reset("cf", 1, dict(FAKE_OPTIONS)))


WELCOME, OBSERVATION_FRAME = _fake_frames()
EXECUTED: list[str] = []


def _mark_executed() -> None:
    EXECUTED.append("pickle payload ran")


class Bomb:
    """Unpickling this would run `_mark_executed`: a client must never unpickle a reply."""

    def __reduce__(self) -> tuple[Callable[[], None], tuple[()]]:
        return (_mark_executed, ())


def paths(value: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every key path of a nested msgpack value."""
    found = [prefix] if prefix else []
    if isinstance(value, dict):
        for key, item in value.items():
            found += paths(item, (*prefix, key))
    elif isinstance(value, list):
        for index, item in enumerate(value):
            found += paths(item, (*prefix, index))
    return found


def with_value(template: Any, path: tuple[Any, ...], value: Any, delete: bool = False) -> Any:
    if not path:
        return value
    copy = dict(template) if isinstance(template, dict) else list(template)
    head, rest = path[0], path[1:]
    if delete and not rest:
        del copy[head]
        return copy
    copy[head] = with_value(template[head], rest, value, delete)
    return copy


@st.composite
def evil_reply(draw: st.DrawFn, template: bytes) -> list[bytes] | None:
    """A reply frame (or frames, or silence) built to break a client."""
    wire = msgpack.unpackb(template, raw=False)
    kind = draw(
        st.sampled_from(
            ["mutate"] * 6 + ["delete", "number", "bytes", "truncated", "trailing",
             "error", "other_type", "multipart", "pickle", "silence", "ext", "same"]
        )
    )  # fmt: skip
    if kind in ("mutate", "delete", "number"):
        path = draw(st.sampled_from(paths(wire)))
        if kind == "number":
            value = draw(st.sampled_from(EXTREME_FLOATS + EXTREME_INTS))
        else:
            value = draw(ANY_VALUE)
        return [pack(with_value(wire, path, value, delete=kind == "delete"))]
    if kind == "bytes":
        return [draw(st.binary(max_size=200))]
    if kind == "truncated":
        return [template[: draw(st.integers(0, len(template) - 1))]]
    if kind == "trailing":
        return [template + draw(st.binary(min_size=1, max_size=4))]
    if kind == "error":
        return [pack({"type": "error", "code": draw(st.text(max_size=10)), "message": draw(st.text(max_size=10))})]  # fmt: skip
    if kind == "other_type":
        return [draw(st.sampled_from([encode(Bye()), WELCOME, OBSERVATION_FRAME]))]
    if kind == "multipart":
        return [template, draw(st.binary(max_size=10))]
    if kind == "pickle":
        return [pickle.dumps(Bomb())]
    if kind == "silence":
        return None
    if kind == "ext":
        return [msgpack.packb(msgpack.ExtType(draw(st.integers(0, 127)), b"\x00"))]
    return [template]


def call_client(target: str, evil: EvilServer, reply: list[bytes] | None) -> str:
    """One client call meets the evil reply: it returns or raises a clear error (the outcome)."""
    if target in ("hello", "step"):
        evil.play(reply)
        with ZmqChannel(evil.address, timeout_s=CLIENT_TIMEOUT_S) as connection:
            try:
                if target == "hello":
                    connection.hello()
                else:
                    connection.request(Step(1, 0.0))
                outcome = "returned"
            except CLEAR_ERRORS as exc:
                outcome = type(exc).__name__
            evil.play([WELCOME])
            assert isinstance(connection.hello(), Welcome)  # the connection recovered
        return outcome
    script = {"env": [reply], "env_reset": [[WELCOME], reply], "env_step": [[WELCOME], [OBSERVATION_FRAME], reply]}  # fmt: skip
    evil.play(*script[target])
    try:
        env = RemoteEnv(
            evil.address, "cf", reward=zero_reward,
            timeout_s=CLIENT_TIMEOUT_S, reset_timeout_s=CLIENT_TIMEOUT_S,
        )  # fmt: skip
    except CLEAR_ERRORS as exc:
        return type(exc).__name__
    try:
        if target != "env":
            env.reset(seed=1)
        if target == "env_step":
            env.step({"acceleration": np.zeros(1), "lane_change": 0})
        return "returned"
    except CLEAR_ERRORS as exc:
        return type(exc).__name__
    finally:
        env.close()


@pytest.mark.parametrize("target", ["hello", "step", "env", "env_reset", "env_step"])
def test_fuzz_the_client(target: str, evil: EvilServer) -> None:
    template = WELCOME if target in ("hello", "env") else OBSERVATION_FRAME
    outcomes: dict[str, int] = {}

    @settings(
        max_examples=60,
        derandomize=True,
        database=None,
        deadline=None,
        suppress_health_check=list(HealthCheck),
    )
    @given(reply=evil_reply(template))
    def property_(reply: list[bytes] | None) -> None:
        if target == "env" and reply is not None and is_schema_fault(reply):
            return  # a fair UsageError: the user's scenario "cf" is not offered
        if reply is not None and len(reply) > 1:
            return  # a known bug: test_a_multipart_reply_is_malformed
        outcome = call_client(target, evil, reply)
        outcomes[outcome] = outcomes.get(outcome, 0) + 1

    property_()
    print(f"\nclient {target}: {outcomes}")
    assert not EXECUTED
    assert len(outcomes) >= 2


def is_schema_fault(reply: list[bytes]) -> bool:
    """A well-formed welcome without the scenario "cf": RemoteEnv refuses the user's choice
    with a `UsageError` (a welcome that breaks a rule is an `InvalidReply`, a MalformedReply)."""
    try:
        welcome = decode_reply(reply[0])
    except ProtocolError:
        return False
    return isinstance(welcome, Welcome) and not any(s.name == "cf" for s in welcome.scenarios)


def test_a_pickle_reply_is_never_executed(evil: EvilServer) -> None:
    evil.play([pickle.dumps(Bomb())])
    with (
        ZmqChannel(evil.address, timeout_s=CLIENT_TIMEOUT_S) as connection,
        pytest.raises(MalformedReply, match="not valid msgpack"),
    ):
        connection.hello()
    assert not EXECUTED


def test_a_reply_over_the_socket_cap_is_a_lost_connection_not_a_crash(evil: EvilServer) -> None:
    evil.play([b"\x00" * (SOCKET_MAX_BYTES + 1)], [b"\x00" * (1024 * 1024 + 1)])
    with ZmqChannel(evil.address, timeout_s=10.0) as connection:
        with pytest.raises(ServerLost):
            connection.hello()  # ZeroMQ drops the frame and the connection
        with pytest.raises(MalformedReply, match="exceeds the limit"):
            connection.hello()


def test_a_multipart_reply_is_malformed(evil: EvilServer) -> None:
    evil.play([WELCOME, b"extra"], [WELCOME])
    with ZmqChannel(evil.address, timeout_s=CLIENT_TIMEOUT_S) as connection:
        with pytest.raises(MalformedReply):
            connection.hello()
        assert isinstance(connection.hello(), Welcome)


@pytest.mark.parametrize("fault", ["unknown_field", "bounds"])
def test_remote_env_refuses_a_bad_schema_with_malformed_reply(
    evil: EvilServer, fault: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    wire = msgpack.unpackb(WELCOME, raw=False)
    if fault == "unknown_field":
        wire["observation_fields"][0]["name"] = "warp_factor"
    else:
        wire["action"]["acceleration_min"], wire["action"]["acceleration_max"] = 3.0, -6.0
    evil.play([pack(wire)])
    connections: list[ZmqChannel] = []

    class Tracked(ZmqChannel):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            connections.append(self)

    monkeypatch.setattr("agent_client.transport.ZmqChannel", Tracked)  # what connect() builds
    try:
        with pytest.raises(MalformedReply):
            RemoteEnv(evil.address, "cf", reward=zero_reward, timeout_s=CLIENT_TIMEOUT_S)
    finally:
        for connection in connections:  # what RemoteEnv leaks when it raises ValueError
            if not connection._context.closed:
                connection.close()


def test_a_client_that_missed_a_reply_can_retry_its_step() -> None:
    with sim_server("--backend", "fake") as server, ZmqChannel(server.address, 5.0) as connection:
        connection.hello()
        connection.request(Reset("cf", 1, {"decision_interval": 1.0}))
        with pytest.raises(ServerTimeout):
            connection.request(Step(1, 0.0), timeout_s=0.0)  # its reply is "lost"
        retried = connection.request(Step(1, 0.0))  # Lazy Pirate: ask again
        assert isinstance(retried, Observation) and retried.seq == 1
        # The late reply to the first attempt must not be taken for the answer to step 2.
        following = connection.request(Step(2, 0.0))
        assert isinstance(following, Observation) and following.seq == 2
        assert following.time > retried.time


def test_a_fresh_socket_of_the_same_client_keeps_the_session() -> None:
    with sim_server("--backend", "fake") as server, ZmqChannel(server.address, 5.0) as connection:
        connection.hello()
        connection.request(Reset("cf", 1))
        first = connection.request(Step(1, 0.0))
        connection._drop_socket()  # what a malformed reply or a lost connection leads to
        again = connection.request(Step(1, 0.0))  # same routing id: the cached reply
        assert isinstance(again, Observation) and isinstance(first, Observation)
        assert again.time == first.time
