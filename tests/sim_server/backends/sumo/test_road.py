"""The road ahead from SUMO's best lanes (`vehicle.getBestLanes`), without SUMO: the tuples as
libsumo gives them on a deceleration lane, an acceleration lane and a junction; the stop line
from the next link (`vehicle.getNextLinks`) and the foes with priority; a junction leader's gap
measured from positions."""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import pytest

from protocol.messages import ROAD_RANGE, Road, SignalState
from sim_server.backends.sumo.backend import SumoBackend
from sim_server.backends.sumo.road import Foe, carried, road_ahead, stop_line, yields_at
from sim_server.backends.sumo.signals import Signal, signal_line

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


def link(state: str, is_open: bool = True, priority: bool = True) -> tuple[object, ...]:
    """A next-links entry: (lane, has priority, is open, has foe, via, state, direction,
    length)."""
    return ("on_0", priority, is_open, not is_open, ":j_1_0", state, "s", 8.3)


def test_the_stop_line_is_the_lanes_end_where_the_way_is_closed() -> None:
    assert stop_line([link("r", is_open=False)], 42.0, 10.0, 14.0) == 42.0  # red
    assert stop_line([link("G")], 42.0, 10.0, 14.0) == ROAD_RANGE  # green
    assert stop_line([link("M")], 42.0, 10.0, 14.0) == ROAD_RANGE  # the major road
    minor_closed = link("m", is_open=False, priority=False)  # foes with priority approach
    assert stop_line([minor_closed], 42.0, 10.0, 14.0) == 42.0
    assert stop_line([], 42.0, 10.0, 14.0) == ROAD_RANGE  # a lane that ends: no junction
    assert stop_line([link("y")], 42.0, 10.0, 14.0) == 42.0  # 10 m/s stops in 17 m at 3 m/s²
    assert stop_line([link("y")], 10.0, 20.0, 25.0) == ROAD_RANGE  # 20 m/s cannot: drives on
    assert stop_line([link("r", is_open=False)], -0.5, 1.0, 14.0) == 0.0  # at the line


def test_a_yellow_light_is_reached_in_time_only_within_the_speed_limits_before_it() -> None:
    """At 22 m/s, 52 m before a light with 3 s of yellow left (stopping would take 4.8 m/s²):
    it reaches the line in time, unless the limit before it is 11 m/s, which SUMO holds it to
    (São Paulo: a red light passed); then the light closes its way."""
    yellow = Signal(51.6, SignalState.YELLOW, 3.0)
    assert signal_line(yellow, 22.2) == ROAD_RANGE
    assert signal_line(yellow, 22.2, limit_before=11.1) == 51.6
    assert stop_line([link("y")], 51.6, 22.2, 22.2, yellow_left=3.0) == ROAD_RANGE
    assert stop_line([link("y")], 51.6, 22.2, 22.2, yellow_left=3.0, limit_before=11.1) == 51.6


def test_a_foe_with_priority_closes_the_way_while_the_ego_could_not_leave_before_it() -> None:
    minor = [link("m", priority=False)]
    assert yields_at(minor) == ":j_1_0"
    assert yields_at([link("M")]) == "" and yields_at([link("m", False, False)]) == ""
    far = Foe(distance=300.0, exit_distance=303.0, speed=25.0, ego_exit_distance=3.0)
    near = Foe(distance=60.0, exit_distance=63.0, speed=25.0, ego_exit_distance=3.0)
    gone = Foe(distance=-10.0, exit_distance=-7.0, speed=25.0, ego_exit_distance=3.0)
    inside = Foe(distance=-1.0, exit_distance=2.0, speed=5.0, ego_exit_distance=3.0)
    standing = (2.0, 0.0, 16.0)  # 2 m before the line, at rest, on a 16 m/s ramp
    assert stop_line(minor, *standing, [far]) == ROAD_RANGE  # 12 s away: time to go
    assert stop_line(minor, *standing, [near]) == 2.0  # 2.4 s away: it would run into the ego
    assert stop_line(minor, *standing, [gone]) == ROAD_RANGE
    assert stop_line(minor, *standing, [inside]) == 2.0
    assert stop_line(minor, 30.0, 16.0, 16.0, [near]) == ROAD_RANGE  # at speed, well ahead of it


class Positions:
    """The vehicle queries `_nearest` makes, answered from fixed positions (SUMO's: the front
    bumper's middle; angles clockwise from north)."""

    def __init__(self, places: dict[str, tuple[float, float, float]]) -> None:
        self.places = places

    def getPosition(self, vehicle: str) -> tuple[float, float]:
        x, y, _ = self.places[vehicle]
        return x, y

    def getAngle(self, vehicle: str) -> float:
        return self.places[vehicle][2]

    def getLength(self, vehicle: str) -> float:
        return 5.0

    def getSpeed(self, vehicle: str) -> float:
        return 0.0


def test_a_junction_leader_reported_at_distance_0_is_seen_at_its_measured_gap(
    tmp_path: Path,
) -> None:
    """SUMO clamps a link leader's gap at 0 (read as the ego's minGap, 2.5 m): measured from
    the positions instead, and never below 0 for one beside the ego on a junction."""
    backend = SumoBackend(cache_dir=tmp_path)
    places = {"ego": (0.0, 0.0, 0.0), "ahead": (0.0, 6.0, 0.0), "beside": (3.2, 3.0, 30.0)}
    backend._api = SimpleNamespace(vehicle=Positions(places))  # type: ignore[assignment]
    episode = SimpleNamespace(min_gaps={})
    ahead = backend._nearest(episode, (("ahead", 0.0),), 2.5, None, "ego")  # type: ignore[arg-type]
    assert ahead.gap == pytest.approx(1.0)  # its rear 1 m ahead of the ego's front
    beside = backend._nearest(episode, (("beside", 0.0),), 2.5, None, "ego")  # type: ignore[arg-type]
    assert beside.gap == 0.0 and math.isfinite(beside.gap)
    unmeasured = backend._nearest(episode, (("ahead", 0.0),), 2.5, None)  # type: ignore[arg-type]
    assert unmeasured.gap == 2.5
    farther = backend._nearest(episode, (("ahead", 7.0),), 2.5, None, "ego")  # type: ignore[arg-type]
    assert farther.gap == 9.5  # SUMO's distance where it gives one
