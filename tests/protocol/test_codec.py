from __future__ import annotations

import math

import msgpack
import pytest

from protocol.codec import decode_reply, decode_request, encode
from protocol.errors import ErrorCode, ProtocolError
from protocol.messages import (
    ActionSchema,
    AppliedAction,
    Bye,
    Close,
    Command,
    Conflict,
    Ego,
    EgoObservation,
    Error,
    Events,
    FieldSpec,
    Hello,
    LeaderTrip,
    MultiObservation,
    MultiStep,
    Neighbour,
    Neighbours,
    Observation,
    Reset,
    Safety,
    ScenarioInfo,
    Step,
    Traffic,
    Welcome,
)


def make_observation(**changes: object) -> Observation:
    near = Neighbour(True, 12.5, 0.0, 14.0, "veh.1")
    absent = Neighbour(False, 200.0, 0.0, 0.0)
    values: dict[str, object] = {
        "seq": 3,
        "time": 31.2,
        "ego": Ego(15.0, -0.5, 0, 1, 120.0, 22.22),
        "neighbours": Neighbours(absent, absent, near, absent, absent, absent),
        "events": Events(lane_change_refused=True),
        "action": AppliedAction(4.0, 1, 3.0, 0, "bounds", "no_lane"),
        "ceiling": LeaderTrip("veh.1", 29.0, 160.0, 15.2),
    }
    values.update(changes)
    return Observation(**values)  # type: ignore[arg-type]


def _parts(obs: Observation) -> tuple[Ego, Neighbours, Events, AppliedAction]:
    return obs.ego, obs.neighbours, obs.events, obs.action


REQUESTS = [
    Hello((1, 0), "test"),
    Reset("cf", 7, {"flow": 1200.0, "report_ceiling": False, "name": "x", "none": None}),
    Reset("cflc"),
    Step(1, -2.5, -1),
    MultiStep(4, (Command("ego.0", 1.5, 0), Command("ego.1", -3.0, 1))),
    Close(),
]
REPLIES = [
    Welcome(
        protocol=(1, 0),
        server="s",
        backend="sumo",
        backend_version="1.28.0",
        scenarios=(ScenarioInfo("cf", "d", {"flow": 1500.0}),),
        observation_fields=(FieldSpec("time", "s", "simulation time"),),
        action=ActionSchema(-6.0, 3.0),
        sensor_range=200.0,
        max_frame_bytes=65536,
    ),
    make_observation(),
    make_observation(ceiling=None, terminated=True, reason="collision"),
    Error("busy", "try later"),
    Bye(),
    MultiObservation(
        2,
        30.2,
        (
            EgoObservation("ego.0", *_parts(make_observation())),
            EgoObservation("ego.1", *_parts(make_observation()), True, False, "collision"),
        ),
    ),
]

TRAFFIC = Traffic(
    id=("veh.1", "veh.2"),
    vehicle_type=("human", "truck"),
    lane=(0, 1),
    position=(120.0, 80.5),
    speed=(14.0, 12.0),
    acceleration=(0.1, -0.4),
    leader=("", "veh.1"),
    gap=(200.0, 31.5),
    leader_speed=(0.0, 14.0),
)
SAFETY = Safety(
    conflicts=(Conflict("veh.1", 31.0, 36.5, 1.2, 4.5, None, 2.1, 0.4, 1.9),),
    ttc_threshold=3.0,
    drac_threshold=3.0,
    pet_threshold=2.0,
)


@pytest.mark.parametrize("message", REQUESTS, ids=lambda m: type(m).__name__)
def test_requests_round_trip(message: object) -> None:
    assert decode_request(encode(message)) == message  # type: ignore[arg-type]


@pytest.mark.parametrize("message", REPLIES, ids=lambda m: type(m).__name__)
def test_replies_round_trip(message: object) -> None:
    assert decode_reply(encode(message)) == message  # type: ignore[arg-type]


def test_wire_is_a_map_with_named_fields() -> None:
    wire = msgpack.unpackb(encode(Step(4, 1.5, 1)), raw=False)
    assert wire == {"type": "step", "seq": 4, "acceleration": 1.5, "lane_change": 1}
    obs = msgpack.unpackb(encode(make_observation()), raw=False)
    assert obs["neighbours"]["leader"]["gap"] == 12.5
    assert obs["ego"]["speed_limit"] == 22.22


def test_unknown_keys_are_ignored_for_forward_compatibility() -> None:
    frame = msgpack.packb({"type": "step", "seq": 1, "acceleration": 0.0, "future": [1, 2]})
    assert decode_request(frame) == Step(1, 0.0)


def test_integers_are_accepted_as_floats() -> None:
    frame = msgpack.packb({"type": "step", "seq": 1, "acceleration": 2})
    assert decode_request(frame).acceleration == 2.0  # type: ignore[union-attr]


def _code(frame: bytes, max_bytes: int = 65536) -> ErrorCode:
    with pytest.raises(ProtocolError) as caught:
        decode_request(frame, max_bytes)
    return caught.value.code


@pytest.mark.parametrize(
    ("frame", "code"),
    [
        (b"\xc1", ErrorCode.DECODE_ERROR),
        (b"", ErrorCode.DECODE_ERROR),
        (msgpack.packb([1, 2, 3]), ErrorCode.DECODE_ERROR),
        (msgpack.packb({"seq": 1}), ErrorCode.INVALID_MESSAGE),
        (msgpack.packb({"type": "warp"}), ErrorCode.UNKNOWN_TYPE),
        (msgpack.packb({"type": "observation"}), ErrorCode.UNKNOWN_TYPE),
        (msgpack.packb({"type": "step", "seq": 1}), ErrorCode.INVALID_MESSAGE),
        (msgpack.packb({"type": "step", "seq": "1", "acceleration": 0}), ErrorCode.INVALID_MESSAGE),
        (msgpack.packb({"type": "step", "seq": True, "acceleration": 0}), ErrorCode.INVALID_MESSAGE),
        (msgpack.packb({"type": "step", "seq": 1, "acceleration": math.nan}), ErrorCode.INVALID_NUMBER),
        (msgpack.packb({"type": "step", "seq": 1, "acceleration": math.inf}), ErrorCode.INVALID_NUMBER),
        (msgpack.packb({"type": "reset", "scenario": "cf", "options": {"a": [1]}}), ErrorCode.INVALID_MESSAGE),
        (msgpack.packb({"type": "reset", "scenario": "cf", "options": {"a": math.nan}}), ErrorCode.INVALID_NUMBER),
        (msgpack.packb({"type": "hello", "protocol": [1]}), ErrorCode.INVALID_MESSAGE),
        (msgpack.packb({"type": "hello", "protocol": [1, 0]}) + b"\x00", ErrorCode.DECODE_ERROR),
        # protocol 1.2: what the protocol never sends is a decode_error, under any key
        (msgpack.packb({"type": "reset", "scenario": b"cf"}, use_bin_type=True), ErrorCode.DECODE_ERROR),
        (msgpack.packb({"type": "hello", "protocol": [1, 0], "x": b"?"}, use_bin_type=True), ErrorCode.DECODE_ERROR),
        (msgpack.packb({"type": "hello", "protocol": [1, 0], "x": msgpack.ExtType(1, b"?")}), ErrorCode.DECODE_ERROR),
        (msgpack.packb({"type": "hello", "protocol": [1, 0], b"x": 1}, use_bin_type=True), ErrorCode.DECODE_ERROR),
        (msgpack.packb({"type": "reset", "scenario": "cf", "options": {b"flow": 1}}, use_bin_type=True), ErrorCode.DECODE_ERROR),
        (msgpack.packb({"type": "hello", "protocol": [1, 0], 7: 1}), ErrorCode.DECODE_ERROR),
        (msgpack.packb({"type": 7}), ErrorCode.INVALID_MESSAGE),
        (msgpack.packb({"type": "hello", "protocol": [1, 0], "client": "x" * 4097}), ErrorCode.INVALID_MESSAGE),
        (msgpack.packb({"type": "step", "seq": 2**63, "acceleration": 0.0}), ErrorCode.INVALID_NUMBER),
    ],
)  # fmt: skip
def test_bad_frames_get_distinct_codes(frame: bytes, code: ErrorCode) -> None:
    assert _code(frame) is code


def test_frame_over_the_limit() -> None:
    frame = msgpack.packb({"type": "hello", "protocol": [1, 0], "client": "x" * 2000})
    assert _code(frame, max_bytes=1000) is ErrorCode.FRAME_TOO_LARGE


def test_deeply_nested_msgpack_is_a_decode_error_not_a_crash() -> None:
    frame = b"\x91" * 100_000 + b"\x00"  # 100k nested one-element arrays
    assert _code(frame, max_bytes=1 << 20) is ErrorCode.DECODE_ERROR


def test_nesting_is_accepted_up_to_msgpacks_limit_of_1023_levels() -> None:
    head = msgpack.packb({"type": "hello", "protocol": [1, 0]})
    for depth, ok in ((32, True), (1023, True), (1024, False)):
        frame = b"\x83" + head[1:] + msgpack.packb("x") + b"\x91" * depth + b"\x00"
        if ok:
            assert decode_request(frame, 1 << 20).TYPE == "hello"
        else:
            assert _code(frame, max_bytes=1 << 20) is ErrorCode.DECODE_ERROR


def test_an_error_names_the_field_it_is_about() -> None:
    with pytest.raises(ProtocolError) as caught:
        decode_request(msgpack.packb({"type": "step", "seq": 1, "acceleration": "fast"}))
    assert caught.value.field == "step.acceleration"
    with pytest.raises(ProtocolError) as caught:
        decode_request(b"\xc1")
    assert caught.value.field == ""


def test_error_message_names_the_field() -> None:
    with pytest.raises(ProtocolError, match=r"step\.acceleration"):
        decode_request(msgpack.packb({"type": "step", "seq": 1, "acceleration": "fast"}))


def test_safety_and_traffic_round_trip() -> None:
    """Arrays of numbers, strings and messages (protocol 1.3) keep the fast path's verdict."""
    obs = make_observation(terminated=True, reason="collision", safety=SAFETY, traffic=TRAFFIC)
    assert decode_reply(encode(obs)) == obs
    empty = make_observation(traffic=Traffic((), (), (), (), (), (), (), (), ()))
    assert decode_reply(encode(empty)) == empty


@pytest.mark.parametrize(
    ("column", "value", "words"),
    [
        ("speed", math.nan, "observation.traffic.speed[1]: nan is not a finite number"),
        ("lane", 1.5, "observation.traffic.lane[1]"),
        ("id", "x" * 5000, "observation.traffic.id[1]"),
    ],
)
def test_a_bad_item_of_an_array_is_named(column: str, value: object, words: str) -> None:
    wire = msgpack.unpackb(encode(make_observation(traffic=TRAFFIC)))
    wire["traffic"][column][1] = value
    with pytest.raises(ProtocolError, match=words.replace("[", r"\[").replace("]", r"\]")):
        decode_reply(msgpack.packb(wire))


def test_an_array_longer_than_the_protocol_allows_is_refused() -> None:
    wire = msgpack.unpackb(encode(make_observation(traffic=TRAFFIC)))
    wire["traffic"]["speed"] = [1.0] * 1025
    with pytest.raises(ProtocolError, match="more than 1024 items"):
        decode_reply(msgpack.packb(wire), max_frame_bytes=1 << 20)


def test_an_infinite_conflict_measure_is_refused() -> None:
    wire = msgpack.unpackb(encode(make_observation(safety=SAFETY)))
    wire["safety"]["conflicts"][0]["max_drac"] = math.inf
    with pytest.raises(ProtocolError, match=r"conflicts\[0\].max_drac"):
        decode_reply(msgpack.packb(wire))
