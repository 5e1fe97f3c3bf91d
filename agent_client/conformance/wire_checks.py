"""The checks of what travels: the transport's envelope, the welcome, and the error code of every
malformed request (docs/conformance.md)."""

from __future__ import annotations

import contextlib
import math
from typing import Any

import msgpack

from agent_client.conformance.kit import (
    CheckFailed,
    CheckWarning,
    Kit,
    ScenarioNotOffered,
    expect,
    expect_error,
)
from agent_client.conformance.probe import CLIENT_NAME, BadReply, NoReply
from agent_client.conformance.raw import REQUEST_ID, RawPeer, RawReply
from agent_client.transport.replies import (
    ReplyChecker,
    handshake_problems,
    scenario_problems,
    with_step_lengths,
)
from protocol.codec import decode_reply, encode
from protocol.errors import ErrorCode, ProtocolError
from protocol.messages import Close, Error, Hello, Reply, Welcome
from protocol.schema import Flattener
from protocol.version import PROTOCOL_VERSION, format_version

SETTLE_S = 0.3
"""How long the transport check waits for a second reply after the first."""
_MAX_OVERSIZED_FRAME = 8 * 1024 * 1024
"""Above this announced limit the frame_too_large probe is left out (ZeroMQ caps frames)."""
SHALLOW, DEEP = 32, 10_000
"""Nesting a server must accept in an unknown key, and nesting it may refuse (§2)."""


UNREACHABLE_REQ = (
    "not run: the server's replies lack the request-id frame (see transport), so a REQ client "
    "never sees them"
)


class ServerBusy(Exception):
    """The server answered `busy`: another client holds it."""


def check_transport(kit: Kit) -> str:
    """One request, one reply, envelope echoed: seen through a raw socket (§1, §7.1, §7.2)."""
    peer = RawPeer(kit.address, kit.timeout_s)
    hello = encode(Hello(PROTOCOL_VERSION, CLIENT_NAME))
    try:
        reply = peer.exchange([hello], SETTLE_S)  # NoReply: the server cannot be tested
        try:
            problems, done = _transport_problems(peer, reply)
        finally:
            with contextlib.suppress(NoReply):
                peer.exchange([encode(Close())], 0.0)  # free the server again
    finally:
        peer.close()
    if problems:
        kit.reaches_req = "request-id" not in problems[0]
        raise CheckFailed("; ".join(problems))
    return done


def _transport_problems(peer: RawPeer, reply: RawReply) -> tuple[list[str], str]:
    """What is wrong with the reply to the raw hello, and the detail if nothing is."""
    answer = _raw_answer(reply.frames, peer.direct)
    if isinstance(answer, Error) and answer.code == ErrorCode.BUSY.value:
        raise ServerBusy(answer.message)
    problems = [] if peer.direct else _envelope_problems(reply.frames)
    if reply.extra:
        unit = "bytes" if peer.direct else "message" if reply.extra == 1 else "messages"
        problems.append(
            f"{reply.extra} more {unit} after the reply to one hello: one request gets exactly "
            "one reply (§1)"
        )
    if peer.direct:
        return problems, "direct://: one frame answered one frame, nothing more"
    try:
        multipart = _multipart(peer)
    except CheckFailed as exc:
        problems.append(str(exc))
        multipart = ""
    return problems, (
        f"[request id, empty, hello] answered once with the envelope echoed; {multipart}"
    )


def _envelope_problems(frames: list[bytes]) -> list[str]:
    if frames[:-1] == [REQUEST_ID, b""]:
        return []
    if frames[:1] != [REQUEST_ID]:
        return [
            f"a hello sent as [request id, empty, hello] was answered with {len(frames)} "
            "frame(s), without the request-id frame: echo the whole envelope, every frame before "
            "the empty delimiter (protocol.md §7.1); a REQ client discards such a reply"
        ]
    return [f"the reply's envelope is {frames[:-1]!r:.80}, not [request id, empty]"]


def _raw_answer(frames: list[bytes], direct: bool) -> Reply:
    try:
        return decode_reply(frames[-1])  # type: ignore[return-value]
    except ProtocolError as exc:
        where = "the reply" if direct else "the reply's last frame"
        raise CheckFailed(f"{where} to a hello: {exc.message}") from exc


def _multipart(peer: RawPeer) -> str:
    """A request of two frames after the envelope must get decode_error (§1)."""
    hello = encode(Hello(PROTOCOL_VERSION, CLIENT_NAME))
    reply = peer.exchange([hello, hello], 0.0)
    answer = _raw_answer(reply.frames, False)
    expect_error(answer, ErrorCode.DECODE_ERROR, "a request of two frames")
    return "a two-frame request -> decode_error"


def check_handshake(kit: Kit, reply: Reply) -> str:
    """The welcome decodes and keeps every rule the client checks (§2.2, §3, §4.6)."""
    welcome = expect(reply, Welcome, "hello")
    problems = handshake_problems(welcome)
    if problems:
        raise CheckFailed("; ".join(map(str, problems)))
    offered = {s.name: s for s in welcome.scenarios}
    wanted = kit.requested_scenario or welcome.scenarios[0].name
    if wanted not in offered:
        raise ScenarioNotOffered(
            f"{kit.address} offers no scenario {wanted!r}; offered: {', '.join(offered)}"
        )
    kit.announced = welcome
    kit.welcome, kit.notes = with_step_lengths(welcome)
    kit.scenario = next(s for s in kit.welcome.scenarios if s.name == wanted)
    kit.replies = ReplyChecker(kit.welcome)
    action = welcome.action
    return (
        f"protocol {format_version(welcome.protocol)}, backend {welcome.backend} "
        f"{welcome.backend_version}, {len(offered)} scenario(s), "
        f"{len(welcome.observation_fields)} fields, "
        f"acceleration [{action.acceleration_min:g}, {action.acceleration_max:g}] m/s^2"
    )


def check_version_refusal(kit: Kit) -> str:
    """Another major version is refused naming both versions; other minors are welcome (§3)."""
    assert kit.welcome is not None
    ours = format_version(kit.welcome.protocol)
    future = (PROTOCOL_VERSION[0] + 1, 0)
    reply = kit.ask({"type": "hello", "protocol": list(future), "client": CLIENT_NAME})
    error = expect_error(reply, ErrorCode.VERSION_MISMATCH, f"hello {format_version(future)}")
    for minor in (0, 99):
        hello = {"type": "hello", "protocol": [PROTOCOL_VERSION[0], minor], "client": CLIENT_NAME}
        expect(kit.ask(hello), Welcome, f"hello {PROTOCOL_VERSION[0]}.{minor} (same major)")
    kit.hello()
    missing = [v for v in (format_version(future), ours) if v not in error.message]
    if missing:
        raise CheckWarning(
            f"version_mismatch message {error.message!r} does not name {' and '.join(missing)} "
            "as MAJOR.MINOR (§3 Handshake: it should)"
        )
    return (
        f"hello {format_version(future)} refused naming both versions; hellos 1.0 and 1.99 "
        f"welcomed (same major); hello {format_version(PROTOCOL_VERSION)} works"
    )


def check_schema(kit: Kit) -> str:
    """Every scenario's step length and well-known options; a real observation flattens (§2)."""
    assert kit.welcome is not None and kit.announced is not None
    problems = scenario_problems(kit.announced)
    if problems:
        raise CheckFailed("; ".join(map(str, problems)))
    kit.hello()
    _, obs = kit.reset(1)
    vector = Flattener(kit.welcome.observation_fields)(obs)
    names = [f.name for f in kit.welcome.observation_fields]
    bad = [name for name, v in zip(names, vector, strict=True) if not math.isfinite(v)]
    if bad:
        raise CheckFailed(f"non-finite values in the flat vector: {bad}")
    if kit.notes:
        raise CheckWarning("; ".join(kit.notes))
    total = sum(len(s.options) for s in kit.welcome.scenarios)
    return (
        f"{total} option defaults, step lengths and well-known option types valid; the first "
        f"observation keeps every rule and flattens to {len(vector)} finite values"
    )


def check_bad_requests(kit: Kit) -> str:
    """Malformed requests get their code, and the server goes on (§5)."""
    assert kit.welcome is not None and kit.scenario is not None
    limit = kit.welcome.max_frame_bytes
    step = {"type": "step", "seq": 1, "acceleration": 0.0}
    cases: list[tuple[str, bytes | dict[str, Any], ErrorCode]] = [
        ("garbage bytes", b"\xc1\xc1\xc1", ErrorCode.DECODE_ERROR),
        ("reset without scenario", {"type": "reset"}, ErrorCode.INVALID_MESSAGE),
        ("unknown type", {"type": "teleport"}, ErrorCode.UNKNOWN_TYPE),
        ("step before reset", step, ErrorCode.OUT_OF_ORDER),
    ]
    if limit <= _MAX_OVERSIZED_FRAME:
        padding = "x" * limit  # an unknown key, ignored by the receiver: only the size matters
        oversized = {"type": "hello", "protocol": list(PROTOCOL_VERSION), "padding": padding}
        cases.insert(1, (f"a frame over {limit} bytes", oversized, ErrorCode.FRAME_TOO_LARGE))
    problems = _refusals(kit, cases)
    kit.reset(40)
    for value in (math.nan, -math.inf):  # on a running episode: unambiguously the number
        frame = {**step, "acceleration": value}
        problems.extend(_refused(kit, frame, ErrorCode.INVALID_NUMBER, f"{value} acceleration"))
    try:
        kit.step(1, 0.0)
    except CheckFailed as exc:
        problems.append(f"after the refused steps: {exc}")
    if problems:
        raise CheckFailed("; ".join(problems))
    codes = sorted({code.value for _, _, code in cases} | {ErrorCode.INVALID_NUMBER.value})
    return f"{len(cases) + 2} bad requests refused ({', '.join(codes)}); served after each"


def check_error_codes(kit: Kit) -> str:
    """The codes of protocol.md §7.4's corner cases: one code fits each (§5)."""
    assert kit.scenario is not None
    scenario = kit.scenario.name
    hello = {"type": "hello", "protocol": list(PROTOCOL_VERSION), "client": CLIENT_NAME}
    option = next(iter(kit.scenario.options), "x")
    cases: list[tuple[str, bytes | dict[str, Any], ErrorCode]] = [
        ("a NaN option", {"type": "reset", "scenario": scenario, "options": {option: math.nan}},
         ErrorCode.INVALID_NUMBER),
        ("an integer map key", _packed({**hello, 7: 1}), ErrorCode.DECODE_ERROR),
        ("a client name of 4097 characters", {**hello, "client": "x" * 4097},
         ErrorCode.INVALID_MESSAGE),
        ("a type of 7", {"type": 7}, ErrorCode.INVALID_MESSAGE),
        ("a seed of -1", {"type": "reset", "scenario": scenario, "seed": -1},
         ErrorCode.INVALID_NUMBER),
    ]  # fmt: skip
    assert kit.welcome is not None
    if kit.welcome.protocol >= (1, 2):  # before 1.2 bin and ext values had no code of their own
        cases += [
            ("a bin scenario", _packed({"type": "reset", "scenario": scenario.encode()}),
             ErrorCode.DECODE_ERROR),
            ("an ext value under an unknown key",
             _packed({**hello, "x": msgpack.ExtType(1, b"!")}), ErrorCode.DECODE_ERROR),
            ("a bin map key", _packed({**hello, b"x": 1}), ErrorCode.DECODE_ERROR),
        ]  # fmt: skip
    for kind in (float, bool, str, int):
        found = kit.option_of(kind)
        if found is not None:
            name, _ = found
            wrong = "x" if kind is not str else 1
            cases += [
                (f"option {name} nil", {"type": "reset", "scenario": scenario,
                 "options": {name: None}}, ErrorCode.INVALID_OPTION),
                (f"option {name} of the wrong type", {"type": "reset", "scenario": scenario,
                 "options": {name: wrong}}, ErrorCode.INVALID_OPTION),
            ]  # fmt: skip
            break
    problems = _refusals(kit, cases)
    problems += _nesting(kit, hello)
    if problems:
        raise CheckFailed("; ".join(problems))
    codes = sorted({code.value for _, _, code in cases})
    return (
        f"{len(cases)} corner cases refused ({', '.join(codes)}); {SHALLOW} levels of nesting "
        f"accepted, {DEEP} welcomed or decode_error"
    )


def _nesting(kit: Kit, hello: dict[str, Any]) -> list[str]:
    head = _packed(hello)
    problems = []
    assert kit.welcome is not None
    for depth in (SHALLOW, DEEP):
        frame = bytes([0x80 | (len(hello) + 1)]) + head[1:] + _packed("x")
        frame += b"\x91" * depth + b"\x00"
        if len(frame) > kit.welcome.max_frame_bytes:
            continue  # frame_too_large would be right: nothing to learn about nesting
        try:
            reply = kit.ask(frame)
        except (NoReply, BadReply) as exc:
            problems.append(f"a hello with {depth} levels of nesting: {exc}")
            continue
        allowed = (Welcome,) if depth == SHALLOW else (Welcome, Error)
        if not isinstance(reply, allowed) or (
            isinstance(reply, Error) and reply.code != ErrorCode.DECODE_ERROR.value
        ):
            want = "a welcome" if depth == SHALLOW else "a welcome or decode_error"
            got = reply.code if isinstance(reply, Error) else reply.TYPE
            problems.append(f"a hello with {depth} levels of nesting: expected {want}, got {got}")
    return problems


def _packed(value: Any) -> bytes:
    return msgpack.packb(value, use_bin_type=True)


def _refusals(kit: Kit, cases: list[tuple[str, bytes | dict[str, Any], ErrorCode]]) -> list[str]:
    """Send each case after a hello; the server must refuse it and then welcome again."""
    problems: list[str] = []
    kit.hello()
    for what, frame, code in cases:
        problems.extend(_refused(kit, frame, code, what))
        try:
            kit.hello()  # after each refusal: the server still answers normally
        except (CheckFailed, NoReply, BadReply) as exc:
            problems.append(f"hello after {what}: {exc}")
            raise CheckFailed("; ".join(problems)) from exc
    return problems


def _refused(kit: Kit, frame: bytes | dict[str, Any], code: ErrorCode, what: str) -> list[str]:
    """Problems (none or one) with the refusal of one bad request."""
    try:
        expect_error(kit.ask(frame), code, what)
    except (CheckFailed, BadReply) as exc:
        return [str(exc)]
    except NoReply as exc:
        return [f"{what}: {exc}"]
    return []
