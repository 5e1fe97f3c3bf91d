"""The exploration schedule shared by the trainer and the sampling workers.

Before `learning_starts` transitions the actions come from a warm-up driver (IDM plus noise, IDM
+ MOBIL plus noise, or uniform random); afterwards from the policy plus noise whose scale decays
linearly from 1 to `noise_final` over `noise_decay_steps` environment steps.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from agent_client.drivers.idm import IDMDriver
from agent_client.drivers.mobil import IDMMobilDriver
from agent_client.drivers.policy import ActionScale
from agent_client.rl.lanes import LANE_COMMANDS
from agent_client.training.sampling.collect import Slot

if TYPE_CHECKING:  # not at run time: a sampling worker process never imports torch
    from agent_client.training.config import TrainConfig

WARMUP_LANE_PROBABILITY = 0.05
"""Share of warm-up decisions with a random (possible) lane change."""


def noise_scale_at(config: TrainConfig, global_step: int) -> float:
    """The multiplier of the acceleration noise after `global_step` environment steps."""
    fraction = min(1.0, global_step / max(config.noise_decay_steps, 1))
    return 1.0 + (config.noise_final - 1.0) * fraction


def learning(config: TrainConfig, global_step: int) -> bool:
    """Whether the policy acts (True) or the warm-up driver (False)."""
    return global_step >= config.learner.learning_starts


class WarmupDriver:
    """The warm-up actions: IDM's acceleration plus Gaussian noise (and now and then a random
    possible lane change); IDM + MOBIL's, the lane changes a route needs included, plus the
    same noise, so that the buffer holds merges and exits from the start; or a uniform random
    acceleration and lane choice."""

    def __init__(
        self, policy: str, scale: ActionScale, noise_sigma: float, rng: np.random.Generator
    ) -> None:
        self.policy = policy
        self.scale = scale
        self.noise_sigma = noise_sigma
        self.rng = rng
        self.idm = IDMDriver()
        self._mobil: dict[int, IDMMobilDriver] = {}
        """One IDM + MOBIL per server (it keeps the time of its last lane decision)."""

    def __call__(self, slot: Slot) -> tuple[float, int]:
        """(normalised acceleration, lane choice index) for the episode in `slot`."""
        possible = np.flatnonzero(slot.mask)
        if self.policy == "idm+mobil":
            driver = self._mobil.setdefault(slot.env_index, IDMMobilDriver())
            acceleration, change = driver.act(slot.obs)
            u = self.scale.to_policy(acceleration, slot.obs)
            u += self.rng.normal(0.0, self.noise_sigma)
            lane = 0 if len(slot.mask) == 4 else LANE_COMMANDS.index(change)  # 4: its own choice
            if not slot.mask[lane] or self.rng.random() < WARMUP_LANE_PROBABILITY:
                lane = int(self.rng.choice(possible))
            return float(np.clip(u, -1.0, 1.0)), lane
        if self.policy == "idm":
            acceleration, _ = self.idm.act(slot.obs)
            u = self.scale.to_policy(acceleration, slot.obs)
            u += self.rng.normal(0.0, self.noise_sigma)
            lane = 0
            if not slot.mask[lane] or self.rng.random() < WARMUP_LANE_PROBABILITY:
                lane = int(self.rng.choice(possible))
            return float(np.clip(u, -1.0, 1.0)), lane
        return float(self.rng.uniform(-1.0, 1.0)), int(self.rng.choice(possible))
