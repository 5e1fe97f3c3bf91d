"""Reward functions over named observations: the paper's r_a1-r_a4 and r_lc, our "safe" and
"wave" (the ring's stop-and-go waves).

Every reward is computed on the learner's side from two consecutive `Observation`s, so any
simulator behind the protocol gets the same reward. One signature, ``reward(prev, obs, dt)``,
where `prev` is None on the first step and `dt` the decision interval (s). Select one by name
with `make_reward`; `REWARDS` lists them.

Units. The wire is SI (m, s, m/s, m/s^2). The paper's Table 1 quotes v and Δv in km/h and d in m;
its own arithmetic (Eq. 8 bis, ``2 * 80/3.6 / 100``) turns v into m/s wherever it multiplies the
headway h_d. So here: a speed that stands alone is in km/h (x `KMH_PER_MS`), h_d * v is a distance
in metres (v in m/s), and d is the net leader gap in metres. With no leader the wire reports
``leader.gap`` = the sensor range (200 m on our servers), which the paper's formulas take as d.

Appendix A: `max_reward` is r_max at the paper's ideal steady state and `q_upper_bound` is
r_max / (1 - gamma), e.g. 0.56 and 56 for r_a3 with gamma = 0.99.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property, partial
from typing import Any

from agent_client.constants import JERK_COMFORT_LIMIT, KMH_PER_MS, PAPER_SPEED_LIMIT
from agent_client.errors import UsageError
from agent_client.rl.lanes import route_side, secure_gap
from protocol.messages import (
    ROAD_RANGE,
    AppliedAction,
    Ego,
    Events,
    LaneChangeRefusal,
    Neighbour,
    Neighbours,
    Observation,
    Traffic,
)

RewardFn = Callable[[Observation | None, Observation, float], float]
"""reward(prev, obs, dt) -> float; `prev` is None on the first step of an episode."""


# --------------------------------------------------------------------------- Table 1 thresholds

COLLISION_GAP = 0.0
"""m: C when the leader's net gap is below this (or the simulator reports a collision)."""
REVERSE_SPEED = 0.0
"""m/s: R when the ego's speed is below this."""
JERK_LIMIT = JERK_COMFORT_LIMIT
"""m/s^3: U when |jerk| exceeds this (the paper's "maximum jerk passengers cannot notice")."""
LOW_SPEED = 1.0
"""m/s: L needs the ego slower than this ..."""
FAR_GAP = 15.0
"""m: ... and the leader farther than this (and the ego slower than the leader)."""
GAP_TOO_SMALL = LaneChangeRefusal.GAP_TOO_SMALL
"""`AppliedAction.lane_change_refused` reason that sets G."""
SIMULATOR_DRIVES = LaneChangeRefusal.SIMULATOR_DRIVES
"""The refusal of every command while the simulator drives the ego (not the policy's doing)."""

# --------------------------------------------------------------------------- paper parameters

PAPER_HEADWAY = 2.0
"""s: the paper's desired time headway h_d."""
SPEED_NORM_KMH = PAPER_SPEED_LIMIT * KMH_PER_MS
"""km/h: v' = v / 80 km/h (Eq. 7)."""
GAP_NORM = 100.0
"""m: d' = d / 100 m (Eq. 7)."""
SPEED_DIFF_NORM_KMH = 40.0
"""km/h: Table 1 normalises Δv by 40 km/h (used by Eq. 6)."""
REFERENCE_SPEED = PAPER_SPEED_LIMIT
"""m/s: 80 km/h, the speed of the paper's r_max and the fallback speed limit."""
PENALTY_CR = -1.0
"""Normalised penalty of C or R (x100 in Eqs. 5, 6 and 8)."""
PENALTY_U = -0.8
"""Normalised penalty of U (and of G in Eq. 12)."""
PENALTY_L = -0.5
"""Normalised penalty of L."""
MIN_INTERVAL = 1e-3
"""s: shorter times between observations give no jerk or acceleration estimate (0)."""
DIVISION_EPSILON = 1e-3
"""Floor of Eq. 6's denominator |(d - h_d v) Δv'| (m, times the dimensionless Δv')."""
ROUTE_LANES = 3
"""Lanes to change that the route's shaping counts at most (`route_potential`)."""
GAP_READY_SHARE = 0.5
"""Share of the next lane's weight in the route's potential that an open gap beside the ego
takes off (`route_potential`)."""
GAP_READY_SLACK = 20.0
"""m short of a secure gap at which a gap counts as not open at all (`gap_readiness`)."""


# --------------------------------------------------------------------------- state flags


@dataclass(frozen=True, slots=True)
class Flags:
    """The state flags of the paper's Table 1 for one step; O is `otherwise`."""

    collision: bool = False
    """C: a collision event, or the leader's net gap below 0 m."""
    reverse: bool = False
    """R: the ego's speed below 0 m/s."""
    uncomfortable: bool = False
    """U: |jerk| above 5.6 m/s^3."""
    low_speed: bool = False
    """L: crawling (< 1 m/s) though the leader is far (> 15 m, faster) or absent."""
    gap_too_small: bool = False
    """G: a lane change refused because the target gap is too small."""

    @property
    def otherwise(self) -> bool:
        """O: none of the other flags."""
        return not (
            self.collision
            or self.reverse
            or self.uncomfortable
            or self.low_speed
            or self.gap_too_small
        )

    def letters(self) -> str:
        """The set flags as the paper's letters, e.g. "CU", or "O"."""
        pairs = (
            ("C", self.collision),
            ("R", self.reverse),
            ("U", self.uncomfortable),
            ("L", self.low_speed),
            ("G", self.gap_too_small),
        )
        return "".join(letter for letter, on in pairs if on) or "O"


def interval(prev: Observation | None, obs: Observation, dt: float) -> float:
    """Time between the observations (s), or `dt` if there is no earlier one or no progress."""
    if prev is not None and obs.time > prev.time:
        return obs.time - prev.time
    return dt


def jerk(prev: Observation | None, obs: Observation, dt: float) -> float:
    """The ego's jerk (m/s^3): change of realised acceleration over the elapsed time; 0 if none."""
    if prev is None:
        return 0.0
    elapsed = interval(prev, obs, dt)
    if elapsed < MIN_INTERVAL:
        return 0.0
    return (obs.ego.acceleration - prev.ego.acceleration) / elapsed


def is_collision(obs: Observation) -> bool:
    """C: the simulator reports a collision, or the leader overlaps the ego (gap < 0 m)."""
    leader = obs.neighbours.leader
    return (
        obs.events.collision
        or obs.reason == "collision"
        or (leader.present and leader.gap < COLLISION_GAP)
    )


def is_low_speed(obs: Observation) -> bool:
    """L: d > 15 m and v < 1 m/s and Δv = v - v_leader < 0.

    Without a leader the road ahead is free (the wire's gap is the sensor range, > 15 m) and
    there is no leader speed to compare with, so crawling below 1 m/s counts as L by itself.
    """
    v = obs.ego.speed
    if v >= LOW_SPEED:
        return False
    leader = obs.neighbours.leader
    if not leader.present:
        return True
    return leader.gap > FAR_GAP and v - leader.speed < 0.0


def flags(prev: Observation | None, obs: Observation, dt: float) -> Flags:
    """Table 1's state flags of the step that ended in `obs` (jerk needs `prev`)."""
    return Flags(
        collision=is_collision(obs),
        reverse=obs.ego.speed < REVERSE_SPEED,
        uncomfortable=abs(jerk(prev, obs, dt)) > JERK_LIMIT,
        low_speed=is_low_speed(obs),
        gap_too_small=obs.action.lane_change_refused == GAP_TOO_SMALL,
    )


def _paper_penalty(f: Flags, scale: float) -> float | None:
    """The C/R, U, L cases shared by Eqs. 5-8 (first match wins); None in state O."""
    if f.collision or f.reverse:
        return scale * PENALTY_CR
    if f.uncomfortable:
        return scale * PENALTY_U
    if f.low_speed:
        return scale * PENALTY_L
    return None


def _leader_gap(obs: Observation, no_leader_gap: float | None) -> float:
    """d (m): the leader's net gap; with no leader the wire's sensor range, or the override."""
    leader = obs.neighbours.leader
    if not leader.present and no_leader_gap is not None:
        return no_leader_gap
    return leader.gap


# --------------------------------------------------------------------------- paper rewards


@dataclass(frozen=True)
class AdditionReward:
    """r_a1, Eq. 5: -100 C/R, -80 U, -50 L, else h_d v - d.

    h_d v is the desired gap in metres (v in m/s), so the O term is "desired minus actual gap"
    (m): it grows with speed and shrinks with distance. Its supremum h_d v is reached at d = 0,
    i.e. it pays for tailgating - the paper saw r_a1 drivers "accelerate until they collide".
    Without a leader d is the sensor range: h_d v - 200, a large negative reward.
    """

    desired_headway: float = PAPER_HEADWAY
    """h_d (s)."""
    no_leader_gap: float | None = None
    """d (m) without a leader; None takes the wire's value, the sensor range."""

    def __call__(self, prev: Observation | None, obs: Observation, dt: float) -> float:
        penalty = _paper_penalty(flags(prev, obs, dt), 100.0)
        if penalty is not None:
            return penalty
        return self.desired_headway * obs.ego.speed - _leader_gap(obs, self.no_leader_gap)


@dataclass(frozen=True)
class MultiplicationReward:
    """r_a2, Eq. 6: -100 C/R, -80 U, -50 L, else v / |(d - h_d v) Δv'|.

    v in the numerator in km/h (Table 1), h_d v in metres (v in m/s) and Δv' = (v - v_leader)
    in km/h / 40 km/h (Table 1's normalisation). The denominator vanishes exactly at the ideal
    state (d = h_d v or Δv = 0), so it is floored at `epsilon`: the reward is finite but can
    reach v / epsilon (80 000 at 80 km/h) - the paper's "difficult to define the boundary".
    Without a leader d is the sensor range and v_leader is 0 (the wire's absent neighbour).
    """

    desired_headway: float = PAPER_HEADWAY
    """h_d (s)."""
    epsilon: float = DIVISION_EPSILON
    """Floor of the denominator."""
    no_leader_gap: float | None = None
    """d (m) without a leader; None takes the wire's value, the sensor range."""

    def __call__(self, prev: Observation | None, obs: Observation, dt: float) -> float:
        penalty = _paper_penalty(flags(prev, obs, dt), 100.0)
        if penalty is not None:
            return penalty
        v = obs.ego.speed
        d = _leader_gap(obs, self.no_leader_gap)
        dv_norm = (v - obs.neighbours.leader.speed) * KMH_PER_MS / SPEED_DIFF_NORM_KMH
        denominator = abs((d - self.desired_headway * v) * dv_norm)
        return v * KMH_PER_MS / max(denominator, self.epsilon)


@dataclass(frozen=True)
class NormalisedReward:
    """r_a3, Eq. 7: -1 C or R, -0.8 U, -0.5 L, else v' - d' (v' = v / 80 km/h, d' = d / 100 m).

    Faithful, pitfalls included (cf-learning-facts.md): without a leader d is the sensor range,
    so with 200 m the O term is about v/22.2 - 2 <= -1 per step, no better than the crash
    penalty, and ending the episode looks attractive; and the O term grows as d shrinks, so it
    pays for tailgating. `scale` multiplies every case (Eq. 8 is scale = 100).
    """

    scale: float = 1.0
    """Multiplies penalties and the O term."""
    no_leader_gap: float | None = None
    """d (m) without a leader; None takes the wire's value, the sensor range (faithful)."""

    def __call__(self, prev: Observation | None, obs: Observation, dt: float) -> float:
        penalty = _paper_penalty(flags(prev, obs, dt), self.scale)
        if penalty is not None:
            return penalty
        v_norm = obs.ego.speed * KMH_PER_MS / SPEED_NORM_KMH
        d_norm = _leader_gap(obs, self.no_leader_gap) / GAP_NORM
        return self.scale * (v_norm - d_norm)


@dataclass(frozen=True)
class MagnifiedReward(NormalisedReward):
    """r_a4, Eq. 8: r_a3 magnified 100 times (-100 C/R, -80 U, -50 L, 100 (v' - d'))."""

    scale: float = 100.0
    """Multiplies penalties and the O term."""


def _neighbour_slots(neighbours: Neighbours) -> tuple[Neighbour, ...]:
    return (
        neighbours.left_leader,
        neighbours.left_follower,
        neighbours.leader,
        neighbours.follower,
        neighbours.right_leader,
        neighbours.right_follower,
    )


def follower_acceleration(before: Neighbour, obs: Observation, elapsed: float) -> float:
    """Estimated acceleration change (m/s^2) of the vehicle seen as `before` one step earlier.

    The wire carries neighbours' speeds, not accelerations, so the change is estimated as the
    vehicle's speed change over the step divided by the elapsed time (its acceleration before the
    step taken as 0). The vehicle is found in `obs` by id in any of the six slots (after the ego
    changed lanes it sits in another slot); absent, unnamed or no longer seen: 0.
    """
    if not before.present or not before.id or elapsed < MIN_INTERVAL:
        return 0.0
    for now in _neighbour_slots(obs.neighbours):
        if now.present and now.id == before.id:
            return (now.speed - before.speed) / elapsed
    return 0.0


@dataclass(frozen=True)
class LaneChangeReward:
    """r_lc, Eq. 12: -1 C/R, -0.8 U or G, -0.5 L, v' when following, and on the step where a
    lane change starts 2 v' - 0.1 (|Δa| + |Δa_CF| + |Δa_LF|).

    Δa is the ego's change of realised acceleration over the step (m/s^2); Δa_CF and Δa_LF those
    of the followers in the current (source) lane and the target lane, taken from `prev` and
    estimated by `follower_acceleration`. Absolute values: with the formula's minus sign, signed
    MOBIL increments would reward making a follower brake, the opposite of the paper's text ("if
    LC leads sharp brake to followers ... it will not get a great reward, and even be punished");
    with magnitudes any sharp change - braking or not, ego or follower - costs.
    """

    lane_change_gain: float = 2.0
    """Factor of v' on a lane-change step."""
    acceleration_weight: float = 0.1
    """Weight of the summed acceleration changes (per m/s^2)."""

    def __call__(self, prev: Observation | None, obs: Observation, dt: float) -> float:
        f = flags(prev, obs, dt)
        if f.collision or f.reverse:
            return PENALTY_CR
        if f.uncomfortable or f.gap_too_small:
            return PENALTY_U
        if f.low_speed:
            return PENALTY_L
        v_norm = obs.ego.speed * KMH_PER_MS / SPEED_NORM_KMH
        if not obs.events.lane_change_started:
            return v_norm
        return self.lane_change_gain * v_norm - self.acceleration_weight * self.disturbance(
            prev, obs, dt
        )

    @staticmethod
    def disturbance(prev: Observation | None, obs: Observation, dt: float) -> float:
        """|Δa| + |Δa_CF| + |Δa_LF| (m/s^2) of a lane-change step; 0 without `prev`."""
        if prev is None:
            return 0.0
        elapsed = interval(prev, obs, dt)
        direction = obs.action.lane_change or obs.action.requested_lane_change
        before = prev.neighbours
        target = {1: before.left_follower, -1: before.right_follower}.get(direction)
        total = abs(obs.ego.acceleration - prev.ego.acceleration)
        total += abs(follower_acceleration(before.follower, obs, elapsed))
        if target is not None:
            total += abs(follower_acceleration(target, obs, elapsed))
        return total


# --------------------------------------------------------------------------- our reward


@dataclass(frozen=True)
class SafeReward:
    """Safe, efficient, comfortable driving without r_a3's pitfalls (recommended default).

    Per step without a collision::

        r = (v / v_limit) * H(h) * (1 - w_ttc * P(TTC)) * C(jerk)   drive term, in [0, 1]
            - w_refused [refused]  or  - w_lane_change [a lane change started]     <= 0.1

    with the comfort gate C(jerk) = 1 - w_jerk * min((jerk / 5.6)^2, 1), and
    ``-collision_penalty`` (20) on a collision or reversing step, so every step lies in
    [-0.1, 1] or is exactly -20 (or ``-stop_penalty``, at most that, on an unreasonable stop).

    - Efficiency v / v_limit (``obs.ego.speed_limit``), clipped to [0, 1]: speeding never pays.
    - Headway h = gap / v; H(h) = exp(-ln(h / h_d)^2 / (2 sigma^2)), the log-normal headway
      likelihood of Zhu et al. (2020) with mu = ln(h_d), rescaled to peak 1 at h = h_d = 1.2 s,
      sigma = 0.3 below h_d: H(1.0 s) = 0.83, H(0.8 s) = 0.40, H(0.5 s) = 0.01, so tailgating
      earns less than following at the same speed (h_d lies between the evaluation's 1.0 s safety
      line and IDM's 1.5 s, so the learner follows a little closer than IDM). Above h_d,
      sigma_far (default inf) keeps H = 1: a far leader scores like an empty road, which has
      H = 1 - good free driving, never below a crash. A finite sigma_far pays for closing up
      to h_d, and w_far bounds what a far leader can cost (H >= 1 - w_far).
    - TTC = gap / (v - v_leader) when closing in; P = 1 - TTC / 4 s below 4 s, growing to 1 as
      TTC -> 0: the share of the drive term lost (a gate, not a subtraction, so the penalty keeps
      the step >= 0; see (a)).
    - Comfort: a smooth quadratic gate on jerk, (jerk / 5.6)^2 = 1 at the paper's threshold,
      where the step keeps 1 - w_jerk = 50 % of its drive term; no cliff for exploration noise to
      trip, and a cost in proportion to what the step earns, so a chattering (bang-bang)
      controller loses half its reward whatever its speed (docs/learner-design.md, "`safe`",
      says why a gate and not an additive cost).

    - ``stop_penalty`` (default 0) costs the step that ends an episode as an unreasonable
      stop (the server's ``stopped``: standing with the road ahead free), a failure like a
      crash, where 0 leaves it an end like the road's, which pays nothing more either.
    - The route (protocol 1.6, `Observation.road`): ``lane_end_penalty`` costs the step that
      ends an episode at the end of a lane it had to leave (``lane_end``: a merge not made, an
      exit missed), and ``route_weight`` shapes the way there with the potential
      Phi = -|lanes to change| (1 - lane_end / ROAD_RANGE) (Ng et al. 1999): each step adds
      w (Phi(obs) - Phi(prev)), so a lane change towards the route earns what staying would
      cost later, and the end comes into view long before the discount horizon of ~5 s does.
      On roads whose lanes all go on (cf, cflc, the ring) both are always 0.

    (a) Crashing never pays. Normal driving is >= 0 per step; the only negative collision-free
    terms are lane-change costs, at most c = 0.1 per step, the route's shaping, which sums to
    at most w x `ROUTE_LANES` over an episode, and the stop and lane-end penalties, which end
    the episode; the two ends may not cost more than the collision penalty. Even the worst
    collision-free future is worth >= -c / (1 - gamma) = -0.1 / 0.01 = -10 at gamma = 0.99,
    above the -20 of crashing now: at no state is a crash (or any episode end) better than going on.
    `min_collision_penalty(gamma)` gives the bound for other gammas.
    Full throttle (3 m/s^2) from 15 m/s, 30 m behind a 15 m/s leader (see the test
    test_safe_full_throttle_crash_is_worse_than_following): the crash after 5.4 s returns 6.4 at
    gamma = 0.99 (the headway and TTC gates take the drive term to 0 while closing in, then
    -20 * 0.99^53 = -11.7), against 67.3 for following at 15 m/s; under r_a3 the same runs
    return 26.9 and 37.4, so there the crash earns 72 % of the follower's return.
    """

    desired_headway: float = 1.2
    """h_d (s): where the headway term peaks (below IDM's 1.5 s, above the 1.0 s safety line)."""
    headway_sigma: float = 0.3
    """Log-normal sigma of H below h_d."""
    headway_far_sigma: float = math.inf
    """Log-normal sigma of H above h_d; inf keeps H = 1 for long headways."""
    headway_far_weight: float = 1.0
    """Share of the drive term a far leader can cost, in [0, 1]: above h_d,
    H = 1 - w_far (1 - exp(-ln(h / h_d)^2 / (2 sigma_far^2))), so H never falls below
    1 - w_far. 1 lets the far side fall to 0, as the plain log-normal does."""
    ttc_threshold: float = 4.0
    """s: TTC below this costs part of the drive term."""
    ttc_weight: float = 1.0
    """Share of the drive term lost as TTC -> 0, in [0, 1]."""
    jerk_weight: float = 0.5
    """Share of the drive term lost at |jerk| >= 5.6 m/s^3 (quadratic below), in [0, 1]."""
    refused_weight: float = 0.1
    """Cost of a refused lane change: a too small gap (G), no lane on that side, or one already
    under way (a policy that asks at every step for a change it cannot get pays for it); not
    of one towards the route near the end of the lane, refused for the gap."""
    lane_change_weight: float = 0.01
    """Cost of starting a lane change (against dithering)."""
    collision_penalty: float = 20.0
    """Cost of a collision (or of reversing), > `min_collision_penalty(0.99)` = 18."""
    stop_penalty: float = 0.0
    """Cost of the step that ends an episode as an unreasonable stop (``stopped``: standing
    with the road ahead free); 0 leaves it an episode end like the road's."""
    lane_end_penalty: float = 5.0
    """Cost of the step that ends an episode at the end of a lane the ego had to leave
    (``lane_end``)."""
    route_weight: float = 2.0
    """w of the route's potential shaping, per lane to change (0: none)."""
    red_light_penalty: float = 50.0
    """Cost of the step in which the ego passed a red light (`Events.red_light`, protocol 1.8):
    more than what driving on instead of waiting can earn within the discount horizon (at
    gamma = 0.98, at most 1 / (1 - gamma) = 50), so that waiting for the green pays."""
    fallback_speed_limit: float = REFERENCE_SPEED
    """m/s: used if the observation carries no positive speed limit."""

    def __post_init__(self) -> None:
        if self.desired_headway <= 0.0 or self.headway_sigma <= 0.0:
            raise ValueError("desired_headway and headway_sigma must be positive")
        if self.headway_far_sigma <= 0.0 or self.ttc_threshold <= 0.0:
            raise ValueError("headway_far_sigma and ttc_threshold must be positive")
        if not 0.0 <= self.ttc_weight <= 1.0:
            raise ValueError(f"ttc_weight must be within [0, 1], got {self.ttc_weight}")
        if not 0.0 <= self.headway_far_weight <= 1.0:
            raise ValueError(
                f"headway_far_weight must be within [0, 1], got {self.headway_far_weight}"
            )
        if not 0.0 <= self.jerk_weight <= 1.0:
            raise ValueError(f"jerk_weight must be within [0, 1], got {self.jerk_weight}")
        if min(self.refused_weight, self.lane_change_weight, self.collision_penalty,
               self.stop_penalty, self.lane_end_penalty, self.route_weight,
               self.red_light_penalty) < 0.0:  # fmt: skip
            raise ValueError("lane-change weights, penalties and route weight must be non-negative")
        if self.stop_penalty > self.collision_penalty:
            raise ValueError(
                f"stop_penalty {self.stop_penalty} must not exceed collision_penalty "
                f"{self.collision_penalty}: a crash would then pay better than a stop"
            )
        if self.lane_end_cost > self.collision_penalty:
            raise ValueError(
                f"lane_end_penalty + {ROUTE_LANES} x route_weight = {self.lane_end_cost:g} must "
                f"not exceed collision_penalty {self.collision_penalty}: a crash would then pay "
                "better than missing the route"
            )

    def __call__(self, prev: Observation | None, obs: Observation, dt: float) -> float:
        if is_collision(obs) or obs.ego.speed < REVERSE_SPEED:
            return -self.collision_penalty
        if self.stop_penalty and obs.reason == "stopped":
            return -self.stop_penalty
        if obs.events.red_light:
            return -self.red_light_penalty
        route = self.route_weight * (route_potential(obs) - route_potential(prev)) if prev else 0.0
        if obs.reason == "lane_end":
            return route - self.lane_end_penalty
        limit = obs.ego.speed_limit if obs.ego.speed_limit > 0.0 else self.fallback_speed_limit
        efficiency = min(max(obs.ego.speed / limit, 0.0), 1.0)
        drive = efficiency * self.headway_score(obs) * (1.0 - self.ttc_weight * self.ttc_cost(obs))
        comfort = 1.0 - self.jerk_weight * min((jerk(prev, obs, dt) / JERK_LIMIT) ** 2, 1.0)
        lane = 0.0
        refused = obs.action.lane_change_refused
        if refused and refused != SIMULATOR_DRIVES and not _trying_for_route(prev, obs):
            lane = self.refused_weight
        elif obs.events.lane_change_started:
            lane = self.lane_change_weight
        return drive * comfort - lane + route

    def headway_score(self, obs: Observation) -> float:
        """H in [0, 1]: 1 at h_d, with no leader, or standing still; 0 when overlapping."""
        leader = obs.neighbours.leader
        if not leader.present:
            return 1.0
        if leader.gap <= 0.0:
            return 0.0
        if obs.ego.speed <= 0.0:
            return 1.0
        headway = leader.gap / obs.ego.speed
        if not headway > 1e-9:  # also catches an underflow to 0 (log domain)
            return 0.0
        ratio = math.log(min(headway, 1e9) / self.desired_headway)
        if ratio < 0.0:
            return math.exp(-(ratio**2) / (2.0 * self.headway_sigma**2))
        far = math.exp(-(ratio**2) / (2.0 * self.headway_far_sigma**2))
        if self.headway_far_weight == 1.0:
            return far  # the plain log-normal, to the last bit
        return 1.0 - self.headway_far_weight * (1.0 - far)

    def ttc_cost(self, obs: Observation) -> float:
        """P in [0, 1]: 1 - TTC / threshold when closing in below the threshold, else 0."""
        leader = obs.neighbours.leader
        closing = obs.ego.speed - leader.speed
        if not leader.present or closing <= 0.0:
            return 0.0
        ttc = max(leader.gap, 0.0) / closing
        return max(0.0, 1.0 - ttc / self.ttc_threshold)

    def worst_step(self) -> float:
        """Lowest reward of a collision-free step that lets the episode go on (<= 0)."""
        return -max(self.refused_weight, self.lane_change_weight)

    @property
    def lane_end_cost(self) -> float:
        """The most missing the route can cost: the lane-end penalty and the whole shaping."""
        return self.lane_end_penalty + ROUTE_LANES * self.route_weight

    def min_collision_penalty(self, gamma: float) -> float:
        """Penalty above which a crash is worse than the worst collision-free future (going on
        at `worst_step` for ever, or ending in an unreasonable stop or at a lane end)."""
        _check_gamma(gamma)
        return max(-self.worst_step() / (1.0 - gamma), self.stop_penalty, self.lane_end_cost)


def _trying_for_route(prev: Observation | None, obs: Observation) -> bool:
    """A change towards the route near the end of the lane, refused for the gap: asking at
    every decision there is how a gap is caught, not a fault (`agent_client.rl.lanes`)."""
    return (
        prev is not None
        and obs.action.lane_change_refused == GAP_TOO_SMALL
        and obs.action.requested_lane_change == route_side(prev) != 0
    )


def route_potential(obs: Observation) -> float:
    """Phi of the route's shaping, in [-`ROUTE_LANES`, 0]: minus the lanes the ego must still
    cross, each weighted by how near the end of its lane is (0 at `ROAD_RANGE` or beyond), the
    next one's weight lowered by up to `GAP_READY_SHARE` as the gap beside the ego on that side
    opens (`gap_readiness`): what the ego's speed does to find a gap pays before the change."""
    road = obs.road
    if road is None or not road.lanes_to_change:
        return 0.0
    lanes = min(abs(road.lanes_to_change), ROUTE_LANES)
    near = 1.0 - min(road.lane_end, ROAD_RANGE) / ROAD_RANGE
    ready = GAP_READY_SHARE * gap_readiness(obs, 1 if road.lanes_to_change > 0 else -1)
    return -near * (lanes - ready)


def gap_readiness(obs: Observation, direction: int) -> float:
    """In [0, 1]: 1 when the gaps to the new leader and from the new follower on side
    `direction` are at least a safe driver's secure gaps (`agent_client.rl.lanes.secure_gap`),
    falling to 0 as the shorter falls `GAP_READY_SLACK` m short of its own."""
    near, speed = obs.neighbours, obs.ego.speed
    lead, lag = (
        (near.left_leader, near.left_follower)
        if direction > 0
        else (near.right_leader, near.right_follower)
    )
    margins = [0.0]
    if lead.present:
        margins.append(lead.gap - secure_gap(speed, lead.speed))
    if lag.present:
        margins.append(lag.gap - secure_gap(lag.speed, speed))
    return min(max(1.0 + min(margins) / GAP_READY_SLACK, 0.0), 1.0)


# --------------------------------------------------------------------------- the ring's waves


def traffic_speeds(obs: Observation) -> tuple[float, ...]:
    """Every vehicle's speed (m/s): the ego's and its traffic's (the reset option
    ``report_traffic``); a `UsageError` if the observation carries no traffic."""
    if obs.traffic is None:
        raise UsageError(
            "this reward reads the traffic's speeds: send the reset option report_traffic "
            "(agent-client train --option report_traffic=true)"
        )
    return (obs.ego.speed, *obs.traffic.speed)


@dataclass(frozen=True)
class WaveReward:
    """Damp stop-and-go waves (the ring): drive at the traffic's mean speed, smoothly, with a
    buffer gap, instead of copying the leader's oscillation.

    Per step without a collision::

        r = E(v_mean) * M(v - v_mean) * H(h) * (1 - P(TTC)) * A(a)     in [0, 1]

    and ``-collision_penalty`` (20) on a collision or reversing step.

    - v_mean is the mean speed of every vehicle (the ego and its ``traffic``: send the reset
      option ``report_traffic``; on a multi-ego ring the traffic is the humans).
      E = clip(v_mean / v_limit, 0, 1) is the system-level term of Flow's ring reward (Wu et
      al.: the mean speed of all vehicles), which on a ring only damping raises (everyone's
      long-run speed is the same there), and which an ego that blocks the ring takes to 0;
      ``spread_weight`` optionally takes a share sigma / v_limit off it (sigma: the speeds'
      standard deviation across vehicles). ``own_speed_weight`` w mixes in the ego's own
      speed, E = (1 - w) E + w clip(v / v_limit, 0, 1): with w = 0 a ring that the ego has
      brought to a stop is a trap (v = v_mean = 0 earns 0, and so does every small step
      away from it, M's slope being 0 there), which w > 0 tilts towards driving off.
    - M = exp(-(v - v_mean)^2 / (2 tol^2)), tol 1 m/s: Stern et al.'s FollowerStopper drives at
      the traffic's average speed, so that the gap to its leader, not its speed, absorbs the
      leader's oscillation. An ego that has to brake to a stop in a wave loses the steps it
      stands, which pays for keeping a buffer; and M is a step reward (the ego's speed against
      the others' mean now), not a consequence tens of seconds later, so a short horizon
      learns it.
    - H (the log-normal headway gate of `safe`, knee at 1.0 s, the evaluation's safety line) and
      the TTC gate P (below 4 s) keep the ego off its leader's bumper; as in `safe` they are
      gates, so every collision-free step is >= 0 and crashing never pays.
    - A(a) = 1 - w_accel * min((a / 1.5 m/s^2)^2, 1): accelerating and braking are what carry
      a wave on (Flow's ring reward penalises the AV's |a|); 1.5 m/s^2 is the humans' braking.

    Measured on the ring (policies trained with it, at 1-11 of 22 egos): docs/learner.md,
    "Learning to damp the ring's waves". ``wave_own`` in `REWARDS` is this with w = 0.5.
    """

    speed_tolerance: float = 1.0
    """m/s: tol of M, the speed difference to the traffic's mean that keeps 61 % of the step."""
    desired_headway: float = 1.0
    """h_d (s): below it the headway gate H falls (1.0 s: the evaluation's safety line)."""
    headway_sigma: float = 0.3
    """Log-normal sigma of H below h_d."""
    ttc_threshold: float = 4.0
    """s: TTC below this costs part of the step."""
    accel_scale: float = 1.5
    """m/s^2: |a| at which the acceleration gate takes its full share."""
    accel_weight: float = 0.5
    """Share of the step lost at |a| >= accel_scale (quadratic below), in [0, 1]."""
    spread_weight: float = 0.0
    """Factor of sigma / v_limit taken off E (0: E is the mean speed alone)."""
    own_speed_weight: float = 0.0
    """Share of E that is the ego's own speed over the limit, in [0, 1]."""
    collision_penalty: float = 20.0
    """Cost of a collision (or of reversing)."""
    fallback_speed_limit: float = REFERENCE_SPEED
    """m/s: used if the observation carries no positive speed limit."""

    def __post_init__(self) -> None:
        if min(self.speed_tolerance, self.desired_headway, self.headway_sigma) <= 0.0:
            raise ValueError("speed_tolerance, desired_headway and headway_sigma must be positive")
        if self.ttc_threshold <= 0.0 or self.accel_scale <= 0.0:
            raise ValueError("ttc_threshold and accel_scale must be positive")
        if not 0.0 <= self.accel_weight <= 1.0:
            raise ValueError(f"accel_weight must be within [0, 1], got {self.accel_weight}")
        if min(self.spread_weight, self.collision_penalty) < 0.0:
            raise ValueError("spread_weight and collision_penalty must be non-negative")
        if not 0.0 <= self.own_speed_weight <= 1.0:
            raise ValueError(f"own_speed_weight must be within [0, 1], got {self.own_speed_weight}")

    def __call__(self, prev: Observation | None, obs: Observation, dt: float) -> float:
        speeds = traffic_speeds(obs)
        if is_collision(obs) or obs.ego.speed < REVERSE_SPEED:
            return -self.collision_penalty
        mean = math.fsum(speeds) / len(speeds)
        match = math.exp(-(((obs.ego.speed - mean) / self.speed_tolerance) ** 2) / 2.0)
        gates = self._gates.headway_score(obs) * (1.0 - self._gates.ttc_cost(obs))
        accel = 1.0 - self.accel_weight * min((obs.ego.acceleration / self.accel_scale) ** 2, 1.0)
        return self.efficiency(obs) * match * gates * accel

    @cached_property
    def _gates(self) -> SafeReward:
        """`safe`'s headway and TTC gates with this reward's knee and threshold."""
        return SafeReward(
            desired_headway=self.desired_headway,
            headway_sigma=self.headway_sigma,
            ttc_threshold=self.ttc_threshold,
        )

    def efficiency(self, obs: Observation) -> float:
        """E in [0, 1]: the traffic's mean speed over the limit, less its spread if weighted, mixed
        with the ego's own speed over the limit if weighted."""
        speeds = traffic_speeds(obs)
        limit = obs.ego.speed_limit if obs.ego.speed_limit > 0.0 else self.fallback_speed_limit
        mean = math.fsum(speeds) / len(speeds)
        spread = math.sqrt(math.fsum((v - mean) ** 2 for v in speeds) / len(speeds))
        speed = min(max(mean / limit, 0.0), 1.0)
        system = speed * (1.0 - min(self.spread_weight * spread / limit, 1.0))
        own = min(max(obs.ego.speed / limit, 0.0), 1.0)
        return (1.0 - self.own_speed_weight) * system + self.own_speed_weight * own


# --------------------------------------------------------------------------- registry

REWARDS: dict[str, Callable[..., RewardFn]] = {
    "ra1": AdditionReward,
    "ra2": MultiplicationReward,
    "ra3": NormalisedReward,
    "ra4": MagnifiedReward,
    "rlc": LaneChangeReward,
    "safe": SafeReward,
    "wave": WaveReward,
    "wave_own": partial(WaveReward, own_speed_weight=0.5),
}
"""Reward factories by name; keyword parameters are the dataclass fields."""
TRAFFIC_REWARDS = frozenset({"wave", "wave_own"})
"""The rewards that read every vehicle's speed: the trainer asks for ``report_traffic``."""

DEFAULT_REWARD = "safe"


def make_reward(name: str = DEFAULT_REWARD, **params: float | None) -> RewardFn:
    """The reward called `name`, with keyword parameters; `UsageError` for an unknown name."""
    try:
        factory = REWARDS[name]
    except KeyError:
        known = ", ".join(sorted(REWARDS))
        raise UsageError(f"unknown reward {name!r}; known rewards: {known}") from None
    return factory(**params)


# --------------------------------------------------------------------------- Appendix A


def steady_state(speed: float, headway: float, dt: float = 0.1) -> tuple[Observation, Observation]:
    """Two consecutive observations of ideal following: constant `speed` (m/s, also the speed
    limit) at time headway `headway` (s) behind a leader of the same speed, no events; the
    leader is the traffic (``report_traffic``), so the traffic's mean speed is `speed` too."""
    absent = Neighbour(False, 200.0, 0.0, 0.0)
    leader = Neighbour(True, headway * speed, 0.0, speed, "leader")
    neighbours = Neighbours(absent, absent, leader, absent, absent, absent)
    action = AppliedAction(0.0, 0, 0.0, 0)

    def at(seq: int) -> Observation:
        ego = Ego(speed, 0.0, 0, 1, speed * dt * seq, speed)
        ahead = headway * speed + 5.0 + speed * dt * seq
        traffic = Traffic(
            ("leader",), ("human",), (0,), (ahead,), (speed,), (0.0,), ("",), (200.0,), (0.0,)
        )
        return Observation(seq, dt * seq, ego, neighbours, Events(), action, traffic=traffic)

    return at(1), at(2)


def max_reward(
    name: str,
    *,
    speed: float = REFERENCE_SPEED,
    headway: float | None = None,
    **params: float | None,
) -> float:
    """r_max of Appendix A: the reward at the paper's ideal steady state.

    As in the paper's Eq. 8 bis: the ego at `speed` (80 km/h, also the speed limit) follows a
    leader of the same speed at the desired headway (`headway`, default the reward's own h_d or
    2 s), without jerk or lane change. r_a3 gives 1 - 2 * 22.2 / 100 = 0.56; r_a4 56; r_lc 1;
    safe 1; r_a1 0 (its supremum h_d v is at d = 0); r_a2 v / epsilon = 80 000.
    """
    reward = make_reward(name, **params)
    if headway is None:
        headway = float(getattr(reward, "desired_headway", PAPER_HEADWAY))
    prev, obs = steady_state(speed, headway)
    return reward(prev, obs, obs.time - prev.time)


def _check_gamma(gamma: float) -> None:
    if not 0.0 <= gamma < 1.0:
        raise ValueError(f"gamma must be within [0, 1), got {gamma}")


def q_upper_bound(reward: str | float, gamma: float, **params: Any) -> float:
    """Eq. 4 / A9: r_max / (1 - gamma); `reward` is r_max, or a reward name whose r_max
    `max_reward` computes with `params` (its speed, headway and the reward's own parameters)."""
    _check_gamma(gamma)
    r_max = max_reward(reward, **params) if isinstance(reward, str) else float(reward)
    return r_max / (1.0 - gamma)
