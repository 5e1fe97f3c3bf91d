"""A trained policy as a driver: features in, acceleration and lane change out.

``policy.pt`` holds the actor (and the critic that picks the lane), the feature set, the lane
decision cadence and the acceleration scaling (and the reference a residual policy corrects), so
`agent-client drive --policy runs/NAME/policy.pt` needs nothing else. The driver is plain numpy: a
process that only drives (an evaluation worker) never imports torch; reading and writing policy
files does.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from agent_client.drivers.mobil import DECISION_INTERVAL, IDMMobilDriver, MobilParams, jerk_limited
from agent_client.drivers.safety import NONE as NO_OVERRIDE
from agent_client.drivers.safety import SafetyLayer
from agent_client.rl.features import FeatureMap, FeatureMismatch
from agent_client.rl.greedy import GreedyPolicy
from agent_client.rl.lanes import LaneChoice
from protocol.messages import ActionSchema, Observation

RESIDUAL_RANGE = 2.0
"""m/s²: how far a residual policy's acceleration may stray from what its reference wants (±),
where the drive is not at stake (`Reference.at_stake`)."""

STOP_DECELERATION = MobilParams().stop_deceleration
MAX_INTERVAL = 60.0
"""s: the longest decision interval a simulator offers (an observation further apart than this
from the last one seen belongs to another episode, and says nothing of the interval)."""
"""m/s²: harder braking than this is applied at once, as the reference applies it."""


@dataclass(frozen=True)
class Reference:
    """A driver a residual policy is trained on top of, in the three parts it needs, none of
    which keeps state."""

    acceleration: Callable[[Observation], float]
    """The acceleration it wants (m/s²), before its jerk limit."""
    lane_change: Callable[[Observation, bool], int]
    """Its lane change (`LaneChoice.reference`): a residual policy changes lanes as it does."""
    at_stake: Callable[[Observation], float]
    """From 0 to 1: how far the policy's correction fades out, so that where the drive is at
    stake (a lane end the route must leave, a standstill) the reference drives."""


_IDM_MOBIL = IDMMobilDriver()
REFERENCES: dict[str, Reference] = {
    "idm+mobil": Reference(
        _IDM_MOBIL.wanted_acceleration, _IDM_MOBIL.lane_change, _IDM_MOBIL.at_stake
    ),
}
"""The drivers a policy can be trained on top of."""


RESIDUAL_LANES = ("follow", "default", "own")
"""How a residual policy's lane choice relates to its reference's: ``follow`` (the reference's
change is the only choice), ``default`` (the reference's change is the first of four choices,
keep / left / right the policy's own: it starts as the reference and leaves it where a choice
of its own is worth more) or ``own`` (keep / left / right alone)."""


def lane_choice(
    n_choices: int,
    every: int,
    gap_rule: bool,
    residual: str = "",
    route_masks: bool = True,
    residual_lanes: str = "follow",
) -> LaneChoice:
    """The lane choice of a policy; a residual one relates to its reference's as
    `residual_lanes` says (`RESIDUAL_LANES`; `n_choices` 4 for ``default``)."""
    if residual_lanes not in RESIDUAL_LANES:
        raise ValueError(f"residual_lanes {residual_lanes!r} is not one of {RESIDUAL_LANES}")
    uses = residual and n_choices > 1 and residual_lanes != "own"
    reference = REFERENCES[residual].lane_change if uses else None
    return LaneChoice(n_choices, every, gap_rule, route_masks, reference)


@dataclass(frozen=True)
class ActionScale:
    """Maps the actor's [-1, 1] onto an acceleration (m/s^2): the server's bounds, or with
    `residual` a correction of up to ±`RESIDUAL_RANGE` of what a reference driver wants
    (residual policy learning, Silver et al. 2018, Johannink et al. 2019: the policy starts as
    good as the reference, IDM + MOBIL on roads where lanes end, and learns what to do better),
    changed from one decision to the next no faster than the reference's own jerk limit unless
    braking hard. The correction fades out where the reference says the drive is at stake
    (`Reference.at_stake`; a shield, Alshiekh et al. 2018): close to the end of a lane the
    route must leave, and at a standstill, the reference alone drives, so that what the policy
    learned elsewhere cannot make it miss a merge or an exit, or stand, on a road it never
    saw."""

    low: float
    high: float
    residual: str = ""
    """"" (the acceleration itself), or a key of `REFERENCES`."""
    interval: float = DECISION_INTERVAL
    """Seconds per decision (with `residual`: the jerk limit's time step)."""
    reach: float = RESIDUAL_RANGE
    """m/s²: with `residual`, how far the actor's output reaches from what the reference wants
    (at u = ±1). A reach as wide as the action's bounds lets the policy choose any acceleration,
    the reference only where its output is 0: the integrated driver's parametrisation."""
    shield: bool = True
    """With `residual`, fade the reach out where the reference says the drive is at stake
    (`Reference.at_stake`); False: the policy decides there too (a safety layer may override
    it, counted: `agent_client.drivers.safety`)."""

    def __post_init__(self) -> None:
        if self.residual and self.residual not in REFERENCES:
            raise ValueError(f"residual {self.residual!r} is not one of: {', '.join(REFERENCES)}")

    @classmethod
    def from_schema(
        cls,
        schema: ActionSchema,
        residual: str = "",
        interval: float = DECISION_INTERVAL,
        reach: float = RESIDUAL_RANGE,
        shield: bool = True,
    ) -> ActionScale:
        low, high = schema.acceleration_min, schema.acceleration_max
        return cls(low, high, residual, interval, reach, shield)

    def to_env(self, u: float, obs: Observation | None = None) -> float:
        """The acceleration for the actor's `u` in the state `obs` (needed with `residual`)."""
        if not self.residual:
            return self.low + (u + 1.0) * 0.5 * (self.high - self.low)
        assert obs is not None, "a residual policy's action depends on the observation"
        reference = REFERENCES[self.residual]
        wanted = reference.acceleration(obs) + self._reach(obs) * u
        if wanted > -STOP_DECELERATION:  # as the reference's own: a comfortable jerk at most
            wanted = jerk_limited(wanted, obs.ego.acceleration, self.interval)
        return min(max(wanted, self.low), self.high)

    def to_policy(self, acceleration: float, obs: Observation | None = None) -> float:
        """The actor's `u` that gives `acceleration` in the state `obs` (clipped to [-1, 1]);
        with `residual`, 0 wherever the reference itself gives it (within its jerk limit,
        or where the correction has faded out)."""
        if not self.residual:
            u = 2.0 * (acceleration - self.low) / (self.high - self.low) - 1.0
            return min(1.0, max(-1.0, u))
        assert obs is not None, "a residual policy's action depends on the observation"
        reach = self._reach(obs)
        if reach <= 0.0 or abs(self.to_env(0.0, obs) - acceleration) < 1e-9:
            return 0.0
        u = (acceleration - REFERENCES[self.residual].acceleration(obs)) / reach
        return min(1.0, max(-1.0, u))

    def _reach(self, obs: Observation) -> float:
        """m/s²: how far a residual policy's correction reaches in `obs` (at u = ±1)."""
        if not self.shield:
            return self.reach
        return self.reach * (1.0 - REFERENCES[self.residual].at_stake(obs))


class PolicyDriver:
    """Drives with a trained policy (greedy), asking for lane changes only when they can happen.

    A residual policy's jerk limit (and its reference's) steps over the decision interval of the
    road it drives, as IDM + MOBIL's own: the one it was trained on until two observations have
    shown it (a network whose SUMO step is 1 s decides every second: with a 0.1 s limit there,
    an ego braked hard at a junction would recover a tenth as fast and stop)."""

    name = "policy"

    def __init__(
        self, policy: GreedyPolicy, features: FeatureMap, scale: ActionScale, lanes: LaneChoice
    ) -> None:
        self.policy = policy
        self.features = features
        self.scale = scale
        self.lanes = lanes
        self.layer = SafetyLayer(scale.interval, scale.low)
        """Overrides a decision only where a stated rule says the drive is at stake."""
        self.override = NO_OVERRIDE
        """What the layer changed of the last decision (the episode loop counts it)."""
        self._last_time = -math.inf

    def act(self, obs: Observation) -> tuple[float, int]:
        if obs.seq > 0 and self._last_time < obs.time < self._last_time + MAX_INTERVAL:
            interval = obs.time - self._last_time
            if abs(interval - self.scale.interval) > 1e-9:
                self.scale = replace(self.scale, interval=interval)
                self.layer = SafetyLayer(interval, self.scale.low)
        self._last_time = obs.time
        u, lane = self.policy.act(self.features(obs), self.lanes.mask(obs))
        acceleration, command, self.override = self.layer.apply(
            obs, self.scale.to_env(u, obs), self.lanes.command(lane, obs)
        )
        return acceleration, command


def save_policy(
    path: Path,
    policy_state: dict[str, Any],
    features: FeatureMap,
    scale: ActionScale,
    lanes: LaneChoice,
) -> None:
    """Write the deployable part of an agent (`Agent.policy_state_dict`: no optimiser, no
    buffer) with what it needs to drive."""
    from agent_client.rl.checkpoint import save_checkpoint  # torch: the driver itself needs none

    state: dict[str, Any] = {
        "policy": policy_state,
        "features": features.name,
        "lane_decision_every": lanes.every,
        "lane_gap_rule": lanes.gap_rule,
        "lane_route_masks": lanes.route_masks,
        "acceleration_bounds": [scale.low, scale.high],
        "residual": scale.residual,
        "residual_reach": scale.reach,
        "residual_shield": scale.shield,
        "residual_lanes": (
            "own" if lanes.reference is None else "default" if lanes.n_choices == 4 else "follow"
        ),
        "decision_interval": scale.interval,
    }
    save_checkpoint(path, state)


def load_policy_driver(path: Path) -> PolicyDriver:
    """Read a policy file safely and wrap it as a driver."""
    from agent_client.rl.checkpoint import load_checkpoint  # torch: the driver itself needs none
    from agent_client.rl.policy import Policy

    state = load_checkpoint(path)
    low, high = state["acceleration_bounds"]
    every = int(state.get("lane_decision_every", 1))
    gap_rule = bool(state.get("lane_gap_rule", False))  # off in files from before the rule
    policy = Policy.from_state_dict(state["policy"])
    features = FeatureMap(state["features"], lane_phase_every=every)
    if policy.obs_dim != features.dim:
        raise FeatureMismatch(
            f"{path}: the policy takes {policy.obs_dim} features, but feature set "
            f"{features.name!r} now has {features.dim} (the file was written by an older "
            "version): train it again"
        )
    residual = str(state.get("residual", ""))  # "" in older files
    route_masks = bool(state.get("lane_route_masks", True))  # on in files from before it
    residual_lanes = str(state.get("residual_lanes", "follow"))  # older files: the reference's
    lanes = lane_choice(
        policy.n_lane_actions, every, gap_rule, residual, route_masks, residual_lanes
    )
    interval = float(state.get("decision_interval", DECISION_INTERVAL))
    reach = float(state.get("residual_reach", RESIDUAL_RANGE))
    shield = bool(state.get("residual_shield", True))
    scale = ActionScale(low, high, residual, interval, reach, shield)
    return PolicyDriver(policy, features, scale, lanes)
