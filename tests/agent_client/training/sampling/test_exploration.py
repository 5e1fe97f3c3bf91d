"""The exploration schedule: warm-up driver, then policy noise decaying to `noise_final`."""

from __future__ import annotations

import numpy as np
import pytest

from agent_client.drivers.episode import Episode
from agent_client.drivers.policy import ActionScale
from agent_client.training.config import TrainConfig, apply_overrides
from agent_client.training.sampling.collect import Slot
from agent_client.training.sampling.exploration import WarmupDriver, learning, noise_scale_at
from tests.agent_client.rl.test_rewards import lead, make_obs

SCALE = ActionScale(-6.0, 3.0)


def config(**values: object) -> TrainConfig:
    return apply_overrides(TrainConfig(), dict(values))


def slot(mask: list[bool]) -> Slot:
    obs = make_obs(speed=10.0, leader=lead(30.0, 10.0))
    episode = Episode(episode=0, seed=0, step_length=0.1)
    return Slot(0, obs, np.zeros(6, np.float32), np.array(mask), episode)


def test_noise_decays_linearly_to_its_final_scale_and_stays_there() -> None:
    c = config(noise_final=0.2, noise_decay_steps=1000)
    assert noise_scale_at(c, 0) == 1.0
    assert noise_scale_at(c, 500) == pytest.approx(0.6)
    assert noise_scale_at(c, 1000) == pytest.approx(0.2)
    assert noise_scale_at(c, 10**6) == pytest.approx(0.2)


def test_the_policy_acts_from_learning_starts_on() -> None:
    c = config(learner={"learning_starts": 100})
    assert not learning(c, 99)
    assert learning(c, 100)


@pytest.mark.parametrize("policy", ["idm", "random"])
def test_warmup_actions_are_normalised_and_only_choose_possible_lanes(policy: str) -> None:
    driver = WarmupDriver(policy, SCALE, 0.5, np.random.default_rng(0))
    keep_or_right = slot([True, False, True])
    actions = [driver(keep_or_right) for _ in range(2000)]
    accelerations = np.array([a for a, _ in actions])
    lanes = {lane for _, lane in actions}
    assert accelerations.min() >= -1.0 and accelerations.max() <= 1.0
    assert lanes <= {0, 2}
    if policy == "random":
        assert lanes == {0, 2} and accelerations.std() > 0.4
    else:  # IDM plus noise: mostly keep, now and then a possible change
        share = np.mean([lane != 0 for _, lane in actions])
        assert 0.0 < share < 0.1
