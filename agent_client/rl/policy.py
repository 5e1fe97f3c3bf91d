"""The deployable greedy policy: the actor for the acceleration, critic 1 for the lane choice.

Plain numpy at run time (`agent_client.rl.greedy`: no torch call per step), built from a
policy state that holds tensors only, so a policy file loads with
``torch.load(weights_only=True)``. Files of version 1 (written before the networks became plain
tensors) are converted on loading.
"""

from __future__ import annotations

from typing import Any

import torch

from agent_client.rl.greedy import GreedyPolicy
from agent_client.rl.networks import Params

POLICY_FORMAT = "av-bridge-ddpg-policy"
"""The format tag of policy files (kept from the first version, so old files are recognised)."""
POLICY_VERSION = 2


class Policy(GreedyPolicy):
    """A `GreedyPolicy` built from a policy state (`Agent.policy_state_dict()`) of tensors."""

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> Policy:
        """Build from `Agent.policy_state_dict()` (loaded with weights_only=True)."""
        version = state.get("version")
        if state.get("format") != POLICY_FORMAT or version not in (1, POLICY_VERSION):
            raise ValueError(
                f"not a {POLICY_FORMAT} v1 or v{POLICY_VERSION} state: "
                f"{state.get('format')!r} v{version!r}"
            )
        obs_dim, n_lanes = int(state["obs_dim"]), int(state["n_lane_actions"])
        actor, critic = state["actor"], state.get("critic")
        if version == 1:
            actor = _from_module_state(actor, ensemble=False)
            critic = _from_module_state(critic, ensemble=True) if critic is not None else None
        actor = [torch.as_tensor(p).detach().numpy().copy() for p in actor]
        critic = [torch.as_tensor(p).detach().numpy().copy() for p in critic] if critic else None
        return cls(actor, critic if n_lanes > 1 else None, obs_dim, n_lanes)


def _from_module_state(module_state: dict[str, torch.Tensor], ensemble: bool) -> Params:
    """A version-1 ``nn.Sequential`` state (net.0.weight (out, in), ...) as a layer list."""
    params: Params = []
    weights = sorted(
        (key for key in module_state if key.endswith(".weight")),
        key=lambda key: int(key.split(".")[1]),
    )
    for key in weights:
        weight = module_state[key].t().contiguous()
        bias = module_state[key.removesuffix("weight") + "bias"]
        params += [weight[None], bias[None, None]] if ensemble else [weight, bias]
    return params
