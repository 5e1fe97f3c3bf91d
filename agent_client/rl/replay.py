"""A uniform experience-replay buffer for the hybrid (acceleration, lane) action.

It stores `terminated`, not `done`: a time-limit truncation is stored as terminated = 0 so that the
learner still bootstraps from the next state. With several lane choices it also stores which of
them could happen in the state and in the next state (`mask`, `next_mask`). Arrays are
preallocated numpy; `sample` returns torch tensors. `state_dict` holds only tensors and plain
python values, so a checkpoint that contains it loads with `torch.load(..., weights_only=True)`.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import torch

_FORMAT = "av-bridge-replay"
_FORMAT_VERSION = 2


class Batch(NamedTuple):
    """A sampled minibatch; every field has the batch size as its first dimension."""

    obs: torch.Tensor
    """(B, obs_dim) float32."""
    acceleration: torch.Tensor
    """(B, 1) float32, the actor's normalised output in [-1, 1]."""
    lane: torch.Tensor
    """(B,) int64 index of the discrete lane choice."""
    reward: torch.Tensor
    """(B,) float32."""
    next_obs: torch.Tensor
    """(B, obs_dim) float32."""
    terminated: torch.Tensor
    """(B,) float32, 1 where the episode truly ended (no bootstrapping), 0 otherwise."""
    mask: torch.Tensor | None = None
    """(B, n_lanes) bool: the lane choices that could happen in `obs` (None: all)."""
    next_mask: torch.Tensor | None = None
    """(B, n_lanes) bool: the lane choices that could happen in `next_obs` (None: all)."""

    def to(self, device: torch.device) -> Batch:
        """The same batch on `device` (copied without waiting where the device allows it)."""

        def moved(tensor: torch.Tensor | None) -> torch.Tensor | None:
            return None if tensor is None else tensor.to(device, non_blocking=True)

        return Batch(
            self.obs.to(device, non_blocking=True),
            self.acceleration.to(device, non_blocking=True),
            self.lane.to(device, non_blocking=True),
            self.reward.to(device, non_blocking=True),
            self.next_obs.to(device, non_blocking=True),
            self.terminated.to(device, non_blocking=True),
            moved(self.mask),
            moved(self.next_mask),
        )


FIELDS = ("obs", "next_obs", "acceleration", "lane", "reward", "terminated", "mask", "next_mask")


class ReplayBuffer:
    """A ring buffer of transitions with its own seeded generator for uniform sampling."""

    def __init__(
        self, capacity: int, obs_dim: int, seed: int | None = None, n_lanes: int = 1
    ) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        if obs_dim < 1:
            raise ValueError(f"obs_dim must be >= 1, got {obs_dim}")
        self.capacity = int(capacity)
        self.obs_dim = int(obs_dim)
        self.obs = np.zeros((capacity, obs_dim), dtype=np.float32)
        self.next_obs = np.zeros((capacity, obs_dim), dtype=np.float32)
        self.acceleration = np.zeros((capacity, 1), dtype=np.float32)
        self.lane = np.zeros(capacity, dtype=np.int64)
        self.reward = np.zeros(capacity, dtype=np.float32)
        self.terminated = np.zeros(capacity, dtype=np.float32)
        self.n_lanes = int(n_lanes)
        self.mask = np.ones((capacity, n_lanes), dtype=bool)
        self.next_mask = np.ones((capacity, n_lanes), dtype=bool)
        self.pos = 0
        self.size = 0
        self.rng = np.random.default_rng(seed)

    def __len__(self) -> int:
        return self.size

    @property
    def full(self) -> bool:
        return self.size == self.capacity

    def add(
        self,
        obs: np.ndarray,
        acceleration: float,
        lane: int,
        reward: float,
        next_obs: np.ndarray,
        terminated: bool,
        mask: np.ndarray | None = None,
        next_mask: np.ndarray | None = None,
    ) -> None:
        """Store one transition, overwriting the oldest one when full (masks default to all)."""
        obs_arr = np.asarray(obs, dtype=np.float32)
        next_arr = np.asarray(next_obs, dtype=np.float32)
        if obs_arr.shape != (self.obs_dim,) or next_arr.shape != (self.obs_dim,):
            raise ValueError(
                f"obs and next_obs must have shape ({self.obs_dim},), "
                f"got {obs_arr.shape} and {next_arr.shape}"
            )
        if not -1.0 <= acceleration <= 1.0:
            raise ValueError(
                f"acceleration must be the normalised action in [-1, 1], got {acceleration}"
            )
        if not 0 <= lane < self.n_lanes:
            raise ValueError(f"lane must be an index below {self.n_lanes}, got {lane}")
        i = self.pos
        self.obs[i] = obs_arr
        self.next_obs[i] = next_arr
        self.acceleration[i, 0] = acceleration
        self.lane[i] = lane
        self.reward[i] = reward
        self.terminated[i] = float(terminated)
        self.mask[i] = True if mask is None else mask
        self.next_mask[i] = True if next_mask is None else next_mask
        self.pos = (self.pos + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def add_batch(
        self,
        obs: np.ndarray,
        acceleration: np.ndarray,
        lane: np.ndarray,
        reward: np.ndarray,
        next_obs: np.ndarray,
        terminated: np.ndarray,
    ) -> None:
        """Store N transitions at once (a vector env step); same rules as `add`."""
        obs_arr = np.asarray(obs, dtype=np.float32)
        n = obs_arr.shape[0] if obs_arr.ndim == 2 else -1
        next_arr = np.asarray(next_obs, dtype=np.float32)
        acc = np.asarray(acceleration, dtype=np.float32).reshape(-1)
        lanes = np.asarray(lane, dtype=np.int64).reshape(-1)
        rewards = np.asarray(reward, dtype=np.float32).reshape(-1)
        terms = np.asarray(terminated, dtype=np.float32).reshape(-1)
        if obs_arr.shape != (n, self.obs_dim) or next_arr.shape != (n, self.obs_dim):
            raise ValueError(
                f"obs and next_obs must have shape (N, {self.obs_dim}), "
                f"got {obs_arr.shape} and {next_arr.shape}"
            )
        if not len(acc) == len(lanes) == len(rewards) == len(terms) == n:
            raise ValueError(f"all fields must hold {n} transitions")
        if n > 0 and (
            np.any(np.abs(acc) > 1.0) or np.any(lanes < 0) or np.any(lanes >= self.n_lanes)
        ):
            raise ValueError(
                f"acceleration must lie in [-1, 1] and lane indices in [0, {self.n_lanes})"
            )
        if n > self.capacity:  # only the newest `capacity` transitions would survive anyway
            skip = n - self.capacity
            self.pos = (self.pos + skip) % self.capacity
            obs_arr, next_arr = obs_arr[skip:], next_arr[skip:]
            acc, lanes, rewards, terms = acc[skip:], lanes[skip:], rewards[skip:], terms[skip:]
            n = self.capacity
        idx = (self.pos + np.arange(n)) % self.capacity
        self.obs[idx] = obs_arr
        self.next_obs[idx] = next_arr
        self.acceleration[idx, 0] = acc
        self.lane[idx] = lanes
        self.reward[idx] = rewards
        self.terminated[idx] = terms
        self.mask[idx] = True
        self.next_mask[idx] = True
        self.pos = (self.pos + n) % self.capacity
        self.size = min(self.size + n, self.capacity)

    def sample(self, batch_size: int) -> Batch:
        """Draw `batch_size` transitions uniformly, with replacement, as CPU tensors."""
        if self.size == 0:
            raise ValueError("cannot sample from an empty replay buffer")
        idx = self.rng.integers(0, self.size, size=batch_size)
        return Batch(
            obs=torch.from_numpy(self.obs[idx]),
            acceleration=torch.from_numpy(self.acceleration[idx]),
            lane=torch.from_numpy(self.lane[idx]),
            reward=torch.from_numpy(self.reward[idx]),
            next_obs=torch.from_numpy(self.next_obs[idx]),
            terminated=torch.from_numpy(self.terminated[idx]),
            mask=torch.from_numpy(self.mask[idx]),
            next_mask=torch.from_numpy(self.next_mask[idx]),
        )

    def state_dict(self) -> dict[str, Any]:
        """The filled part of the buffer, its position and its generator state (safe types only)."""
        n = self.size
        return {
            "format": _FORMAT,
            "version": _FORMAT_VERSION,
            "capacity": self.capacity,
            "obs_dim": self.obs_dim,
            "pos": self.pos,
            "size": n,
            "obs": torch.from_numpy(self.obs[:n].copy()),
            "next_obs": torch.from_numpy(self.next_obs[:n].copy()),
            "acceleration": torch.from_numpy(self.acceleration[:n].copy()),
            "lane": torch.from_numpy(self.lane[:n].copy()),
            "reward": torch.from_numpy(self.reward[:n].copy()),
            "terminated": torch.from_numpy(self.terminated[:n].copy()),
            "mask": torch.from_numpy(self.mask[:n].copy()),
            "next_mask": torch.from_numpy(self.next_mask[:n].copy()),
            "rng": self.rng.bit_generator.state,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a buffer saved by `state_dict`; capacity and obs_dim must match."""
        if state.get("format") != _FORMAT or state.get("version") != _FORMAT_VERSION:
            raise ValueError(
                f"not a {_FORMAT} v{_FORMAT_VERSION} state: "
                f"{state.get('format')!r} v{state.get('version')!r}"
            )
        if (
            state["capacity"] != self.capacity
            or state["obs_dim"] != self.obs_dim
            or tuple(state["mask"].shape[1:]) != (self.n_lanes,)
        ):
            raise ValueError(
                f"buffer shape mismatch: saved capacity={state['capacity']} "
                f"obs_dim={state['obs_dim']}, this buffer capacity={self.capacity} "
                f"obs_dim={self.obs_dim}"
            )
        n = int(state["size"])
        for name in FIELDS:
            getattr(self, name)[:n] = state[name].numpy()
        self.size = n
        self.pos = int(state["pos"])
        self.rng.bit_generator.state = state["rng"]
