"""The lane choice: which of keep / left / right can happen, and when a lane decision is taken.

A choice that cannot happen is masked, not learned away: a lane that does not exist, or any
change while one is under way (`Ego.changing_lane`, protocol 1.1), and (with `gap_rule`) a change
into a gap the observation already shows too small for a safe change: shorter than a safe
driver's secure gap, the reaction distance plus the difference of the braking distances, to the
new leader and from the new follower (`secure_gap`). A lane decision is taken at
every `every`-th decision only (the observation's `seq` says which), so that a lane change is a
decision and not a request repeated every 0.1 s; in between only "keep" is allowed. The masks
come from the observation alone, so a saved policy drives with the same rule it learned with.
Near the end of a lane the ego must leave (protocol 1.6) the change towards its route is the
only choice, at every decision, unmasked by the gap rule: staying is what fails there, and the
simulator's own gap check refuses the change into an unsafe gap (`route_side`), as it does IDM +
MOBIL's; what the policy learns there is the speed that finds a gap. Further back, a change away
from the route is masked where it would leave less than `ROUTE_KEEP_S` per lane to come back
before the lane it moves to ends (`leaves_route`): a policy does not leave the exit lane 400 m
before the exit, whatever its critic has learned so far. With a `reference` (a residual policy's
driver, IDM + MOBIL) the lane choices are that driver's: the one it makes is the only choice.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from protocol.messages import ROAD_RANGE, Observation

LANE_COMMANDS = (0, 1, -1)
"""Lane choice index -> lane-change command: keep, left, right."""
KEEP_ONLY = np.array([True])

SAFE_REACTION_S = 1.0
"""s: the reaction time of the secure gap (IDM's and Krauss' usual 1 s headway)."""
SAFE_DECELERATION = 4.5
"""m/s^2: the braking of the secure gap, a passenger car's comfortable maximum."""
SAFE_STANDSTILL_M = 2.5
"""m: the gap left at standstill (a typical minimum gap)."""
URGENT_S = 12.0
"""s: this close to the end of a lane the ego must leave, its change towards the route is not
masked by the gap rule (`route_side`)."""
ROUTE_KEEP_S = 2 * URGENT_S
"""s per lane to cross: a change away from the route that leaves less than this before the
lane it moves to ends is masked (`leaves_route`)."""
URGENT_MIN_SPEED = 10.0
"""m/s: the speed `URGENT_S` counts with when slower (a standing ego still sees its lane end)."""


def secure_gap(follower_speed: float, leader_speed: float) -> float:
    """The net gap (m) a follower at `follower_speed` needs behind a leader at `leader_speed` to
    be able to brake in time: standstill gap + reaction distance + braking distance difference."""
    braking = (follower_speed**2 - leader_speed**2) / (2 * SAFE_DECELERATION)
    return SAFE_STANDSTILL_M + follower_speed * SAFE_REACTION_S + max(0.0, braking)


def gap_is_safe(obs: Observation, direction: int) -> bool:
    """Whether the gap in the lane on side `direction` (1 left, -1 right) is not visibly too
    small: the ego behind the new leader, and the new follower behind the ego."""
    near = obs.neighbours
    lead, lag = (
        (near.left_leader, near.left_follower)
        if direction > 0
        else (near.right_leader, near.right_follower)
    )
    speed = obs.ego.speed
    if lead.present and lead.gap < secure_gap(speed, lead.speed):
        return False
    return not (lag.present and lag.gap < secure_gap(lag.speed, speed))


@dataclass(frozen=True)
class LaneChoice:
    """The lane choices of a policy (1: keep only, 3: keep/left/right) and their cadence."""

    n_choices: int = 1
    every: int = 1
    """A lane decision at every `every`-th decision (1: at each)."""
    gap_rule: bool = False
    """Mask changes into gaps shorter than the `secure_gap` (policies from before it: off)."""
    route_masks: bool = True
    """Near the end of a lane the route must leave, make the change towards the route the only
    choice (`route_side`) and mask changes away from it (`leaves_route`). False: the policy
    decides its mandatory changes too (a safety layer asks for the change only where the lane
    end is about to be missed, and counts it: `agent_client.drivers.safety`)."""
    reference: Callable[[Observation, bool], int] | None = field(
        default=None, compare=False, repr=False
    )
    """A driver's lane change for an observation (-1, 0, 1; the bool: whether a discretionary
    change may be made now, at a lane decision), made the only choice: a residual policy
    changes lanes as its reference does (`agent_client.drivers.policy.ActionScale`)."""

    def __post_init__(self) -> None:
        if self.n_choices not in (1, 3, 4):
            raise ValueError(f"n_choices must be 1, 3 or 4, got {self.n_choices}")
        if self.n_choices == 4 and self.reference is None:
            raise ValueError("4 lane choices need a reference: the first is its choice")
        if self.every < 1:
            raise ValueError(f"every must be >= 1, got {self.every}")

    def due(self, obs: Observation) -> bool:
        """Whether the decision answering `obs` may change lanes."""
        return obs.seq % self.every == 0

    def phase(self, obs: Observation) -> float:
        """Where `obs` lies between two lane decisions, in [0, 1)."""
        return lane_phase(obs.seq, self.every)

    def command(self, index: int, obs: Observation) -> int:
        """The lane-change command (-1, 0, +1) of choice `index` in `obs`."""
        if self.n_choices == 4:
            return self._reference_command(obs) if index == 0 else LANE_COMMANDS[index - 1]
        return LANE_COMMANDS[index]

    def index_of(self, command: int, obs: Observation) -> int:
        """The choice that gives `command` in `obs` (with 4 choices: the reference's, where
        the command is the one it makes)."""
        if self.n_choices == 4:
            return (
                0 if command == self._reference_command(obs) else 1 + LANE_COMMANDS.index(command)
            )
        return LANE_COMMANDS.index(command)

    def _reference_command(self, obs: Observation) -> int:
        """The reference's lane change in `obs` (0 while a change is under way or where its
        side has no lane)."""
        assert self.reference is not None
        ego = obs.ego
        command = self.reference(obs, self.due(obs)) if ego.changing_lane == 0 else 0
        return command if 0 <= ego.lane + command < ego.lane_count else 0

    def mask(self, obs: Observation) -> np.ndarray:
        """(n_choices,) bool: the choices that can happen now; at least one (keep, except
        where the route's change, or a `reference`'s, is the only choice). With 4 choices the
        reference's is always possible, before keep / left / right as the policy's own."""
        if self.n_choices == 1:
            return KEEP_ONLY
        if self.n_choices == 4:
            return np.concatenate([[True], self._own_mask(obs)])
        if self.reference is not None:
            command = self._reference_command(obs)
            return np.array([command == 0, command == 1, command == -1])
        return self._own_mask(obs)

    def _own_mask(self, obs: Observation) -> np.ndarray:
        """Keep / left / right as the policy's own choices. Near the end of a lane the route
        must leave (`route_side`), the change towards the route is the only choice with the
        route's masks; without them it is one choice among the others, offered at every
        decision and whatever the visible gap (the simulator refuses an unsafe one), as IDM +
        MOBIL asks it: a policy that may ask only once a second finds a tenth of the gaps, and
        the safety layer asking for it in between counted against a policy that had no say."""
        ego = obs.ego
        free, due = ego.changing_lane == 0, self.due(obs)
        route = route_side(obs)
        if self.route_masks and free and route and 0 <= ego.lane + route < ego.lane_count:
            return np.array([False, route == 1, route == -1])  # the route's change, or nothing
        keep_route = self.route_masks
        left = free and (due or route == 1) and ego.lane + 1 < ego.lane_count
        right = free and (due or route == -1) and ego.lane > 0
        left = left and not (keep_route and leaves_route(obs, 1))
        right = right and not (keep_route and leaves_route(obs, -1))
        if self.gap_rule:
            left = left and (route == 1 or gap_is_safe(obs, 1))
            right = right and (route == -1 or gap_is_safe(obs, -1))
        return np.array([True, left, right])


def route_side(obs: Observation) -> int:
    """The side (1 left, -1 right) the ego must move to soon to stay on its route, 0 if none:
    within `URGENT_S` seconds per lane to cross of the end of its lane (`Road`, protocol 1.6).
    There the change that way is asked for at every decision, whatever the gap: the
    simulator's own gap check, which accepts what it can, is the judge, as for IDM + MOBIL."""
    road = obs.road
    if road is None or not road.lanes_to_change:
        return 0
    lanes = abs(road.lanes_to_change)
    if road.lane_end > max(obs.ego.speed, URGENT_MIN_SPEED) * URGENT_S * lanes:
        return 0
    return 1 if road.lanes_to_change > 0 else -1


def away_from_route(obs: Observation, direction: int) -> tuple[float, int] | None:
    """For a change to `direction` (1 left, -1 right) that moves away from the route into a
    lane that ends (`Road`, protocol 1.6): where that lane ends (m) and the lanes then to
    cross; None for any other change (a lane beside that leads on along the route)."""
    road = obs.road
    if road is None:
        return None
    lane_end = road.left_lane_end if direction > 0 else road.right_lane_end
    lanes_after = abs(road.lanes_to_change - direction)
    if lane_end >= ROAD_RANGE or lanes_after <= abs(road.lanes_to_change):
        return None
    return lane_end, lanes_after


def leaves_route(obs: Observation, direction: int) -> bool:
    """Whether a change to `direction` moves away from the route where the lane it moves to
    ends within `ROUTE_KEEP_S` seconds per lane then to cross (`away_from_route`)."""
    away = away_from_route(obs, direction)
    if away is None:
        return False
    lane_end, lanes_after = away
    return lane_end <= max(obs.ego.speed, URGENT_MIN_SPEED) * ROUTE_KEEP_S * lanes_after


def lane_phase(seq: int, every: int) -> float:
    """Where decision `seq` lies between two lane decisions taken every `every`, in [0, 1)."""
    return (seq % every) / every


def choose_lanes(
    q: np.ndarray, valid: np.ndarray, epsilon: float, rng: np.random.Generator | None
) -> np.ndarray:
    """(N,) lane choice indices from Q values (N, K): the best valid choice; with `rng`
    (exploring), a uniformly random valid one instead with probability `epsilon`."""
    lanes = np.where(valid, q, -np.inf).argmax(axis=1).astype(np.int64)
    if rng is not None:
        for i in np.flatnonzero(rng.random(len(lanes)) < epsilon):
            lanes[i] = rng.choice(np.flatnonzero(valid[i]))
    return lanes
