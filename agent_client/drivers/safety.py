"""The safety layer of a learned driver: it overrides a decision only where a stated rule says
the drive is at stake, and every override is counted.

A shield (Alshiekh et al. 2018, "Safe reinforcement learning via shielding") that lets the
policy decide everything else. The rules, each judged on the observation alone:

* **a collision about to happen** — after the decision, the ego must still be able to stop
  behind its leader should the leader brake as hard as it can: the gap left after one decision
  at the proposed acceleration must exceed `MIN_GAP` plus the difference of the two braking
  distances at `EMERGENCY_DECELERATION` (the responsibility-sensitive safe distance, Shalev-
  Shwartz et al. 2017, with the reaction time of one decision). Else the acceleration is
  lowered to the highest that keeps it (or the bound's braking, if none does).
* **a red light about to be run** (and a way closed by the right of way, `Road.stop_line`) —
  where the ego can still stop before the line braking no harder than `EMERGENCY_DECELERATION`,
  but would no longer after one decision at the proposed acceleration, it brakes to stop there.
* **a yellow light's dilemma** — where, after one decision at the proposed acceleration, the
  ego could neither stop before a yellow light's line (braking at `EMERGENCY_DECELERATION`)
  nor reach it before the light turns red (holding its speed, within the speed limit), it
  brakes just enough to stop or accelerates just enough to reach it in time (up to
  `CLEARING_AT_MOST`), whichever is nearer to the proposal (a policy that brakes late for a
  yellow light ran the red one twice in 100 trips on an OSM city).
* **a lane end about to be missed** — within `URGENT_TIME` (and at least `URGENT_DISTANCE`) per
  lane to cross of the end of a lane the route must leave, the change towards the route is
  asked for whatever the policy chose (the simulator still refuses an unsafe gap); a change
  into a lane that ends that near is not made (the shipped roads policy moved at 33 m/s into
  an acceleration lane ending 110 m ahead and stood at its end: `sumo:ramp`); and the end of
  the lane is a stop line, as above.
* **a stop nothing calls for** — standing (slower than `STANDSTILL_SPEED`) where the servers
  would end the episode as an unreasonable stop (``stopped``, protocol §6: no leader within
  `STOP_GAP` or one that drives away, no stop line within `STOP_GAP`, no end of a lane the
  route must leave within `GAP_WAIT_DISTANCE` per lane to cross), the ego moves off at
  `MOVE_OFF` at least.

Where none applies, the policy's decision is applied as it is. `SafetyLayer.apply` returns the
decision and what it overrode; the episode loop counts the steps and the lane changes the layer
decided (`agent_client.evaluation.metrics.EpisodeSummary.safety_steps`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from agent_client.rl.lanes import away_from_route
from protocol.messages import ROAD_RANGE, Observation, SignalState, road_ahead

EMERGENCY_DECELERATION = 6.0
"""m/s²: the hardest braking assumed of the ego and of its leader (the ego type's decel)."""
MIN_GAP = 1.0
"""m left to the leader (or the stop line) after such braking."""
URGENT_TIME = 4.0
"""s at the ego's speed per lane to cross, before the end of a lane the route must leave,
within which the layer asks for the change the route needs."""
URGENT_DISTANCE = 40.0
"""m: the same, at least."""
STANDSTILL_SPEED = 1.0
"""m/s: slower than this counts as standing (the servers' ``stop_speed``)."""
STOP_GAP = 15.0
"""m: a leader or a stop line this close makes standing right (the servers' ``stop_gap``)."""
GAP_WAIT_DISTANCE = 150.0
"""m per lane to cross: this close to the end of a lane the route must leave, standing waits
for a gap (the servers' rule, protocol §6)."""
CLEARING_AT_MOST = 3.0
"""m/s²: the most the layer accelerates with to clear a yellow light's line before red."""
MOVE_OFF = 1.0
"""m/s²: the acceleration the layer moves a needlessly standing ego off with, at least."""
TOLERANCE = 1e-6
BISECTIONS = 40
"""Halvings of an acceleration interval (10 m/s² wide: to 1e-11 m/s²)."""


@dataclass(frozen=True, slots=True)
class Override:
    """What the layer changed in one decision."""

    acceleration: bool = False
    lane_change: bool = False
    rule: str = ""
    """Which rule: "collision", "stop_line", "yellow", "lane_end", "standstill" ("" none)."""

    @property
    def any(self) -> bool:
        return self.acceleration or self.lane_change


NONE = Override()


@dataclass(frozen=True)
class SafetyLayer:
    """The rules above, for decisions `interval` seconds apart and accelerations no lower than
    `lowest` (the server's bound)."""

    interval: float = 0.1
    lowest: float = -EMERGENCY_DECELERATION

    def apply(
        self, obs: Observation, acceleration: float, lane_change: int
    ) -> tuple[float, int, Override]:
        """The decision to send, and what of the policy's the layer overrode."""
        road = road_ahead(obs)
        lane, lane_rule, rule = lane_change, "", ""
        if not obs.ego.changing_lane:
            must = _route_side(obs)
            if must and lane_change != must and 0 <= obs.ego.lane + must < obs.ego.lane_count:
                lane, lane_rule = must, "lane_end"
            elif lane_change and _into_a_lane_end(obs, lane_change):
                lane, lane_rule = 0, "lane_end"
        safe = self._collision_free(obs)
        if acceleration > safe + TOLERANCE:
            acceleration, rule = safe, "collision"
        lane_end = road.lane_end if road.lanes_to_change else ROAD_RANGE
        stop = self._stop_before(obs.ego.speed, min(road.stop_line, lane_end))
        if acceleration > stop + TOLERANCE:
            acceleration = stop
            rule = rule or ("stop_line" if road.stop_line <= lane_end else "lane_end")
        yellow = self._out_of_the_dilemma(obs, acceleration)
        if yellow is not None:
            acceleration, rule = min(yellow, safe), rule or "yellow"
        if not rule and acceleration < MOVE_OFF - TOLERANCE and _needless_stop(obs):
            acceleration, rule = min(MOVE_OFF, safe, stop), "standstill"
        if not rule and not lane_rule:
            return acceleration, lane, NONE
        return acceleration, lane, Override(bool(rule), lane != lane_change, rule or lane_rule)

    def _collision_free(self, obs: Observation) -> float:
        """The highest acceleration after which the ego can still stop behind its leader were
        the leader to brake as hard as it can; infinite without a leader."""
        leader = obs.neighbours.leader
        if not leader.present:
            return math.inf
        v, v_lead, dt, b = (
            obs.ego.speed,
            max(leader.speed, 0.0),
            self.interval,
            EMERGENCY_DECELERATION,
        )

        def margin(a: float) -> float:
            v_next = max(v + a * dt, 0.0)
            driven = 0.5 * (v + v_next) * dt
            lead_next = max(v_lead - b * dt, 0.0)
            lead_driven = 0.5 * (v_lead + lead_next) * dt
            gap = leader.gap - driven + lead_driven
            return gap - MIN_GAP - max(0.0, (v_next**2 - lead_next**2) / (2 * b))

        return self._highest(margin)

    def _stop_before(self, speed: float, line: float) -> float:
        """The highest acceleration after which the ego can still stop `MIN_GAP` before a line
        `line` m ahead braking at `EMERGENCY_DECELERATION` (within that margin: full braking,
        standing stays standing); infinite without a line, or where it cannot stop before the
        line even now (then braking would not help: the line is passed)."""
        if line >= ROAD_RANGE:
            return math.inf
        b, dt = EMERGENCY_DECELERATION, self.interval
        if speed * speed > 2 * b * max(line, 0.0) + TOLERANCE:
            return math.inf  # too late to stop before it: the layer does not pretend it can

        def margin(a: float) -> float:
            v_next = max(speed + a * dt, 0.0)
            driven = 0.5 * (speed + v_next) * dt
            return line - driven - MIN_GAP - v_next * v_next / (2 * b)

        return self._highest(margin)

    def _out_of_the_dilemma(self, obs: Observation, acceleration: float) -> float | None:
        """The acceleration nearest `acceleration` that keeps the ego out of a yellow light's
        dilemma: where, after one decision at `acceleration`, it could neither stop before the
        line (braking at `EMERGENCY_DECELERATION`) nor reach it before the light turns red
        (holding its speed, no faster than the speed limit), the highest that still lets it
        stop or the lowest that reaches the line in time (up to `CLEARING_AT_MOST`), whichever
        is nearer; `CLEARING_AT_MOST` where neither does. None where no rule applies (no
        yellow light ahead, or either way open)."""
        road = road_ahead(obs)
        if road.signal_state != SignalState.YELLOW or road.signal_distance >= ROAD_RANGE:
            return None
        line, left, speed = road.signal_distance, road.signal_switch, obs.ego.speed
        limit = obs.ego.speed_limit if obs.ego.speed_limit > 0.0 else math.inf
        b, dt = EMERGENCY_DECELERATION, self.interval

        def after(a: float) -> tuple[float, float]:
            v_next = max(speed + a * dt, 0.0)
            return v_next, 0.5 * (speed + v_next) * dt

        def stop_margin(a: float) -> float:
            v_next, driven = after(a)
            return line - driven - v_next * v_next / (2 * b)

        def reaches(a: float) -> float:  # the margin past the line at the switch
            v_next, driven = after(a)
            return driven + min(v_next, limit) * max(left - dt, 0.0) - line - MIN_GAP

        if stop_margin(acceleration) >= -TOLERANCE or reaches(acceleration) >= 0.0:
            return None
        options: list[float] = []
        stop = self._highest(stop_margin)
        if stop_margin(stop) >= -TOLERANCE:
            options.append(stop)
        if reaches(CLEARING_AT_MOST) >= 0.0:  # the least acceleration that reaches it in time
            options.append(_last_good(lambda a: reaches(a) >= 0.0, CLEARING_AT_MOST, acceleration))
        if not options:
            return CLEARING_AT_MOST  # neither: the nearer it gets, the sooner it is across
        return min(options, key=lambda a: abs(a - acceleration))

    def _highest(self, margin: Callable[[float], float]) -> float:
        """The highest acceleration (within [lowest, +inf)) whose `margin` is not negative:
        infinite where any will do, `lowest` where none does; bisection on a margin that
        falls with the acceleration."""
        top = 10.0
        if margin(top) >= 0.0:
            return math.inf
        if margin(self.lowest) < 0.0:
            return self.lowest
        return _last_good(lambda a: margin(a) >= 0.0, self.lowest, top)


def _last_good(good: Callable[[float], bool], inside: float, outside: float) -> float:
    """Bisection between `inside` (where `good` holds) and `outside` (where it does not): the
    point nearest `outside` found where it still holds."""
    for _ in range(BISECTIONS):
        middle = 0.5 * (inside + outside)
        if good(middle):
            inside = middle
        else:
            outside = middle
    return inside


def _needless_stop(obs: Observation) -> bool:
    """Standing where the road does not make the ego wait (the servers' unreasonable stop)."""
    if obs.ego.speed >= STANDSTILL_SPEED:
        return False
    leader = obs.neighbours.leader
    if leader.present and (leader.gap <= STOP_GAP or leader.speed <= obs.ego.speed):
        return False
    road = road_ahead(obs)
    if road.stop_line <= STOP_GAP:
        return False
    lanes = abs(road.lanes_to_change)
    return not (lanes > 0 and road.lane_end <= GAP_WAIT_DISTANCE * lanes)


def _urgent_distance(obs: Observation, lanes: int) -> float:
    """m before the end of a lane within which `lanes` changes are about to be missed."""
    return lanes * max(URGENT_DISTANCE, obs.ego.speed * URGENT_TIME)


def _into_a_lane_end(obs: Observation, direction: int) -> bool:
    """Whether a change to `direction` (1 left, -1 right) moves away from the route into a lane
    that ends within the urgent distance of the changes it would then need."""
    away = away_from_route(obs, direction)
    return away is not None and away[0] <= _urgent_distance(obs, away[1])


def _route_side(obs: Observation) -> int:
    """The side of the change the route needs now (within the urgent distance of the end of
    the ego's lane), 0 when none."""
    road = obs.road
    if road is None or not road.lanes_to_change:
        return 0
    if road.lane_end > _urgent_distance(obs, abs(road.lanes_to_change)):
        return 0
    return 1 if road.lanes_to_change > 0 else -1
