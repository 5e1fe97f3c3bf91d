"""IDM with MOBIL lane changes: the baseline that changes lanes (``idm+mobil``).

MOBIL (Kesting, Treiber and Helbing 2007, "General lane-changing model MOBIL for car-following
models", TRR 1999) judges a lane change by the accelerations the car-following model (IDM)
gives before and after it:

* **safety**: the new follower must not have to brake harder than ``b_safe``;
* **incentive**: the ego's gain plus ``politeness`` times its old and new followers' gains must
  exceed ``threshold``, plus ``keep_right_bias`` for a change to the left (minus it to the
  right: European rules).

Parameters: p = 0.25 (Treiber's "realistic" range is 0-0.5), b_safe = 4 m/s², threshold 0.2
m/s², bias 0.2 m/s² (the typical values of Treiber's MOBIL page and Kesting et al. 2007).
Discretionary changes are considered once a second, as in highway-env.

IDM's acceleration also stops the ego at a stop line (protocol 1.7, `Road.stop_line`). On top, the
**strategic** changes a route needs (`protocol.messages.Road`, protocol 1.6): a lane
that ends is a standing obstacle for IDM (as highway-env models a lane end); when the ego's lane
must be left (``lanes_to_change`` not 0) within a look-ahead that grows with the lanes to cross
and the speed, MOBIL's incentive test is skipped and only safety counts, every decision; near
the lane end the ego also follows the leader in the target lane, so that it slots in behind it
rather than stopping beside a gap. No change ever leads away from the route, nor into a lane
that ends within the look-ahead. The other vehicles' accelerations are IDM's with the default
parameters, from the six neighbours the ego observes (their lengths taken as 5 m).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from agent_client.drivers.idm import IDMParams, idm_acceleration, stop_line_acceleration
from agent_client.rl.lanes import gap_is_safe, secure_gap
from protocol.messages import ROAD_RANGE, Neighbour, Observation, Road, road_ahead

VEHICLE_LENGTH = 5.0
"""m: the length assumed of the ego and of every neighbour (the observation gives none)."""
FALL_BACK = 4.0
"""m/s below the target lane's speed at which the ego lets a vehicle there pass."""
SPEED_GAIN = 0.5
"""1/s: how fast the ego takes up the target lane's speed (a 2 s time constant)."""
JERK_LIMIT = 5.0
"""m/s³: how fast the acceleration changes from one decision to the next, unless braking at
`MobilParams.stop_deceleration` or harder: under the 5.6 m/s³ a passenger notices
(docs/evaluation.md)."""
STANDSTILL_SPEED = 5.0
"""m/s: below this a residual policy's correction fades out towards a standstill (`at_stake`)."""
URGENT_TIME = 6.0
"""s: see `MobilParams.urgent_distance`."""
DECISION_INTERVAL = 0.1
"""s: the decision interval assumed until two observations have shown it."""


def jerk_limited(wanted: float, previous: float, interval: float) -> float:
    """`wanted` changed from `previous` no faster than `JERK_LIMIT` over `interval` seconds."""
    step = JERK_LIMIT * interval
    return min(max(wanted, previous - step), previous + step)


ALIGN_GAIN = 0.5
"""1/s: the speed offset per metre the ego is off the middle of the gap it moves into."""


@dataclass(frozen=True)
class MobilParams:
    """MOBIL's parameters, and the look-ahead of the strategic changes."""

    politeness: float = 0.25
    """p: the weight of the followers' gains (0 selfish, 0.5 and more altruistic)."""
    threshold: float = 0.2
    """m/s²: the net gain a discretionary change needs."""
    keep_right_bias: float = 0.2
    """m/s²: added to the threshold of a change to the left, taken off one to the right."""
    safe_deceleration: float = 4.0
    """b_safe, m/s²: the hardest braking a change may impose on the new follower (and, for
    its new leader, on the ego)."""
    strategic_time: float = 15.0
    """s: a change the route needs is started within (speed x this + `strategic_margin`) m of
    the lane end per lane to cross."""
    strategic_margin: float = 100.0
    """m: see `strategic_time`."""
    urgent_distance: float = 150.0
    """m: this close to the lane end (or `URGENT_TIME` at its speed, if farther), the ego asks
    for the change the route needs at every decision, whatever the gap."""
    decision_interval: float = 1.0
    """s between two discretionary lane decisions."""
    stop_deceleration: float = 3.0
    """m/s²: the ego brakes for the end of a lane it must leave once stopping there needs this
    much (a firm but normal braking)."""

    def to_dict(self) -> dict[str, float]:
        return asdict(self)


class IDMMobilDriver:
    """IDM car following with MOBIL lane changes and the changes the route needs."""

    name = "idm+mobil"

    def __init__(self, params: IDMParams | None = None, mobil: MobilParams | None = None) -> None:
        self.params = params or IDMParams()
        self.mobil = mobil or MobilParams()
        self.others = IDMParams()
        """The model of the other vehicles, whose gains and braking MOBIL weighs."""
        self._next_decision = -math.inf
        self._last_time = -math.inf
        self.interval = DECISION_INTERVAL
        """Seconds between the last two observations: the jerk limit's time step."""

    def act(self, obs: Observation) -> tuple[float, int]:
        """Acceleration (m/s²) and lane change (-1, 0, +1) for one observation."""
        if obs.seq == 0:
            self._next_decision = -math.inf
        elif obs.time > self._last_time:
            self.interval = obs.time - self._last_time
        self._last_time = obs.time
        acceleration = self.acceleration(obs, self.interval)
        due = obs.time >= self._next_decision
        if due and not self._strategic(obs, road_ahead(obs)):
            self._next_decision = obs.time + self.mobil.decision_interval - 1e-9
        return acceleration, self.lane_change(obs, discretionary=due)

    def lane_change(self, obs: Observation, discretionary: bool = True) -> int:
        """The lane change alone (-1, 0, +1), which keeps no state: the one the route needs
        where it is due (at every decision: safe by MOBIL's criterion, or urgent, the
        simulator refusing an unsafe gap), else with `discretionary` MOBIL's choice (the
        caller decides how often to ask: once a second)."""
        road = road_ahead(obs)
        must = _sign(road.lanes_to_change)
        if obs.ego.changing_lane:
            return 0
        if self._strategic(obs, road):
            return must if self._safe(obs, must) or self._urgent(obs, road) else 0
        return self._discretionary(obs, road, must) if discretionary else 0

    def acceleration(self, obs: Observation, interval: float = DECISION_INTERVAL) -> float:
        """The acceleration alone (m/s²) for decisions every `interval` seconds, which keeps no
        state: `wanted_acceleration`, changed at a comfortable jerk unless braking hard."""
        acceleration = self.wanted_acceleration(obs)
        if acceleration <= -self.mobil.stop_deceleration:
            return acceleration  # braking hard: at once
        return jerk_limited(acceleration, obs.ego.acceleration, interval)

    def wanted_acceleration(self, obs: Observation) -> float:
        """The acceleration (m/s²) this driver wants before its jerk limit: IDM behind the
        leader, before the end of a lane the route must leave, and into the gap beside it where
        the change the route needs cannot be made yet (what a policy trained on top of this
        driver corrects, `agent_client.drivers.policy.ActionScale`)."""
        road = road_ahead(obs)
        ego = obs.ego
        must = _sign(road.lanes_to_change)
        acceleration = self._idm(ego.speed, ego.speed_limit, obs.neighbours.leader)
        acceleration = min(acceleration, stop_line_acceleration(self.params, obs))
        if must:
            acceleration = min(acceleration, self._stop_before(road.lane_end, ego.speed))
        if not ego.changing_lane and self._strategic(obs, road) and not self._fits(obs, must):
            acceleration = min(acceleration, self._fit_in(obs, must))
        return acceleration

    def at_stake(self, obs: Observation) -> float:
        """How much of the drive is at stake, from 0 to 1: a residual policy's correction
        fades out over it (`agent_client.drivers.policy.ActionScale`), so that there this
        driver, which reaches the end of its route and moves off when it can, drives. The
        route: 0 where no change is needed or the lane end is more than twice the urgent
        distance per lane to cross away, 1 within that distance (the change must be made
        now). A standstill: 0 from `STANDSTILL_SPEED` up, 1 at rest (a correction learned at
        speed holds an ego still where it has rarely stood)."""
        road = road_ahead(obs)
        lanes = abs(road.lanes_to_change)
        standing = 1.0 - obs.ego.speed / STANDSTILL_SPEED
        if not lanes:
            return min(max(standing, 0.0), 1.0)
        urgent = lanes * max(self.mobil.urgent_distance, obs.ego.speed * URGENT_TIME)
        return min(max(2.0 - road.lane_end / urgent, standing, 0.0), 1.0)

    def _strategic(self, obs: Observation, road: Road) -> bool:
        """The route needs a change within the look-ahead."""
        lanes = abs(road.lanes_to_change)
        return lanes > 0 and road.lane_end <= self._look_ahead(obs.ego.speed, lanes)

    def _urgent(self, obs: Observation, road: Road) -> bool:
        """Near enough to the lane end to ask at every decision whatever the gap."""
        return road.lane_end <= max(self.mobil.urgent_distance, obs.ego.speed * URGENT_TIME)

    # ----------------------------------------------------------------------- longitudinal

    def _idm(self, speed: float, limit: float, leader: Neighbour) -> float:
        gap = leader.gap if leader.present else None
        return idm_acceleration(self.params, speed, limit, gap, leader.speed)

    def _stop_before(self, lane_end: float, speed: float) -> float:
        """The braking that stops the ego ``s0`` before the end of its lane, once it needs more
        than `MobilParams.stop_deceleration` (before that: no limit, so that the ego keeps the
        speed of the lane it moves to for as long as it can)."""
        if lane_end >= ROAD_RANGE:
            return math.inf
        room = max(lane_end - self.params.s0, 0.1)
        needed = speed * speed / (2.0 * room)
        return -needed if needed > self.mobil.stop_deceleration else math.inf

    def _fit_in(self, obs: Observation, direction: int) -> float:
        """The acceleration that takes the ego into the gap beside it in the target lane: to
        its middle at the lane's speed where it is long enough, else back behind the vehicle
        there (the next gap comes from behind). The gaps needed are `secure_gap`s."""
        ego = obs.ego
        lead, lag = _beside(obs, direction)
        if lead.present and lag.present:
            lane_speed = 0.5 * (lead.speed + lag.speed)
            ahead = lead.gap - secure_gap(lane_speed, lead.speed)
            behind = lag.gap - secure_gap(lag.speed, lane_speed)
            if ahead + behind >= 0.0:  # it fits: take the middle
                shift = ALIGN_GAIN * (ahead - behind) / 2
                target = lane_speed + min(max(shift, -FALL_BACK), FALL_BACK)
            else:
                target = lane_speed - FALL_BACK
        elif lead.present:  # nobody behind: fall behind the leader there
            target = lead.speed - FALL_BACK
        elif lag.present:  # nobody ahead: get ahead of the follower there, or behind it
            target = lag.speed + FALL_BACK if lag.gap > 0.0 else lag.speed - FALL_BACK
        else:
            target = ego.speed_limit
        return min(max(SPEED_GAIN * (target - ego.speed), -self.params.b), self.params.a)

    # ----------------------------------------------------------------------- lateral

    def _look_ahead(self, speed: float, lanes: int) -> float:
        """Metres before a lane end from which the changes across `lanes` lanes are made."""
        return lanes * (speed * self.mobil.strategic_time + self.mobil.strategic_margin)

    def _discretionary(self, obs: Observation, road: Road, must: int) -> int:
        """MOBIL's choice between the lanes beside the ego (0: stay)."""
        ego = obs.ego
        best, best_gain = 0, 0.0
        for direction, lane_end in ((1, road.left_lane_end), (-1, road.right_lane_end)):
            if lane_end <= 0.0 or (must and direction != must):
                continue  # no lane there, or away from the route
            if lane_end < ROAD_RANGE and lane_end <= self._look_ahead(ego.speed, 1):
                continue  # a lane that ends soon
            if not self._safe(obs, direction):
                continue
            gain = self._incentive(obs, road, direction, lane_end)
            bias = self.mobil.keep_right_bias * direction
            if gain > self.mobil.threshold + bias and gain - bias > best_gain:
                best, best_gain = direction, gain - bias
        return best

    def _fits(self, obs: Observation, direction: int) -> bool:
        """The gap beside is safe by MOBIL's criterion and by a secure gap each side (what a
        simulator's own gap check asks; SUMO refuses a gap MOBIL accepts when the ego sits too
        close to the new leader, and the ego then has to move into the gap's middle)."""
        return self._safe(obs, direction) and gap_is_safe(obs, direction)

    def _safe(self, obs: Observation, direction: int) -> bool:
        """MOBIL's safety criterion: neither the new follower nor the ego brakes harder than
        b_safe after the change, and neither gap is negative."""
        lead, lag = _beside(obs, direction)
        ego = obs.ego
        limit = -self.mobil.safe_deceleration
        if lead.present and (
            lead.gap <= 0.0 or self._idm(ego.speed, ego.speed_limit, lead) < limit
        ):
            return False
        if not lag.present:
            return True
        follower = idm_acceleration(self.others, lag.speed, ego.speed_limit, lag.gap, ego.speed)
        return lag.gap > 0.0 and follower >= limit

    def _incentive(self, obs: Observation, road: Road, direction: int, lane_end: float) -> float:
        """The ego's gain from changing to `direction`, plus politeness x its followers'."""
        ego, near = obs.ego, obs.neighbours
        speed, limit, others = ego.speed, ego.speed_limit, self.others
        lead, lag = _beside(obs, direction)
        before = self._idm(speed, limit, near.leader)
        after = self._idm(speed, limit, lead)
        if lane_end < ROAD_RANGE:  # a lane that ends is a standing obstacle (highway-env)
            after = min(after, idm_acceleration(self.params, speed, limit, lane_end, 0.0))
        gain = after - before
        if lag.present:  # the new follower: behind the new leader now, behind the ego then
            now = idm_acceleration(others, lag.speed, limit, _behind(lag, lead), lead.speed)
            then = idm_acceleration(others, lag.speed, limit, lag.gap, speed)
            gain += self.mobil.politeness * (then - now)
        follower, leader = near.follower, near.leader
        if follower.present:  # the old follower: behind the ego now, behind its leader then
            now = idm_acceleration(others, follower.speed, limit, follower.gap, speed)
            then = idm_acceleration(
                others, follower.speed, limit, _behind(follower, leader), leader.speed
            )
            gain += self.mobil.politeness * (then - now)
        return gain


def _beside(obs: Observation, direction: int) -> tuple[Neighbour, Neighbour]:
    """The leader and follower in the lane on side `direction` (1 left, -1 right)."""
    near = obs.neighbours
    if direction > 0:
        return near.left_leader, near.left_follower
    return near.right_leader, near.right_follower


def _behind(follower: Neighbour, leader: Neighbour) -> float | None:
    """The gap from `follower` (behind the ego) to `leader` (ahead of it) with the ego out of
    the way; None without a leader."""
    if not leader.present:
        return None
    return follower.gap + VEHICLE_LENGTH + leader.gap


def _sign(value: int) -> int:
    return (value > 0) - (value < 0)
