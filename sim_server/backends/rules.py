"""The driving rules every simulator behind the bridge applies alike, written once.

How a requested acceleration is limited, when a lane-change command is refused, when a lane
change under way is given up, and when an episode ends. A backend supplies what only its
simulator knows (the speed limit, the lanes, its own gap check) and reports the verdicts in the
observation's `AppliedAction`, `Events` and `reason`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Literal

from protocol.messages import (
    ROAD_RANGE,
    AccelerationLimit,
    EndReason,
    LaneChangeRefusal,
    Observation,
)
from sim_server.backends.options import EpisodeOptions

LANE_CHANGE_TIMEOUT_S = 5.0
"""A commanded lane change not completed this long after it started is given up
(`Events.lane_change_aborted`). SUMO drops a lane-change request it could not begin within the
request's 2 s (the gap closed meanwhile); without a timeout the ego would wait for it forever."""

_EPSILON_S = 1e-9
"""Slack on time comparisons, so that a sum of 0.1 s steps reaches a whole number of seconds."""
GAP_WAIT_DISTANCE = 150.0
"""m per lane to cross: this close to the end of a lane its route must leave (`Road`), an ego
that stands waits for a gap to the lane it needs, which is no unreasonable stop (as it waits at
a stop line)."""


def limit_acceleration(
    request: float, speed: float, limit: float, low: float, high: float, dt: float
) -> tuple[float, AccelerationLimit | Literal[""]]:
    """The acceleration to apply for `dt` seconds at `speed`, and which rule bound it ("" none).

    Clipped to the action's bounds [`low`, `high`], then lowered so that the next speed stays
    within the speed `limit` (never below `low`), then raised so that it does not go below 0.
    """
    applied = min(max(request, low), high)
    why: AccelerationLimit | Literal[""] = AccelerationLimit.BOUNDS if applied != request else ""
    if speed + applied * dt > limit:
        applied, why = max((limit - speed) / dt, low), AccelerationLimit.SPEED_LIMIT
    if speed + applied * dt < 0.0:
        applied, why = -speed / dt, AccelerationLimit.STANDSTILL
    return applied, why


@dataclass(frozen=True, slots=True)
class LaneChangeUnderWay:
    """A commanded lane change under way, from the step that started it until it completes or
    is given up."""

    target: int
    """The lane the ego moves to, in the simulator's own numbering."""
    direction: int
    """As commanded and reported in `Ego.changing_lane`: 1 left, -1 right."""
    started: float
    """Simulation time of the step that started it (s)."""

    def expired(self, now: float) -> bool:
        """Not completed within `LANE_CHANGE_TIMEOUT_S`: give it up."""
        return now - self.started >= LANE_CHANGE_TIMEOUT_S - _EPSILON_S


def lane_change_refusal(
    direction: int,
    *,
    simulator_drives: bool,
    under_way: LaneChangeUnderWay | None,
    ego_lane: Callable[[], tuple[int, int]],
    gap_ok: Callable[[int], bool],
) -> LaneChangeRefusal | Literal[""]:
    """Why a lane change in `direction` (1 left, -1 right, 0 none) must not start now, or "".

    The first rule that applies, in this order: the simulator drives the ego; a lane change is
    still under way; there is no lane on that side (`ego_lane` gives the ego's lane, counted
    from 0 at the rightmost, and the number of lanes); the simulator's own gap check `gap_ok`
    fails. `ego_lane` and `gap_ok` are called only when their rule is reached: each may cost a
    query of the simulator.
    """
    if not direction:
        return ""
    if simulator_drives:
        return LaneChangeRefusal.SIMULATOR_DRIVES
    if under_way is not None:
        return LaneChangeRefusal.IN_PROGRESS
    lane, lane_count = ego_lane()
    if not 0 <= lane + direction < lane_count:
        return LaneChangeRefusal.NO_LANE
    if not gap_ok(direction):
        return LaneChangeRefusal.GAP_TOO_SMALL
    return ""


class EndRule:
    """When an episode ends, judged on each observation after a step.

    In this order: a collision; the end of the road; a red light passed, where
    ``end_on_red_light`` asks for it; a stand at the end of a lane that does not continue the
    ego's route (slower than ``stop_speed`` within ``stop_gap`` of its end, `Observation.road`,
    for ``lane_end_patience`` seconds: a merge not made, an exit missed); an unreasonable stop
    (slower than ``stop_speed`` for ``stop_patience`` seconds, with no leader or one more than
    ``stop_gap`` ahead and faster (beyond a junction: more than ``stop_gap`` beyond its far
    side, room to leave the junction), where the road does not make the ego wait: not within
    ``stop_gap`` of a stop line, `Road.stop_line`, nor within `GAP_WAIT_DISTANCE` per lane to
    cross of the end of a lane it must leave, waiting for a gap, nor within ``stop_gap`` of a
    junction where it gives way, whatever `Road.stop_line` says (a driver may wait longer than
    the simulator's judgement: for a longer gap, for room beyond the junction); a stop that
    began waiting has ``lane_end_patience`` seconds once the wait is over); a stand of
    ``jam_patience`` seconds, whatever holds the ego (a jam that does not clear);
    ``max_episode_time`` seconds after the ego's entry (the only truncation).
    """

    __slots__ = (
        "_end_on_red_light",
        "_entry_time",
        "_jam_patience",
        "_lane_end_patience",
        "_stop_gap",
        "_stop_patience",
        "_stop_speed",
        "_time_limit",
        "at_lane_end_since",
        "standing_since",
        "stopped_at_line",
        "stopped_since",
    )

    def __init__(self, options: EpisodeOptions, entry_time: float) -> None:
        self._stop_speed = options.stop_speed
        self._stop_gap = options.stop_gap
        self._stop_patience = options.stop_patience - _EPSILON_S
        self._lane_end_patience = options.lane_end_patience - _EPSILON_S
        self._entry_time = entry_time
        self._time_limit = options.max_episode_time - _EPSILON_S
        self._jam_patience = options.jam_patience - _EPSILON_S
        self._end_on_red_light = options.end_on_red_light
        self.standing_since: float | None = None
        """Time of the first observation of the current stand (None: moving)."""
        self.stopped_since: float | None = None
        """Time of the first observation of the current stop (None: not stopped)."""
        self.at_lane_end_since: float | None = None
        """Time of the first observation of the current stand at a lane end (None: none)."""
        self.stopped_at_line = False
        """The current stop began at a stop line."""

    @property
    def entry_time(self) -> float:
        """Simulation time at which the client took over the ego."""
        return self._entry_time

    def check(
        self, obs: Observation, give_way: float = ROAD_RANGE, across: float = 0.0
    ) -> EndReason | None:
        """The reason the episode ends with `obs`, or None while it goes on; `give_way`: m to
        the next junction where the ego has no priority, where the simulator knows it (a driver
        may wait there longer than `Road.stop_line` judges it must: `jam_patience` bounds it);
        `across`: m to the far side of the next junction, where the simulator knows it (0:
        none near): a leader beyond it counts by the room it leaves there, for a driver that
        does not enter a junction it could not leave."""
        if obs.events.collision:
            return EndReason.COLLISION
        if obs.events.end_of_road:
            return EndReason.END_OF_ROAD
        if obs.events.red_light and self._end_on_red_light:
            return EndReason.RED_LIGHT
        standing = self._standing_at_lane_end(obs)
        if standing is not None:
            if standing >= self._lane_end_patience:
                return EndReason.LANE_END
            self.stopped_since = None  # waiting there for a gap is no unreasonable stop
            self.stopped_at_line = True  # nor, for a while, once the gap is taken
        elif self._stopped(obs, give_way, across):
            return EndReason.STOPPED
        if self._jammed(obs):
            return EndReason.JAMMED
        if obs.time - self._entry_time >= self._time_limit:
            return EndReason.TIME_LIMIT
        return None

    def _standing_at_lane_end(self, obs: Observation) -> float | None:
        """Seconds the ego has stood (slower than ``stop_speed``) within ``stop_gap`` of the
        end of its lane, or None when it does not (or a stop line within ``stop_gap`` holds
        it: a lane that ends a few metres beyond a red light, São Paulo's export)."""
        road = obs.road
        if (
            road is None
            or road.lane_end > self._stop_gap
            or obs.ego.speed >= self._stop_speed
            or road.stop_line <= self._stop_gap  # a red light or a junction holds it there
        ):
            self.at_lane_end_since = None
            return None
        if self.at_lane_end_since is None:
            self.at_lane_end_since = obs.time
        return obs.time - self.at_lane_end_since

    def _stopped(self, obs: Observation, give_way: float, across: float) -> bool:
        leader = obs.neighbours.leader
        speed = obs.ego.speed
        gap = leader.gap - across if 0.0 < across < leader.gap else leader.gap
        if speed >= self._stop_speed:
            self.stopped_at_line = False
        elif self._made_to_wait(obs) or give_way <= self._stop_gap:
            self.stopped_at_line = True  # waiting for the way to open, for a gap, at a junction
            self.stopped_since = None
            return False
        if speed < self._stop_speed and (
            not leader.present or (gap > self._stop_gap and speed < leader.speed)
        ):
            if self.stopped_since is None:
                self.stopped_since = obs.time
            patience = self._lane_end_patience if self.stopped_at_line else self._stop_patience
            return obs.time - self.stopped_since >= patience
        self.stopped_since = None
        return False

    def _made_to_wait(self, obs: Observation) -> bool:
        """The road makes the ego wait: a stop line within ``stop_gap``, or the end of a lane
        it must leave within `GAP_WAIT_DISTANCE` per lane to cross (a gap to wait for)."""
        road = obs.road
        if road is None:
            return False
        if road.stop_line <= self._stop_gap:
            return True
        lanes = abs(road.lanes_to_change)
        return lanes > 0 and road.lane_end <= GAP_WAIT_DISTANCE * lanes

    def _jammed(self, obs: Observation) -> bool:
        """Stood (slower than ``stop_speed``) for ``jam_patience`` seconds."""
        if obs.ego.speed >= self._stop_speed:
            self.standing_since = None
            return False
        if self.standing_since is None:
            self.standing_since = obs.time
        return obs.time - self.standing_since >= self._jam_patience


def ended(obs: Observation, reason: EndReason) -> Observation:
    """`obs` as the last observation of its episode, terminated or truncated for `reason`."""
    terminates = reason.terminates
    return replace(obs, terminated=terminates, truncated=not terminates, reason=reason)
