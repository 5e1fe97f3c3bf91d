"""Route changes (protocol 1.6): where a driver merged, into which gap, the braking it imposed."""

from __future__ import annotations

from dataclasses import replace

import pytest

from agent_client.evaluation.routes import min_pet, route_changes, route_figures
from protocol.messages import (
    ROAD_RANGE,
    AccelerationLimit,
    AppliedAction,
    Conflict,
    Ego,
    Events,
    Neighbour,
    Neighbours,
    Observation,
    Road,
    Safety,
)

ABSENT = Neighbour(False, 200.0, 0.0, 0.0)


def merge_episode(simulator: bool = False) -> list[Observation]:
    """An ego on an acceleration lane changes left at t = 1 s into a gap 30 m behind a leader
    and 20 m ahead of a follower, which then brakes at 1.5 m/s² for a second."""
    observations = []
    for k in range(40):
        t = 60.0 + 0.1 * k
        lane = 0 if k < 15 else 1
        changing = 1 if 10 <= k < 20 else 0
        events = Events(
            lane_change_started=(k == 10 and not simulator),
            lane_change_completed=(k == 20 and not simulator),
        )
        lag_speed = 20.0 - (1.5 * 0.1 * (k - 20) if 20 < k <= 30 else 0.0 if k <= 20 else 1.5)
        if lane == 0:
            near = Neighbours(
                Neighbour(True, 30.0, 3.2, 20.0, "lead"), Neighbour(True, 20.0, 3.2, 20.0, "lag"),
                ABSENT, ABSENT, ABSENT, ABSENT,
            )  # fmt: skip
            road = Road(200.0 - 2.0 * k, 1, ROAD_RANGE, 0.0)
        else:
            near = Neighbours(
                ABSENT, ABSENT, Neighbour(True, 30.0, 0.0, 20.0, "lead"),
                Neighbour(True, 20.0, 0.0, lag_speed, "lag"), ABSENT, ABSENT,
            )  # fmt: skip
            road = Road(ROAD_RANGE, 0, 0.0, 170.0)
        limit = AccelerationLimit.SIMULATOR if simulator else ""
        action = AppliedAction(0.0, 1 if k == 10 else 0, 0.0, 1 if k == 10 else 0, limit)
        ego = Ego(20.0, 0.0, lane, 3, 100.0 + 2.0 * k, 27.78, 0 if simulator else changing)
        observations.append(Observation(k, t, ego, near, events, action, road=road))
    return observations


def test_a_merge_is_found_with_its_place_gap_and_imposed_braking() -> None:
    (change,) = route_changes(merge_episode())
    assert change.time == pytest.approx(0.9)  # decided on the observation before the start
    assert change.lane_end == pytest.approx(182.0)
    assert (change.lead_gap, change.lag_gap) == (30.0, 20.0)
    assert change.lead_headway == pytest.approx(1.5) and change.lag_headway == pytest.approx(1.0)
    assert change.follower_braking == pytest.approx(1.5)


def test_the_simulators_own_change_is_found_where_the_lane_changes() -> None:
    (change,) = route_changes(merge_episode(simulator=True))
    assert change.time == pytest.approx(1.4)  # the step in which the ego moved lanes
    assert change.follower_braking == pytest.approx(1.5)


def test_a_change_away_from_the_route_is_no_route_change() -> None:
    away = [replace(o, road=replace(o.road, lanes_to_change=-1)) if o.road else o
            for o in merge_episode()]  # fmt: skip
    assert route_changes(away) == []


def test_the_figures_of_a_driver() -> None:
    changes = [route_changes(merge_episode()), []]
    safety = Safety((Conflict("h1", 61.0, 62.0, None, None, 1.2, 0.0, 0.0, 0.0),), 3.0, 3.0, 2.0)
    figures = route_figures(["end_of_road", "lane_end"], changes, [min_pet(safety), None])
    assert figures["arrival_share"] == 0.5 and figures["lane_end_share"] == 0.5
    assert figures["route_changes_per_episode"] == 0.5
    assert figures["max_follower_braking"] == pytest.approx(1.5)
    assert figures["min_pet"] == 1.2
