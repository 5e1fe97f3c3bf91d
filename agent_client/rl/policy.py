"""The deployable greedy policy: the actor for the acceleration, critic 1 for the lane choice.

Plain numpy at run time (no torch call per step), built from a policy state that holds tensors
only, so a policy file loads with ``torch.load(weights_only=True)``. Files of version 1 (written
before the networks became plain tensors) are converted on loading.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from agent_client.rl.networks import NumpyActor, NumpyCritic, Params

POLICY_FORMAT = "av-bridge-ddpg-policy"
"""The format tag of policy files (kept from the first version, so old files are recognised)."""
POLICY_VERSION = 2


def all_valid(n: int, n_lanes: int) -> np.ndarray:
    """(n, n_lanes) masks that allow every lane choice."""
    return np.ones((n, n_lanes), dtype=bool)


class Policy:
    """Greedy actions from an actor and (with several lane choices) the first critic."""

    def __init__(self, actor: Params, critic: Params | None, obs_dim: int, n_lanes: int) -> None:
        if n_lanes > 1 and critic is None:
            raise ValueError("a policy with several lane choices needs the critic")
        self.obs_dim = obs_dim
        self.n_lane_actions = n_lanes
        self._actor = NumpyActor(actor)
        self._critic = NumpyCritic(critic) if critic is not None else None

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
        actor = [torch.as_tensor(p).detach().clone() for p in actor]
        critic = [torch.as_tensor(p).detach().clone() for p in critic] if critic else None
        return cls(actor, critic if n_lanes > 1 else None, obs_dim, n_lanes)

    def act(self, obs: np.ndarray, mask: np.ndarray | None = None) -> tuple[float, int]:
        """Greedy (acceleration in [-1, 1], lane index) for one observation."""
        masks = None if mask is None else np.asarray(mask, dtype=bool).reshape(1, -1)
        acceleration, lanes = self.act_batch(np.asarray(obs, np.float32).reshape(1, -1), masks)
        return float(acceleration[0]), int(lanes[0])

    def act_batch(
        self, obs: np.ndarray, masks: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Greedy actions for N observations: accelerations (N,) float32, lanes (N,) int64."""
        batch = np.asarray(obs, dtype=np.float32)
        if batch.ndim != 2 or batch.shape[1] != self.obs_dim:
            raise ValueError(
                f"expected observations of shape (N, {self.obs_dim}), got {batch.shape}"
            )
        acceleration = self._actor(batch).astype(np.float32)
        if self._critic is None:
            return acceleration, np.zeros(len(batch), dtype=np.int64)
        valid = all_valid(len(batch), self.n_lane_actions) if masks is None else masks
        q = self._critic(batch, acceleration)
        return acceleration, np.where(valid, q, -np.inf).argmax(axis=1).astype(np.int64)


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
