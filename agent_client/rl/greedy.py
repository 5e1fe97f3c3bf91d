"""The greedy policy in plain numpy: what acting needs, without torch.

The actor and the first critic's forward passes over their layers' arrays ([w0, b0, w1, b1, ...],
weights (in, out)), and the greedy choice of the acceleration and the lane. Training acts
through views of the torch weights (`agent_client.rl.networks.numpy_views`), which follow the
optimiser's in-place updates; a policy file or an evaluation worker builds the same from copies,
and a process that only drives never imports torch.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def all_valid(n: int, n_lanes: int) -> np.ndarray:
    """(n, n_lanes) masks that allow every lane choice."""
    return np.ones((n, n_lanes), dtype=bool)


class NumpyActor:
    """The actor's forward pass: (N, obs_dim) float32 -> (N,) normalised accelerations."""

    def __init__(self, params: Sequence[np.ndarray]) -> None:
        self.params = list(params)
        self.layers = list(zip(self.params[0::2], self.params[1::2], strict=True))

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        h = obs
        for w, b in self.layers[:-1]:
            h = np.maximum(h @ w + b, 0.0)
        w, b = self.layers[-1]
        return np.tanh(h @ w + b)[:, 0].astype(np.float32, copy=False)


class NumpyCritic:
    """The first critic of a stacked ensemble: (N, obs_dim), (N,) -> (N, n_lanes) Q-values."""

    def __init__(self, params: Sequence[np.ndarray]) -> None:
        self.params = list(params)
        pairs = zip(self.params[0::2], self.params[1::2], strict=True)
        self.layers = [(w[0], b[0]) for w, b in pairs]

    def __call__(self, obs: np.ndarray, acceleration: np.ndarray) -> np.ndarray:
        h = np.concatenate([obs, acceleration[:, None]], axis=1)
        for w, b in self.layers[:-1]:
            h = np.maximum(h @ w + b, 0.0)
        w, b = self.layers[-1]
        return h @ w + b


class GreedyPolicy:
    """Greedy actions from an actor and (with several lane choices) the first critic."""

    def __init__(
        self,
        actor: Sequence[np.ndarray],
        critic: Sequence[np.ndarray] | None,
        obs_dim: int,
        n_lanes: int,
    ) -> None:
        if n_lanes > 1 and critic is None:
            raise ValueError("a policy with several lane choices needs the critic")
        self.obs_dim = obs_dim
        self.n_lane_actions = n_lanes
        self.actor = NumpyActor(actor)
        self.critic = NumpyCritic(critic) if critic is not None and n_lanes > 1 else None

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
        acceleration = self.actor(batch).astype(np.float32)
        if self.critic is None:
            return acceleration, np.zeros(len(batch), dtype=np.int64)
        valid = all_valid(len(batch), self.n_lane_actions) if masks is None else masks
        q = self.critic(batch, acceleration)
        return acceleration, np.where(valid, q, -np.inf).argmax(axis=1).astype(np.int64)
