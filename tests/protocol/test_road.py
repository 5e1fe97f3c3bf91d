"""The road ahead (protocol 1.6): on the wire, in the flat vector, and for older peers."""

from __future__ import annotations

import msgpack

from protocol.codec import decode_reply, encode
from protocol.messages import (
    OPEN_ROAD,
    ROAD_RANGE,
    Ego,
    EgoObservation,
    EndReason,
    MultiObservation,
    Observation,
    Road,
    road_ahead,
)
from protocol.schema import OBSERVATION_FIELDS, Flattener, fields_for
from tests.protocol.test_codec import _parts, make_observation

MERGING = Road(lane_end=143.5, lanes_to_change=1, left_lane_end=ROAD_RANGE, right_lane_end=0.0)


def test_an_observation_with_its_road_round_trips() -> None:
    obs = make_observation(ego=Ego(15.0, 0.0, 0, 3, 320.0, 27.78), road=MERGING)
    assert decode_reply(encode(obs)) == obs


def test_each_ego_of_a_frame_carries_its_own_road() -> None:
    first = make_observation(road=MERGING)
    second = make_observation(road=OPEN_ROAD, terminated=True, reason=EndReason.LANE_END)
    frame = MultiObservation(
        7,
        40.0,
        (
            EgoObservation("ego.0", *_parts(first), road=first.road),
            EgoObservation("ego.1", *_parts(second), True, False, "lane_end", second.road),
        ),
    )
    decoded = decode_reply(encode(frame))
    assert isinstance(decoded, MultiObservation)
    assert [e.road for e in decoded.egos] == [MERGING, OPEN_ROAD]


def test_an_observation_without_road_is_the_frame_a_1_5_server_sends() -> None:
    obs = make_observation()
    frame = encode(obs)
    assert "road" not in msgpack.unpackb(frame)  # left out when nil, as traffic and safety are
    assert decode_reply(frame) == obs  # and read back with road nil


def test_a_1_5_client_reads_a_1_6_observation_ignoring_its_road() -> None:
    frame = msgpack.unpackb(encode(make_observation(road=MERGING)))
    assert frame["road"]["lanes_to_change"] == 1
    del frame["road"]  # what a reader that does not know the key is left with
    assert decode_reply(msgpack.packb(frame)) == make_observation()


def test_a_1_6_servers_road_has_no_stop_line_and_a_1_6_client_ignores_it() -> None:
    frame = msgpack.unpackb(encode(make_observation(road=MERGING)))
    assert frame["road"]["stop_line"] == ROAD_RANGE
    del frame["road"]["stop_line"]  # what a 1.6 server sends
    decoded = decode_reply(msgpack.packb(frame))
    assert isinstance(decoded, Observation) and decoded.road == MERGING
    assert decoded.road.stop_line == ROAD_RANGE


def test_the_flat_vector_ends_with_the_road() -> None:
    flatten = Flattener(OBSERVATION_FIELDS)
    vector = flatten(make_observation(ego=Ego(15.0, 0.0, 0, 3, 320.0, 27.78), road=MERGING))
    names = [f.name for f in OBSERVATION_FIELDS[-8:-3]]
    assert names == ["lane_end", "lanes_to_change", "left_lane_end", "right_lane_end", "stop_line"]
    assert vector[-8:-3] == [143.5, 1.0, ROAD_RANGE, 0.0, ROAD_RANGE]  # no stop line: the range
    at_a_light = flatten(make_observation(road=Road(ROAD_RANGE, 0, 0.0, 0.0, stop_line=42.0)))
    assert at_a_light[-4] == 42.0


def test_the_flat_vector_ends_with_the_next_traffic_light() -> None:
    flatten = Flattener(OBSERVATION_FIELDS)
    names = [f.name for f in OBSERVATION_FIELDS[-3:]]
    assert names == ["signal_distance", "signal_state", "signal_switch"]
    assert flatten(make_observation(road=MERGING))[-3:] == [ROAD_RANGE, 0.0, 0.0]  # no light
    codes = {}
    for state in ("green", "yellow", "red", "off", "blue"):  # blue: a newer server's state
        road = Road(ROAD_RANGE, 0, 0.0, 0.0, 42.0, 61.5, state, 7.5)
        codes[state] = flatten(make_observation(road=road))[-3:]
    assert codes["red"] == [61.5, 3.0, 7.5]
    assert [codes[s][1] for s in ("green", "yellow", "off", "blue")] == [1.0, 2.0, 0.0, 0.0]


def test_a_1_7_servers_road_has_no_light_and_reads_as_none() -> None:
    road = Road(ROAD_RANGE, 0, 0.0, 0.0, 42.0, 61.5, "red", 7.5)
    frame = msgpack.unpackb(encode(make_observation(road=road)))
    for key in ("signal_distance", "signal_state", "signal_switch"):
        del frame["road"][key]  # what a 1.7 server sends
    decoded = decode_reply(msgpack.packb(frame))
    assert isinstance(decoded, Observation) and decoded.road is not None
    assert (decoded.road.signal_distance, decoded.road.signal_state) == (ROAD_RANGE, "")
    assert decoded.road.stop_line == 42.0


def test_an_observation_without_road_reads_as_the_open_road() -> None:
    middle = make_observation(ego=Ego(15.0, 0.0, 1, 3, 320.0, 27.78))
    assert road_ahead(middle) == OPEN_ROAD
    leftmost = make_observation(ego=Ego(15.0, 0.0, 2, 3, 320.0, 27.78))
    assert road_ahead(leftmost) == Road(ROAD_RANGE, 0, 0.0, ROAD_RANGE)
    one_lane = make_observation()
    assert road_ahead(one_lane) == Road(ROAD_RANGE, 0, 0.0, 0.0)


def test_a_client_is_announced_the_fields_of_its_version() -> None:
    assert fields_for((1, 5)) == OBSERVATION_FIELDS[:32]
    assert fields_for((1, 0)) == OBSERVATION_FIELDS[:32]
    assert fields_for((1, 6)) == OBSERVATION_FIELDS[:36]  # the road, no stop line
    assert fields_for((1, 7)) == OBSERVATION_FIELDS[:37]  # the stop line, no traffic light
    assert fields_for((1, 8)) == OBSERVATION_FIELDS
    assert fields_for((1, 9)) == OBSERVATION_FIELDS
