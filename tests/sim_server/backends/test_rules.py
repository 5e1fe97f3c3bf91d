"""The rules every backend shares: acceleration limits, lane-change refusals and timeout, the
end of an episode."""

from __future__ import annotations

from dataclasses import replace

import pytest

from protocol.messages import (
    ROAD_RANGE,
    AccelerationLimit,
    AppliedAction,
    Ego,
    EndReason,
    Events,
    LaneChangeRefusal,
    Neighbour,
    Neighbours,
    Observation,
    Road,
)
from sim_server.backends.options import EpisodeOptions
from sim_server.backends.rules import (
    LANE_CHANGE_TIMEOUT_S,
    EndRule,
    LaneChangeUnderWay,
    ended,
    lane_change_refusal,
    limit_acceleration,
)

LOW, HIGH, LIMIT, DT = -6.0, 3.0, 20.0, 0.1

# --------------------------------------------------------------------------- acceleration


def test_an_acceleration_within_every_limit_is_applied_as_asked() -> None:
    assert limit_acceleration(1.5, 10.0, LIMIT, LOW, HIGH, DT) == (1.5, "")
    assert limit_acceleration(LOW, 10.0, LIMIT, LOW, HIGH, DT) == (LOW, "")  # bounds included


@pytest.mark.parametrize(("request_", "applied"), [(50.0, HIGH), (-50.0, LOW)])
def test_an_acceleration_beyond_the_bounds_is_clipped(request_: float, applied: float) -> None:
    assert limit_acceleration(request_, 10.0, LIMIT, LOW, HIGH, DT) == (
        applied,
        AccelerationLimit.BOUNDS,
    )


def test_the_speed_limit_lowers_the_acceleration_to_reach_it_exactly() -> None:
    applied, why = limit_acceleration(2.0, 19.9, LIMIT, LOW, HIGH, DT)
    assert why is AccelerationLimit.SPEED_LIMIT
    assert applied == pytest.approx(1.0)
    assert 19.9 + applied * DT == pytest.approx(LIMIT)
    # Clipped to the bounds first: the speed limit's reason is the one reported.
    assert limit_acceleration(50.0, 19.9, LIMIT, LOW, HIGH, DT)[1] is AccelerationLimit.SPEED_LIMIT


def test_far_above_the_speed_limit_the_ego_brakes_no_harder_than_the_bound() -> None:
    assert limit_acceleration(0.0, 30.0, LIMIT, LOW, HIGH, DT) == (
        LOW,
        AccelerationLimit.SPEED_LIMIT,
    )


def test_braking_stops_at_standstill_instead_of_reversing() -> None:
    applied, why = limit_acceleration(-6.0, 0.2, LIMIT, LOW, HIGH, DT)
    assert why is AccelerationLimit.STANDSTILL
    assert applied == pytest.approx(-2.0)
    assert limit_acceleration(-50.0, 0.0, LIMIT, LOW, HIGH, DT) == (
        0.0,
        AccelerationLimit.STANDSTILL,
    )


def test_the_reasons_are_the_wire_strings() -> None:
    _, why = limit_acceleration(-50.0, 10.0, LIMIT, LOW, HIGH, DT)
    assert why == "bounds" and isinstance(why, str)


# --------------------------------------------------------------------------- lane changes


class Calls:
    """The simulator queries of a refusal, answering as told and counting the calls."""

    def __init__(self, lane: int = 1, lane_count: int = 3, gap_ok: bool = True) -> None:
        self.lane, self.lane_count, self.gap = lane, lane_count, gap_ok
        self.asked: list[str] = []

    def ego_lane(self) -> tuple[int, int]:
        self.asked.append("lane")
        return self.lane, self.lane_count

    def gap_ok(self, direction: int) -> bool:
        self.asked.append(f"gap {direction}")
        return self.gap


UNDER_WAY = LaneChangeUnderWay(target=2, direction=1, started=30.0)


def refusal(
    direction: int,
    calls: Calls,
    simulator_drives: bool = False,
    under_way: LaneChangeUnderWay | None = None,
) -> str:
    return lane_change_refusal(
        direction,
        simulator_drives=simulator_drives,
        under_way=under_way,
        ego_lane=calls.ego_lane,
        gap_ok=calls.gap_ok,
    )


def test_keeping_the_lane_is_never_refused_and_asks_nothing() -> None:
    calls = Calls(lane_count=1, gap_ok=False)
    assert refusal(0, calls, simulator_drives=True, under_way=UNDER_WAY) == ""
    assert calls.asked == []


def test_a_lane_change_with_a_lane_and_a_gap_is_allowed() -> None:
    calls = Calls(lane=1, lane_count=3)
    assert refusal(-1, calls) == ""
    assert calls.asked == ["lane", "gap -1"]


def test_refusals_come_in_order_each_asking_only_what_it_needs() -> None:
    # Every rule would refuse: the simulator driving comes first, and asks nothing.
    calls = Calls(lane=2, lane_count=3, gap_ok=False)
    verdict = refusal(1, calls, simulator_drives=True, under_way=UNDER_WAY)
    assert verdict is LaneChangeRefusal.SIMULATOR_DRIVES and calls.asked == []
    # Then a lane change under way.
    assert refusal(1, calls, under_way=UNDER_WAY) is LaneChangeRefusal.IN_PROGRESS
    assert calls.asked == []
    # Then no lane on that side (the gap is not checked).
    assert refusal(1, calls) is LaneChangeRefusal.NO_LANE
    assert calls.asked == ["lane"]
    # Then the simulator's own gap check.
    calls = Calls(lane=1, lane_count=3, gap_ok=False)
    assert refusal(1, calls) is LaneChangeRefusal.GAP_TOO_SMALL
    assert calls.asked == ["lane", "gap 1"]


@pytest.mark.parametrize(
    ("lane", "lane_count", "direction", "verdict"),
    [
        (0, 1, 1, "no_lane"),
        (0, 1, -1, "no_lane"),
        (0, 3, -1, "no_lane"),
        (0, 3, 1, ""),
        (2, 3, 1, "no_lane"),
        (2, 3, -1, ""),
    ],
)
def test_no_lane_beyond_the_outer_lanes(
    lane: int, lane_count: int, direction: int, verdict: str
) -> None:
    assert refusal(direction, Calls(lane, lane_count)) == verdict


def tenths(start: float, count: int) -> list[float]:
    """Simulation times after `start`, 0.1 s apart, as SUMO reports them (36.3 - 31.3 is
    4.9999999999999964 in floating point)."""
    first = round(start * 10)
    return [(first + k) / 10 for k in range(1, count + 1)]


def test_a_lane_change_under_way_is_given_up_after_the_timeout() -> None:
    change = LaneChangeUnderWay(target=1, direction=-1, started=31.3)
    expired = [change.expired(now) for now in tenths(change.started, 60)]
    assert expired.index(True) + 1 == round(LANE_CHANGE_TIMEOUT_S / 0.1) == 50
    assert all(expired[49:])


# --------------------------------------------------------------------------- end of episode

ABSENT = Neighbour(False, 200.0, 0.0, 0.0)
OPTIONS = EpisodeOptions(max_episode_time=10.0, stop_speed=1.0, stop_gap=15.0, stop_patience=2.0)
ENTRY = 30.3


def observation(
    time: float,
    speed: float,
    leader: Neighbour = ABSENT,
    events: Events = Events(),  # noqa: B008 - immutable
) -> Observation:
    return Observation(
        seq=1,
        time=time,
        ego=Ego(speed, 0.0, 0, 1, 100.0, 22.2),
        neighbours=Neighbours(ABSENT, ABSENT, leader, ABSENT, ABSENT, ABSENT),
        events=events,
        action=AppliedAction(0.0, 0, 0.0, 0),
    )


def verdicts(rule: EndRule, speeds: list[float], leader: Neighbour = ABSENT) -> list[object]:
    """The rule's verdict on 0.1 s steps at these speeds, the first 1 s after the entry."""
    times = tenths(ENTRY + 0.9, len(speeds))
    return [rule.check(observation(t, v, leader)) for t, v in zip(times, speeds, strict=True)]


def test_a_stop_ends_the_episode_after_the_patience_not_before() -> None:
    rule = EndRule(OPTIONS, ENTRY)
    found = verdicts(rule, [0.5] * 21)
    assert found[:20] == [None] * 20  # stopped at the first, 1.9 s later still patient
    assert found[20] is EndReason.STOPPED  # 2.0 s after the first stopped observation


def test_moving_again_restarts_the_patience() -> None:
    rule = EndRule(OPTIONS, ENTRY)
    found = verdicts(rule, [0.5] * 15 + [1.0] + [0.5] * 21)
    assert found == [None] * 36 + [EndReason.STOPPED]


@pytest.mark.parametrize(
    ("leader", "stops"),
    [
        (Neighbour(True, 50.0, 0.0, 5.0, "far and faster"), True),
        (Neighbour(True, 10.0, 0.0, 5.0, "close and faster"), False),
        (Neighbour(True, 50.0, 0.0, 0.2, "far and slower: a queue"), False),
        (Neighbour(True, 10.0, 0.0, 0.0, "close and stopped: a queue"), False),
    ],
)
def test_a_stop_behind_a_near_or_slower_leader_is_not_unreasonable(
    leader: Neighbour, stops: bool
) -> None:
    rule = EndRule(OPTIONS, ENTRY)
    found = verdicts(rule, [0.5] * 30, leader)
    assert (EndReason.STOPPED in found) is stops


def test_the_time_limit_counts_from_the_entry_and_truncates() -> None:
    rule = EndRule(OPTIONS, ENTRY)
    found = [rule.check(observation(t, 15.0)) for t in tenths(ENTRY, 110)]
    assert found.index(EndReason.TIME_LIMIT) + 1 == 100  # 10 s of 0.1 s steps
    assert found[:99] == [None] * 99
    last = ended(observation(ENTRY + 10.0, 15.0), EndReason.TIME_LIMIT)
    assert last.truncated and not last.terminated and last.reason == "time_limit"


def test_a_collision_comes_before_every_other_reason() -> None:
    rule = EndRule(replace(OPTIONS, stop_patience=0.0, max_episode_time=0.1), ENTRY)
    crash = Events(collision=True, collision_with="h1", end_of_road=True)
    obs = observation(ENTRY + 5.0, 0.0, events=crash)
    assert rule.check(obs) is EndReason.COLLISION
    assert rule.check(replace(obs, events=Events(end_of_road=True))) is EndReason.END_OF_ROAD
    last = ended(obs, EndReason.COLLISION)
    assert last.terminated and not last.truncated and last.reason == "collision"


# --------------------------------------------------------------------------- the lane's end

MERGING = Road(lane_end=8.0, lanes_to_change=1, left_lane_end=ROAD_RANGE, right_lane_end=0.0)


def at_lane_end(rule: EndRule, speeds: list[float], road: Road = MERGING) -> list[object]:
    """The rule's verdicts on 0.1 s steps at these speeds, on a lane ending `road.lane_end` m
    ahead."""
    times = tenths(ENTRY + 0.9, len(speeds))
    return [
        rule.check(replace(observation(t, v), road=road))
        for t, v in zip(times, speeds, strict=True)
    ]


def test_standing_at_the_end_of_a_lane_that_must_be_left_ends_as_lane_end() -> None:
    rule = EndRule(replace(OPTIONS, lane_end_patience=3.0), ENTRY)
    found = at_lane_end(rule, [0.0] * 31)
    assert found[:30] == [None] * 30  # waiting for a gap is no unreasonable stop (2 s)
    assert found[30] is EndReason.LANE_END  # 3.0 s after it first stood there
    assert EndReason.LANE_END.terminates


def test_moving_on_restarts_the_lane_ends_patience() -> None:
    rule = EndRule(replace(OPTIONS, lane_end_patience=1.0), ENTRY)
    found = at_lane_end(rule, [0.0] * 8 + [2.0] + [0.0] * 11)
    assert found == [None] * 19 + [EndReason.LANE_END]


def test_a_stop_far_from_the_lane_end_is_an_ordinary_stop() -> None:
    far = replace(MERGING, lane_end=200.0)
    found = at_lane_end(EndRule(replace(OPTIONS, lane_end_patience=9.0), ENTRY), [0.0] * 21, far)
    assert found[20] is EndReason.STOPPED


def test_the_open_road_never_ends_at_a_lane_end() -> None:
    found = at_lane_end(EndRule(OPTIONS, ENTRY), [0.0] * 21, Road(ROAD_RANGE, 0, 0.0, 0.0))
    assert EndReason.LANE_END not in found
    assert found[20] is EndReason.STOPPED


def test_waiting_at_a_stop_line_is_no_unreasonable_stop_and_a_far_one_is_no_excuse() -> None:
    at_the_line = Road(ROAD_RANGE, 0, 0.0, 0.0, stop_line=3.0)  # a red light, foes to give way to
    found = at_lane_end(EndRule(OPTIONS, ENTRY), [0.0] * 40, at_the_line)
    assert found == [None] * 40
    far_ahead = Road(ROAD_RANGE, 0, 0.0, 0.0, stop_line=300.0)
    found = at_lane_end(EndRule(OPTIONS, ENTRY), [0.0] * 21, far_ahead)
    assert found[20] is EndReason.STOPPED


def test_a_stop_that_began_at_a_stop_line_has_the_lane_ends_patience_once_it_clears() -> None:
    rule = EndRule(replace(OPTIONS, lane_end_patience=5.0), ENTRY)
    at_the_line = Road(ROAD_RANGE, 0, 0.0, 0.0, stop_line=3.0)
    cleared = Road(ROAD_RANGE, 0, 0.0, 0.0)
    times = tenths(ENTRY + 0.9, 80)
    roads = [at_the_line] * 20 + [cleared] * 60
    found = [
        rule.check(replace(observation(t, 0.0), road=road))
        for t, road in zip(times, roads, strict=True)
    ]
    assert found[:69] == [None] * 69  # 4.9 s after the line cleared: still patient
    assert found[70] is EndReason.STOPPED  # 5 s
    rule = EndRule(replace(OPTIONS, lane_end_patience=5.0), ENTRY)  # moving in between: 2 s
    speeds = [0.0] * 20 + [2.0] + [0.0] * 59
    found = [
        rule.check(replace(observation(t, v), road=road))
        for t, v, road in zip(times, speeds, roads, strict=True)
    ]
    assert found.index(EndReason.STOPPED) == 41


def test_waiting_for_a_gap_to_the_lane_the_route_needs_is_no_unreasonable_stop() -> None:
    """The ego stands 60 m before the end of the lane it must leave (a turn at a red light, a
    gap to wait for), nobody ahead: it waits, as it would at the lane's end (SUMO's own driver
    ended `stopped` so in 2 of 5 city episodes before)."""
    before_the_turn = Road(
        lane_end=60.0, lanes_to_change=-1, left_lane_end=0.0, right_lane_end=ROAD_RANGE
    )
    found = at_lane_end(EndRule(OPTIONS, ENTRY), [0.0] * 60, before_the_turn)
    assert found == [None] * 60
    two_lanes_away = replace(before_the_turn, lane_end=250.0, lanes_to_change=-2)
    assert at_lane_end(EndRule(OPTIONS, ENTRY), [0.0] * 60, two_lanes_away) == [None] * 60
    too_far = replace(before_the_turn, lane_end=400.0)  # farther than 150 m per lane
    assert at_lane_end(EndRule(OPTIONS, ENTRY), [0.0] * 21, too_far)[20] is EndReason.STOPPED


def test_waiting_at_a_junction_that_gives_way_is_no_unreasonable_stop() -> None:
    """A driver may wait longer than `Road.stop_line` judges it must (SUMO's own driver, 30 s
    at a minor link on the São Paulo export, a queue beyond it): within ``stop_gap`` of a
    junction where the simulator says it gives way, a stop is a wait, bounded by
    ``jam_patience``; 100 m before one it is not."""
    open_road = Road(ROAD_RANGE, 0, 0.0, 0.0)
    times = tenths(ENTRY + 0.9, 61)
    rule = EndRule(replace(OPTIONS, jam_patience=6.0, max_episode_time=100.0), ENTRY)
    found = [rule.check(replace(observation(t, 0.0), road=open_road), 1.0) for t in times]
    assert found[:60] == [None] * 60 and found[60] is EndReason.JAMMED
    rule = EndRule(OPTIONS, ENTRY)
    times = times[:40]
    found = [rule.check(replace(observation(t, 0.0), road=open_road), 100.0) for t in times]
    assert found[20] is EndReason.STOPPED


def test_a_leader_beyond_a_junction_counts_by_the_room_it_leaves_beyond_it() -> None:
    """SUMO's own driver stands 1 m before a junction it has priority at, its leader 17 m
    ahead and driving off slowly: beyond the 10 m junction there is no room for it yet, and it
    does not enter a junction it could not leave (the Greenville export: 3 `stopped`). With
    the junction's far side 11 m ahead the stop is a wait; with no junction near, it is not."""
    leader = Neighbour(True, 17.0, 0.0, 0.5, "creeping off")
    times = tenths(ENTRY + 0.9, 30)
    rule = EndRule(OPTIONS, ENTRY)
    found = [rule.check(observation(t, 0.0, leader), ROAD_RANGE, 11.0) for t in times]
    assert found == [None] * 30
    rule = EndRule(OPTIONS, ENTRY)
    found = [rule.check(observation(t, 0.0, leader), ROAD_RANGE, 0.0) for t in times]
    assert found[20] is EndReason.STOPPED


def test_a_stand_at_a_lane_end_has_the_lane_ends_patience_once_the_lane_is_left() -> None:
    """SUMO's own driver stands at the end of a short lane until a gap opens, changes lanes
    standing, then waits a moment more: the stop began at the lane end, so it has
    ``lane_end_patience`` (before: 2 s, and ``stopped``)."""
    rule = EndRule(replace(OPTIONS, lane_end_patience=5.0), ENTRY)
    left = Road(ROAD_RANGE, 0, 0.0, 0.0)
    times = tenths(ENTRY + 0.9, 60)
    roads = [MERGING] * 10 + [left] * 50
    found = [
        rule.check(replace(observation(t, 0.0), road=road))
        for t, road in zip(times, roads, strict=True)
    ]
    assert found == [None] * 60  # 5 s after it left the lane: not yet 5 s


def test_a_red_light_before_a_lane_end_holds_the_ego_without_a_lane_end_verdict() -> None:
    """A lane that ends 10 m beyond a red light (a short edge whose lanes must be crossed,
    São Paulo's export): standing at the light is waiting for it, not a merge not made."""
    red_before_the_end = replace(MERGING, lane_end=10.8, stop_line=1.0)
    found = at_lane_end(EndRule(replace(OPTIONS, lane_end_patience=3.0), ENTRY), [0.0] * 60,
                        red_before_the_end)  # fmt: skip
    assert found == [None] * 60
    green = replace(red_before_the_end, stop_line=ROAD_RANGE)
    found = at_lane_end(EndRule(replace(OPTIONS, lane_end_patience=3.0), ENTRY), [0.0] * 31, green)
    assert found[30] is EndReason.LANE_END


def test_standing_for_the_jam_patience_ends_as_jammed_whatever_holds_the_ego() -> None:
    rule = EndRule(replace(OPTIONS, jam_patience=3.0, max_episode_time=100.0), ENTRY)
    queue = Neighbour(True, 4.0, 0.0, 0.0, "stopped ahead")
    found = verdicts(rule, [0.0] * 31, queue)
    assert found[:30] == [None] * 30  # a queue: no unreasonable stop, still patient
    assert found[30] is EndReason.JAMMED and EndReason.JAMMED.terminates
    rule = EndRule(replace(OPTIONS, jam_patience=3.0, max_episode_time=100.0), ENTRY)
    assert EndReason.JAMMED not in verdicts(rule, ([0.0] * 25 + [1.5]) * 3, queue)  # it moves
    at_a_light = Road(ROAD_RANGE, 0, 0.0, 0.0, stop_line=2.0)
    rule = EndRule(replace(OPTIONS, jam_patience=3.0, max_episode_time=100.0), ENTRY)
    assert at_lane_end(rule, [0.0] * 31, at_a_light)[30] is EndReason.JAMMED


def test_a_red_light_passed_ends_the_episode_only_where_the_option_asks() -> None:
    passed = Events(red_light=True)
    obs = observation(ENTRY + 1.0, 12.0, events=passed)
    assert EndRule(OPTIONS, ENTRY).check(obs) is None  # reported, the drive goes on
    ending = EndRule(replace(OPTIONS, end_on_red_light=True), ENTRY)
    assert ending.check(obs) is EndReason.RED_LIGHT and EndReason.RED_LIGHT.terminates
    crash = replace(obs, events=Events(collision=True, collision_with="h1", red_light=True))
    assert ending.check(crash) is EndReason.COLLISION  # a collision comes first
