"""Exploration noise for the normalised acceleration (one scalar process per environment).

Gaussian noise is independent from step to step; Ornstein-Uhlenbeck noise is autocorrelated and
mean-reverting, so it changes the applied acceleration more smoothly (less jerk) at the same
amplitude. Both multiply their output by `scale`, which callers may lower to decay exploration.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import Any

import numpy as np

NOISE_KINDS = ("gaussian", "ou")


class ActionNoise(ABC):
    """A seeded scalar noise process: `sample()` once per step, `reset()` at episode start."""

    kind: str

    def __init__(self, sigma: float, seed: int | None = None) -> None:
        if sigma < 0:
            raise ValueError(f"sigma must be >= 0, got {sigma}")
        self.sigma = float(sigma)
        self.scale = 1.0
        self.rng = np.random.default_rng(seed)

    @abstractmethod
    def sample(self) -> float:
        """The next noise value, already multiplied by `scale`."""

    @abstractmethod
    def reset(self) -> None:
        """Start a new episode."""

    def state_dict(self) -> dict[str, Any]:
        """Parameters, scale and generator state as plain python values."""
        return {
            "kind": self.kind,
            "sigma": self.sigma,
            "scale": self.scale,
            "rng": self.rng.bit_generator.state,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue exactly where the saved process stopped."""
        if state.get("kind") != self.kind:
            raise ValueError(f"cannot load {state.get('kind')!r} noise state into {self.kind!r}")
        self.sigma = float(state["sigma"])
        self.scale = float(state["scale"])
        self.rng.bit_generator.state = state["rng"]


class GaussianNoise(ActionNoise):
    """Independent N(0, sigma^2) noise at every step."""

    kind = "gaussian"

    def sample(self) -> float:
        return self.scale * self.sigma * float(self.rng.standard_normal())

    def reset(self) -> None:
        """Nothing to reset: the noise has no memory."""


class OrnsteinUhlenbeckNoise(ActionNoise):
    """x += theta (mu - x) dt + sigma sqrt(dt) N(0, 1), as in Lillicrap et al. (2015).

    Its lag-1 autocorrelation is 1 - theta dt and its stationary standard deviation about
    sigma / sqrt(2 theta) (1.83 sigma for theta = 0.15), larger than Gaussian noise of equal sigma.
    """

    kind = "ou"

    def __init__(
        self,
        sigma: float,
        theta: float = 0.15,
        dt: float = 1e-2,
        mu: float = 0.0,
        seed: int | None = None,
        initial: float | None = None,
    ) -> None:
        super().__init__(sigma, seed)
        if not 0.0 < theta * dt <= 1.0:
            raise ValueError(f"need 0 < theta * dt <= 1, got theta={theta}, dt={dt}")
        self.theta = float(theta)
        self.dt = float(dt)
        self.mu = float(mu)
        self.initial = float(mu if initial is None else initial)
        self.x = self.initial

    def sample(self) -> float:
        self.x += self.theta * (self.mu - self.x) * self.dt
        self.x += self.sigma * math.sqrt(self.dt) * float(self.rng.standard_normal())
        return self.scale * self.x

    def reset(self) -> None:
        self.x = self.initial

    def state_dict(self) -> dict[str, Any]:
        state = super().state_dict()
        state.update(theta=self.theta, dt=self.dt, mu=self.mu, initial=self.initial, x=self.x)
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self.theta = float(state["theta"])
        self.dt = float(state["dt"])
        self.mu = float(state["mu"])
        self.initial = float(state["initial"])
        self.x = float(state["x"])


def make_noise(
    kind: str, sigma: float, seed: int | None = None, theta: float = 0.15, dt: float = 1e-2
) -> ActionNoise:
    """Build the noise named `kind` ("gaussian" or "ou"); theta and dt apply to OU only."""
    if kind == "gaussian":
        return GaussianNoise(sigma, seed=seed)
    if kind == "ou":
        return OrnsteinUhlenbeckNoise(sigma, theta=theta, dt=dt, seed=seed)
    raise ValueError(f"unknown noise kind {kind!r}; known kinds: {', '.join(NOISE_KINDS)}")
