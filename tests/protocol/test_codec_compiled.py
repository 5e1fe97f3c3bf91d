"""The encoder, the compiled decoders and the fast path against the generic reference.

`encode` must write the same bytes as the generic dataclass walk (`codec._wire_map`), and the
compiled decoders must accept, convert and refuse exactly what the generic converter did, with
the same error code and message: a reference decoder written the generic way is the oracle here.
The fast path (msgspec) must give every frame the verdict of the precise path.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import math
import types
import typing
from collections.abc import Iterator
from enum import IntEnum
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from protocol import codec
from protocol.codec import decode_reply, decode_request, encode
from protocol.errors import ProtocolError
from protocol.messages import (
    REPLY_TYPES,
    REQUEST_TYPES,
    AppliedAction,
    Bye,
    Close,
    Ego,
    Error,
    Events,
    Hello,
    LaneChange,
    LeaderTrip,
    MultiObservation,
    MultiStep,
    Neighbour,
    Neighbours,
    Observation,
    Reset,
    Step,
    Welcome,
)
from tests.protocol.test_codec import REPLIES, REQUESTS

# --------------------------------------------------------------------------- the reference


def reference_converter(hint: Any) -> codec.Converter:
    """The generic converter (field by field, kwargs, the class's own __init__)."""
    scalars: dict[Any, codec.Converter] = {
        float: codec._as_float,
        int: codec._as_int,
        bool: codec._as_bool,
        str: codec._as_str,
        type(None): codec._as_none,
    }
    if hint in scalars:
        return scalars[hint]
    if dataclasses.is_dataclass(hint):
        return reference_dataclass(typing.cast(type, hint))
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        names = " or ".join(getattr(a, "__name__", str(a)) for a in args)
        return codec._union([reference_converter(a) for a in args], names)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return codec._tuple(reference_converter(args[0]), None)
        items = [reference_converter(a) for a in args]

        def fixed(value: Any, path: str) -> tuple[Any, ...]:
            values = codec._tuple(codec._scalar, len(items))(value, path)
            return tuple(
                c(v, f"{path}[{i}]") for i, (c, v) in enumerate(zip(items, values, strict=True))
            )

        return fixed
    if origin is dict:
        if typing.get_origin(args[1]) in (typing.Union, types.UnionType):
            return codec._mapping(codec._scalar)
        return codec._mapping(reference_converter(args[1]))
    raise TypeError(hint)


def reference_dataclass(cls: type) -> codec.Converter:
    hints = typing.get_type_hints(cls)
    fields = [
        (
            f.name,
            f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING,
            reference_converter(hints[f.name]),
        )
        for f in dataclasses.fields(cls)
    ]

    def convert(value: Any, path: str) -> Any:
        if not isinstance(value, dict):
            raise codec._invalid(path, "a map", value)
        kwargs = {}
        for name, has_default, field_converter in fields:
            if name in value:
                kwargs[name] = field_converter(value[name], f"{path}.{name}")
            elif not has_default:
                raise ProtocolError(
                    codec.ErrorCode.INVALID_MESSAGE, f"{path}: missing field {name!r}"
                )
        return cls(**kwargs)

    return convert


def outcome(convert: codec.Converter, raw: Any, path: str) -> tuple[str, Any]:
    """The verdict: the value (its repr too, so that 1 and 1.0 differ) or the error."""
    try:
        value = convert(raw, path)
    except ProtocolError as exc:
        return "error", (exc.code, exc.message)
    return "ok", (value, repr(value))


# --------------------------------------------------------------------------- strategies

finite = st.floats(allow_nan=False, allow_infinity=False)
text = st.text(max_size=12)


@st.composite
def neighbours(draw: st.DrawFn) -> Neighbour:
    return Neighbour(draw(st.booleans()), draw(finite), draw(finite), draw(finite), draw(text))


@st.composite
def observations(draw: st.DrawFn) -> Observation:
    six = [draw(neighbours()) for _ in range(6)]
    ceiling = draw(
        st.none() | st.builds(LeaderTrip, text, finite, st.none() | finite, st.none() | finite)
    )
    return Observation(
        seq=draw(st.integers(0, 2**63 - 1)),
        time=draw(finite),
        ego=Ego(draw(finite), draw(finite), draw(st.integers(0, 5)), 3, draw(finite), 22.2),
        neighbours=Neighbours(*six),
        events=Events(*(draw(st.booleans()) if i != 1 else draw(text) for i in range(7))),
        action=AppliedAction(
            draw(finite), draw(st.sampled_from([-1, 0, 1])), draw(finite), 0, draw(text), ""
        ),
        terminated=draw(st.booleans()),
        truncated=draw(st.booleans()),
        reason=draw(text),
        ceiling=ceiling,
    )


ODD = (
    [None, True, False, 0, 1, -1, 2**63, -(2**63) - 1, 2**64 - 1, 1.5, -0.0, math.nan, math.inf,
     -math.inf, "", "x", "y" * 5000, [], [1, 2], {}, {"a": 1}, {1: 2}, b"bytes"]
)  # fmt: skip
ODD_VALUES = st.sampled_from(ODD).map(copy.deepcopy)  # later mutations must not reach ODD


@st.composite
def mutated(draw: st.DrawFn, wire: dict[str, Any]) -> dict[str, Any]:
    """`wire` with a few of its (possibly nested) values replaced, removed or added."""
    wire = msgpack.unpackb(msgpack.packb(wire), raw=False)  # a deep copy, as a peer sends it
    for _ in range(draw(st.integers(1, 3))):
        target = wire
        while True:
            if not target:
                break
            key = draw(st.sampled_from(sorted(target, key=repr)))
            if isinstance(target[key], dict) and draw(st.booleans()):
                target = target[key]
                continue
            break
        action = draw(st.sampled_from(["replace", "remove", "add", "int"]))
        if not target or action == "add":
            target[draw(text)] = draw(ODD_VALUES)
        elif action == "replace":
            target[key] = draw(ODD_VALUES)
        elif action == "remove":
            del target[key]
        elif isinstance(target[key], float) and target[key].is_integer():
            target[key] = int(target[key])  # an integral float sent as an int
    return wire


# --------------------------------------------------------------------------- encoding


@pytest.mark.parametrize("message", REQUESTS + REPLIES, ids=lambda m: type(m).__name__)
def test_encode_writes_the_bytes_of_the_generic_walk(message: Any) -> None:
    assert encode(message) == msgpack.packb(codec._wire_map(message), use_bin_type=True)


@settings(max_examples=300, deadline=None)
@given(obs=observations())
def test_observations_encode_like_the_generic_walk_and_round_trip(obs: Observation) -> None:
    frame = encode(obs)
    assert frame == msgpack.packb(codec._wire_map(obs), use_bin_type=True)
    assert decode_reply(frame) == obs


def test_an_int_enum_goes_on_the_wire_as_a_plain_int() -> None:
    assert encode(Step(1, 0.5, LaneChange.LEFT)) == encode(Step(1, 0.5, 1))


def test_values_of_subclasses_encode_as_their_base_type() -> None:
    class Lane(IntEnum):
        LEFT = 2

    obs = Observation(
        1, 1.0, Ego(1.0, 0.0, Lane.LEFT, 3, 1.0, 1.0), Neighbours(*[Neighbour(False, 0, 0, 0)] * 6),
        Events(), AppliedAction(0.0, 0, 0.0, 0),
    )  # fmt: skip
    assert encode(obs) == msgpack.packb(codec._wire_map(obs), use_bin_type=True)

    class Seq(int):
        pass

    class Name(str):
        pass

    step, error = Step(Seq(3), np.float64(0.5), 0), Error(Name("busy"), "m")  # type: ignore[arg-type]
    assert encode(step) == msgpack.packb(codec._wire_map(step), use_bin_type=True)
    assert encode(error) == msgpack.packb(codec._wire_map(error), use_bin_type=True)
    with pytest.raises(TypeError):
        encode(Step(1, object(), 0))  # type: ignore[arg-type]
    with pytest.raises(TypeError):  # an option msgpack has no type for is refused before sending
        encode(Reset("cf", 1, {"blob": b"x"}))  # type: ignore[dict-item]


# --------------------------------------------------------------------------- decoding


def test_integers_sent_for_floats_become_floats() -> None:
    wire = codec._wire_map(REPLIES[1])
    wire["time"], wire["ego"]["speed"] = 31, 15
    obs = decode_reply(msgpack.packb(wire))
    assert isinstance(obs, Observation)
    assert type(obs.time) is float and type(obs.ego.speed) is float and obs.ego.speed == 15.0


@pytest.mark.parametrize("cls", REQUEST_TYPES + REPLY_TYPES, ids=lambda c: c.__name__)
def test_every_message_class_compiles(cls: type) -> None:
    assert codec._converter(cls).__qualname__ == f"decode_{cls.__name__}"


def leaf_paths(wire: dict[str, Any], prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    paths = []
    for key, value in wire.items():
        if isinstance(value, dict):
            paths += leaf_paths(value, (*prefix, key))
        paths.append((*prefix, key))
    return paths


FULL_OBSERVATION = codec._wire_map(REPLIES[1])  # every field present, a ceiling too


def with_odd_field(path: tuple[str, ...]) -> Iterator[tuple[Any, dict[str, Any]]]:
    """The full observation's wire map with the field at `path` replaced by each odd value (or
    removed: "missing")."""
    for odd in [*ODD, "missing"]:
        raw = msgpack.unpackb(msgpack.packb(FULL_OBSERVATION), raw=False)
        parent = raw
        for key in path[:-1]:
            parent = parent[key]
        if odd == "missing":
            del parent[path[-1]]
        else:
            parent[path[-1]] = odd
        yield odd, raw


@pytest.mark.parametrize("path", leaf_paths(FULL_OBSERVATION), ids=".".join)
def test_every_field_of_an_observation_gets_the_reference_verdict(path: tuple[str, ...]) -> None:
    for odd, raw in with_odd_field(path):
        expected = outcome(reference_dataclass(Observation), raw, "observation")
        assert outcome(codec._converter(Observation), raw, "observation") == expected, odd


@settings(max_examples=400, deadline=None)
@given(data=st.data())
def test_hostile_observations_get_the_reference_verdict(data: st.DataObject) -> None:
    wire = codec._wire_map(data.draw(observations()))
    raw = data.draw(mutated(wire))
    got = outcome(codec._converter(Observation), raw, "observation")
    assert got == outcome(reference_dataclass(Observation), raw, "observation")


@settings(max_examples=300, deadline=None)
@given(data=st.data())
def test_hostile_requests_get_the_reference_verdict(data: st.DataObject) -> None:
    message = data.draw(st.sampled_from(REQUESTS))
    wire = codec._wire_map(message)
    raw = data.draw(mutated(wire)) if len(wire) > 1 else wire
    cls = type(message)
    assert outcome(codec._converter(cls), raw, cls.TYPE) == outcome(
        reference_dataclass(cls), raw, cls.TYPE
    )


def test_a_request_decodes_through_the_compiled_converter() -> None:
    frame = msgpack.packb({"type": "step", "seq": 2, "acceleration": -1, "extra": [1]})
    step = decode_request(frame)
    assert step == Step(2, -1.0, 0) and type(step.acceleration) is float  # type: ignore[union-attr]


# --------------------------------------------------------------------------- the fast path


@contextlib.contextmanager
def precise_path_only() -> Iterator[None]:
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(codec, "_fast_decoder", lambda cls: None)
        yield


def frame_verdict(decode: Any, frame: bytes) -> tuple[str, Any]:
    try:
        value = decode(frame)
    except ProtocolError as exc:
        return "error", (exc.code, exc.message)
    return "ok", (value, repr(value))


def packed(raw: Any) -> bytes:
    """The frame a peer would send for `raw` (ints beyond msgpack's range cannot be sent)."""
    try:
        return msgpack.packb(raw)
    except OverflowError:
        assume(False)
        raise


def both_verdicts(decode: Any, frame: bytes) -> tuple[tuple[str, Any], tuple[str, Any]]:
    fast = frame_verdict(decode, frame)
    with precise_path_only():
        precise = frame_verdict(decode, frame)
    return fast, precise


def test_the_per_step_messages_have_a_fast_path_and_the_others_do_not() -> None:
    assert {cls for cls in REQUEST_TYPES + REPLY_TYPES if codec._fast_decoder(cls)} == {
        Step, MultiStep, Close, Observation, MultiObservation, Error, Bye
    }  # fmt: skip
    assert codec._fast_decoder(Hello) is None and codec._fast_decoder(Welcome) is None
    assert codec._fast_decoder(Reset) is None


def test_a_valid_observation_never_reaches_msgpack(monkeypatch: pytest.MonkeyPatch) -> None:
    frame = encode(REPLIES[1])

    def refuse(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("the precise path was taken")

    monkeypatch.setattr(codec.msgpack, "unpackb", refuse)
    assert decode_reply(frame) == REPLIES[1]
    assert decode_request(encode(Step(4, 1.5, 1))) == Step(4, 1.5, 1)


@settings(max_examples=400, deadline=None)
@given(data=st.data())
def test_hostile_observation_frames_get_the_precise_verdict(data: st.DataObject) -> None:
    raw = data.draw(mutated(codec._wire_map(data.draw(observations()))))
    fast, precise = both_verdicts(decode_reply, packed(raw))
    assert fast == precise


@settings(max_examples=300, deadline=None)
@given(data=st.data())
def test_hostile_request_frames_get_the_precise_verdict(data: st.DataObject) -> None:
    wire = codec._wire_map(data.draw(st.sampled_from(REQUESTS)))
    raw = data.draw(mutated(wire)) if len(wire) > 1 else wire
    fast, precise = both_verdicts(decode_request, packed(raw))
    assert fast == precise


@pytest.mark.parametrize("path", leaf_paths(FULL_OBSERVATION), ids=".".join)
def test_every_field_of_an_observation_frame_gets_the_precise_verdict(
    path: tuple[str, ...],
) -> None:
    for odd, raw in with_odd_field(path):
        if odd == -(2**63) - 1:
            continue  # no peer can send this: below msgpack's int64
        fast, precise = both_verdicts(decode_reply, msgpack.packb(raw))
        assert fast == precise, odd


@pytest.mark.parametrize(
    "frame",
    [
        encode(Step(1, 0.5, 0)) + b"\x00",  # trailing bytes
        encode(Step(1, 0.5, 0))[:-1],  # truncated
        encode(Step(1, 0.5, 0))[:-1] + b"\x91" * 100_000 + b"\x00",  # deep nesting
        msgpack.packb({"type": "step", "seq": 1, "acceleration": 0.5, 7: 1}),  # an int key
        msgpack.packb({"type": "step", b"seq": 1, "acceleration": 0.5}),  # a bytes key
        b"\x84"
        + b"".join(
            map(msgpack.packb, ["type", "step", "seq", 1, "acceleration", 0.5, "seq", 2])
        ),  # a key twice
        msgpack.packb({"type": "step", "seq": 2**64 - 1, "acceleration": 0.5}),
        msgpack.packb({"type": "step", "seq": 1, "acceleration": 2**64 - 1}),
        msgpack.packb({"type": "close", "x": b"\x00"}),
        msgpack.packb({"type": "error", "code": "c" * 4097, "message": ""}),
        msgpack.packb({"type": "error", "code": "c" * 3000, "message": "m" * 3000}),
        msgpack.packb({"type": "step", "seq": 1, "acceleration": math.nan}),
        # What msgspec reads differently: the first of two type keys, and the values of
        # unknown keys, which it skips unread (malformed ones are a decode error).
        b"\x84"
        + b"".join(
            map(msgpack.packb, ["type", "step", "seq", 1, "acceleration", 0.5, "type", "close"])
        ),
        b"\x82" + b"".join(map(msgpack.packb, ["type", "close", "type", "step"])),
        msgpack.packb({"type": "step", "seq": 1, "acceleration": 0.5, "x": {1: 2}}),
        msgpack.packb({"type": "step", "seq": 1, "acceleration": 0.5, "x": "?"})[:-2] + b"\xa1\xff",
        msgpack.packb({"type": "step", "seq": 1, "acceleration": 0.5, "x": 0})[:-3]
        + b"\xa1\xff\x00",
        msgpack.packb({"type": "step", "seq": 1, "acceleration": 0.5, "x": 0})[:-1]
        + b"\xd4\xff\x00",
        msgpack.packb({"type": "bye", "x": {1: 1}}),
    ],
)
def test_odd_frames_get_the_precise_verdict(frame: bytes) -> None:
    fast, precise = both_verdicts(decode_request, frame)
    assert fast == precise
    fast, precise = both_verdicts(decode_reply, frame)
    assert fast == precise


def test_a_frame_from_another_encoder_gets_the_same_message() -> None:
    """Keys in another order, floats as float32: not what `encode` writes, so the precise path."""
    wire = codec._wire_map(REPLIES[1])
    reordered = dict(reversed(list(wire.items())))
    packer = msgpack.Packer(use_single_float=True)
    for frame in (msgpack.packb(reordered), packer.pack(wire)):
        fast, precise = both_verdicts(decode_reply, frame)
        assert fast == precise and fast[0] == "ok"
    assert decode_reply(msgpack.packb(reordered)) == REPLIES[1]


def test_finite_numbers_whose_sum_overflows_are_accepted() -> None:
    obs = dataclasses.replace(REPLIES[1], time=1.7e308, ego=dataclasses.replace(
        REPLIES[1].ego, speed=1.7e308
    ))  # fmt: skip
    assert decode_reply(encode(obs)) == obs


def test_a_non_finite_observation_field_is_named_in_the_error() -> None:
    obs = dataclasses.replace(REPLIES[1], ego=dataclasses.replace(REPLIES[1].ego, speed=math.inf))
    with pytest.raises(ProtocolError, match=r"observation\.ego\.speed") as caught:
        decode_reply(encode(obs))
    assert caught.value.code is codec.ErrorCode.INVALID_NUMBER


@pytest.mark.parametrize("count", [14, 15, 16, 70])
def test_messages_of_many_fields_encode_like_the_generic_walk(
    count: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The type key makes one entry more: a fixmap of 15 becomes a map16."""
    cls = dataclasses.make_dataclass(
        "Wide", [(f"f{i}", int) for i in range(count)], frozen=True, slots=True
    )
    cls.TYPE = "wide"  # type: ignore[attr-defined]
    monkeypatch.setitem(codec._TYPE_ENTRIES, cls, msgpack.packb("type") + msgpack.packb("wide"))
    message = cls(*range(count))
    assert encode(message) == msgpack.packb(codec._wire_map(message), use_bin_type=True)
