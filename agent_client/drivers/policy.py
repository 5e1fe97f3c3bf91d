"""A trained policy as a driver: features in, acceleration and lane change out.

``policy.pt`` holds the actor (and the critic that picks the lane), the feature set and the
acceleration scaling, so `agent-client drive --policy runs/NAME/policy.pt` needs nothing else.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from agent_client.rl.checkpoint import load_checkpoint, save_checkpoint
from agent_client.rl.features import FeatureMap, FeatureMismatch
from agent_client.rl.td3 import Agent, Policy
from protocol.messages import ActionSchema, Observation

LANE_COMMANDS = (0, 1, -1)
"""Lane index of the agent -> lane-change command: keep, left, right."""


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
    """Drives with a trained policy (greedy)."""

    name = "policy"

    def __init__(self, policy: Policy, features: FeatureMap, scale: ActionScale) -> None:
        self.policy = policy
        self.features = features
        self.scale = scale

    def act(self, obs: Observation) -> tuple[float, int]:
        u, lane = self.policy.act(self.features(obs))
        return self.scale.to_env(u), LANE_COMMANDS[lane]


def save_policy(
    path: Path, agent: Agent, features: str, scale: ActionScale, averaged: bool = False
) -> None:
    """Write the deployable part of an agent (no optimiser, no buffer)."""
    state: dict[str, Any] = {
        "policy": agent.policy_state_dict(averaged),
        "features": features,
        "acceleration_bounds": [scale.low, scale.high],
    }
    save_checkpoint(path, state)


def load_policy_driver(path: Path) -> PolicyDriver:
    """Read a policy file safely and wrap it as a driver."""
    state = load_checkpoint(path)
    low, high = state["acceleration_bounds"]
    policy, features = Policy.from_state_dict(state["policy"]), FeatureMap(state["features"])
    if policy.obs_dim != features.dim:
        raise FeatureMismatch(
            f"{path}: the policy takes {policy.obs_dim} features, but feature set "
            f"{features.name!r} now has {features.dim} (the file was written by an older "
            "version): train it again"
        )
    return PolicyDriver(policy, features, ActionScale(low, high))
