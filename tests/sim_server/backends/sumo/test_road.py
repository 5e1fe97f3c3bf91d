"""The road ahead from SUMO's best lanes (`vehicle.getBestLanes`), without SUMO: the tuples as
libsumo gives them on a deceleration lane, an acceleration lane and a junction."""

from __future__ import annotations

import pytest

from protocol.messages import ROAD_RANGE, Road
from sim_server.backends.sumo.road import carried, road_ahead

# (lane id, length, occupation, offset, allows continuation, next lanes)
BEFORE_EXIT = (
    ("main_0", 1249.0, 0.0, 0, True, ("main_0", "decel_1")),
    ("main_1", 1020.0, 0.0, -1, True, ("main_1", "decel_2")),
    ("main_2", 1020.0, 0.0, -2, True, ("main_2", "decel_3")),
)
ACCELERATION_LANE = (
    ("merge_0", 226.2, 0.0, 1, False, ("merge_0",)),
    ("merge_1", 1022.2, 0.0, 0, True, ("merge_1", "main_down_0")),
    ("merge_2", 1022.2, 0.0, 0, True, ("merge_2", "main_down_1")),
)


LENGTHS = {"main_0": 796.0, "main_1": 796.0, "main_2": 796.0, "decel_1": 224.0, "decel_2": 224.0,
           "decel_3": 224.0, "merge_0": 226.2, "merge_1": 226.2, "merge_2": 226.2,
           "main_down_0": 796.0, "main_down_1": 796.0, "ramp_0": 271.5}  # fmt: skip


def length_of(lane: str) -> float:
    return LENGTHS[lane]


def test_a_lane_that_does_not_lead_to_the_exit_ends_where_it_must_have_been_left() -> None:
    assert road_ahead(BEFORE_EXIT, "main_2", 120.0, length_of) == Road(900.0, -2, 0.0, 900.0)
    assert road_ahead(BEFORE_EXIT, "main_1", 120.0, length_of) == Road(
        900.0, -1, 900.0, 900.0
    )  # the rightmost lane leads into the deceleration lane's neighbour, which ends there too
    assert road_ahead(BEFORE_EXIT, "main_0", 120.0, length_of) == Road(900.0, 0, 900.0, 0.0)


def test_a_ramps_single_lane_sees_the_end_of_the_acceleration_lane_ahead() -> None:
    ramp = (("ramp_0", 1293.7, 0.0, 0, True, ("ramp_0", "merge_0")),)
    assert road_ahead(ramp, "ramp_0", 71.5, length_of) == pytest.approx(
        Road(271.5 + 226.2 - 71.5, 0, 0.0, 0.0)
    )


def test_the_end_of_an_acceleration_lane() -> None:
    assert road_ahead(ACCELERATION_LANE, "merge_0", 26.2, length_of) == Road(
        200.0, 1, ROAD_RANGE, 0.0
    )
    past = road_ahead(ACCELERATION_LANE, "merge_0", 300.0, length_of)  # driven onto its end
    assert past is not None and past.lane_end == 0.0


def test_far_distances_are_reported_at_the_range() -> None:
    far = (("a_0", 5000.0, 0.0, 0, True, ()), ("a_1", 3000.0, 0.0, -1, True, ()))
    assert road_ahead(far, "a_1", 10.0, length_of) == Road(ROAD_RANGE, -1, 0.0, ROAD_RANGE)


def test_on_a_junction_the_road_of_the_lane_it_came_from_is_carried_on() -> None:
    junction = (("main_down_0", 796.0, 0.0, 0, True, ()),)
    assert road_ahead(junction, ":me_0_0", 2.5, length_of) is None
    before = Road(180.0, -2, ROAD_RANGE, 180.0)
    assert carried(before, 4.0, 1, 3) == Road(176.0, -1, ROAD_RANGE, 176.0)  # within its lanes
    assert carried(before, 4.0, 0, 1) == Road(176.0, 0, 0.0, 0.0)
    assert carried(None, 4.0, 0, 1) == Road(ROAD_RANGE, 0, 0.0, 0.0)
