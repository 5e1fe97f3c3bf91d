"""A trained policy as a driver: features in, acceleration and lane change out.

``policy.pt`` holds the actor (and the critic that picks the lane), the feature set, the lane
decision cadence and the acceleration scaling, so `agent-client drive --policy
runs/NAME/policy.pt` needs nothing else. The driver is plain numpy: a process that only drives
(an evaluation worker) never imports torch; reading and writing policy files does.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from agent_client.rl.features import FeatureMap, FeatureMismatch
from agent_client.rl.greedy import GreedyPolicy
from agent_client.rl.lanes import LANE_COMMANDS, LaneChoice
from protocol.messages import ActionSchema, Observation


@dataclass(frozen=True)
class ActionScale:
    """Maps the actor's [-1, 1] onto the server's acceleration bounds (m/s^2)."""

    low: float
    high: float

    @classmethod
    def from_schema(cls, schema: ActionSchema) -> ActionScale:
        return cls(schema.acceleration_min, schema.acceleration_max)

    def to_env(self, u: float) -> float:
        return self.low + (u + 1.0) * 0.5 * (self.high - self.low)

    def to_policy(self, acceleration: float) -> float:
        u = 2.0 * (acceleration - self.low) / (self.high - self.low) - 1.0
        return min(1.0, max(-1.0, u))


class PolicyDriver:
    """Drives with a trained policy (greedy), asking for lane changes only when they can happen."""

    name = "policy"

    def __init__(
        self, policy: GreedyPolicy, features: FeatureMap, scale: ActionScale, lanes: LaneChoice
    ) -> None:
        self.policy = policy
        self.features = features
        self.scale = scale
        self.lanes = lanes

    def act(self, obs: Observation) -> tuple[float, int]:
        u, lane = self.policy.act(self.features(obs), self.lanes.mask(obs))
        return self.scale.to_env(u), LANE_COMMANDS[lane]


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
        "acceleration_bounds": [scale.low, scale.high],
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
    lanes = LaneChoice(policy.n_lane_actions, every, gap_rule)
    return PolicyDriver(policy, features, ActionScale(low, high), lanes)
