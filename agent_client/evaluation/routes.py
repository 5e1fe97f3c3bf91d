"""How a driver follows its route where lanes end: the merge, the way to the exit, the move out
of a lane that drops (protocol 1.6, `protocol.messages.Road`).

A **route change** is a lane change that starts towards a lane that leads on (its direction is the
sign of ``road.lanes_to_change``); where the simulator drives the ego (``ego_driver``), which
reports no lane-change events, it is the step in which the ego moved to the next lane. For each one
`route_changes` keeps where and when it started, the gap it was made into (to the new leader and
from the new follower, in metres and in seconds of the ego's speed) and the braking it imposed on
the new follower: the hardest deceleration of the vehicle that is the ego's follower once the change
completed, over the next `IMPOSED_BRAKING_S` seconds, from its speeds on consecutive observations.
`route_figures` puts a driver's episodes together: the share that reached the end of the route, and
the median and extremes of the changes, with the smallest post-encroachment time of SUMO's SSM
device (PET is defined for merging paths; docs/protocol.md §4.7).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from agent_client.constants import MIN_MOVING_SPEED
from protocol.messages import AccelerationLimit, EndReason, Observation, Safety

IMPOSED_BRAKING_S = 5.0
"""Seconds after a route change completes in which the new follower's braking counts."""


@dataclass(frozen=True)
class RouteChange:
    """A lane change towards the route, when it started."""

    time: float
    """s since the ego was handed over."""
    position: float
    """m along the route (the ego's front)."""
    lane_end: float
    """m to the end of the lane it left (`Road.lane_end`)."""
    speed: float
    """m/s."""
    lead_gap: float | None
    """m to the new leader (None: nobody there within the sensor range)."""
    lag_gap: float | None
    """m from the new follower."""
    lead_headway: float | None
    """`lead_gap` / the ego's speed (s)."""
    lag_headway: float | None
    """`lag_gap` / the ego's speed (s)."""
    follower_braking: float | None
    """m/s², >= 0: the new follower's hardest deceleration after the change (None: nobody
    followed, or the change did not complete)."""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def route_changes(observations: Sequence[Observation]) -> list[RouteChange]:
    """Every lane change of an episode that started towards a lane that leads on."""
    if not observations:
        return []
    entry = observations[0].time
    changes = []
    for index, (before, after) in enumerate(itertools.pairwise(observations)):
        road = before.road
        if not (road and road.lanes_to_change):
            continue
        direction = _change(before, after)
        if direction * road.lanes_to_change <= 0:
            continue  # none, away from the route, or along it
        near = before.neighbours
        lead, lag = (
            (near.left_leader, near.left_follower)
            if direction > 0
            else (near.right_leader, near.right_follower)
        )
        speed = before.ego.speed
        lead_gap = lead.gap if lead.present else None
        lag_gap = lag.gap if lag.present else None
        changes.append(
            RouteChange(
                time=before.time - entry,
                position=before.ego.position,
                lane_end=road.lane_end,
                speed=speed,
                lead_gap=lead_gap,
                lag_gap=lag_gap,
                lead_headway=_headway(lead_gap, speed),
                lag_headway=_headway(lag_gap, speed),
                follower_braking=_imposed_braking(observations, index + 1),
            )
        )
    return changes


def _change(before: Observation, after: Observation) -> int:
    """The direction of a lane change that starts in this step (0: none): one the client
    commanded, or where the simulator drives the ego (which starts changes of its own) a move
    to the next lane of the same road."""
    if after.events.lane_change_started:
        return after.action.lane_change
    if after.action.acceleration_limited_by != AccelerationLimit.SIMULATOR:
        return 0
    moved = after.ego.lane - before.ego.lane
    return moved if abs(moved) == 1 and after.ego.lane_count == before.ego.lane_count else 0


def _headway(gap: float | None, speed: float) -> float | None:
    """A gap in seconds of the ego's speed (None without a vehicle, or standing)."""
    if gap is None or speed <= MIN_MOVING_SPEED:
        return None
    return max(gap, 0.0) / speed


def _imposed_braking(observations: Sequence[Observation], started: int) -> float | None:
    """The new follower's hardest deceleration (m/s², >= 0) from the completion of the lane
    change started at `observations[started]`, over `IMPOSED_BRAKING_S`; None if it did not
    complete or nobody followed."""
    if observations[started].action.acceleration_limited_by == AccelerationLimit.SIMULATOR:
        done: int | None = started  # the simulator's own change: in the new lane from here
    else:
        done = next(
            (
                i
                for i in range(started, len(observations))
                if observations[i].events.lane_change_completed
                or observations[i].events.lane_change_aborted
            ),
            None,
        )
    if done is None or not (observations[done].events.lane_change_completed or done == started):
        return None
    until = observations[done].time + IMPOSED_BRAKING_S
    braking: float | None = None
    for previous, current in itertools.pairwise(observations[done:]):
        if current.time > until:
            break
        was, now = previous.neighbours.follower, current.neighbours.follower
        if not (was.present and now.present and was.id and was.id == now.id):
            continue
        elapsed = current.time - previous.time
        if elapsed > 0:
            deceleration = max(0.0, (was.speed - now.speed) / elapsed)
            braking = deceleration if braking is None else max(braking, deceleration)
    return braking


def min_pet(safety: Safety | None) -> float | None:
    """The smallest post-encroachment time of an episode's conflicts (s), None if none had one."""
    if safety is None:
        return None
    pets = [c.min_pet for c in safety.conflicts if c.min_pet is not None]
    return min(pets) if pets else None


def route_figures(
    reasons: Sequence[str],
    changes: Sequence[Sequence[RouteChange]],
    pets: Sequence[float | None],
) -> dict[str, Any]:
    """One driver's figures over its episodes: each episode's end reason, its route changes and
    its smallest PET."""
    episodes = len(reasons)
    flat = [c for episode in changes for c in episode]

    def median(values: list[float]) -> float | None:
        return float(np.median(values)) if values else None

    braking = [c.follower_braking for c in flat if c.follower_braking is not None]
    known_pets = [p for p in pets if p is not None]
    return {
        "episodes": episodes,
        "arrival_share": sum(r == EndReason.END_OF_ROAD for r in reasons) / episodes
        if episodes
        else None,
        "lane_end_share": sum(r == EndReason.LANE_END for r in reasons) / episodes
        if episodes
        else None,
        "route_changes_per_episode": len(flat) / episodes if episodes else None,
        "median_lane_end_at_change": median([c.lane_end for c in flat]),
        "min_lane_end_at_change": min((c.lane_end for c in flat), default=None),
        "median_time_of_change": median([c.time for c in flat]),
        "median_lead_headway": median([c.lead_headway for c in flat if c.lead_headway is not None]),
        "median_lag_headway": median([c.lag_headway for c in flat if c.lag_headway is not None]),
        "min_lag_gap": min((c.lag_gap for c in flat if c.lag_gap is not None), default=None),
        "median_follower_braking": median(braking),
        "max_follower_braking": max(braking, default=None),
        "min_pet": min(known_pets, default=None),
    }
