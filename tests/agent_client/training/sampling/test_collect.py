"""`LocalCollector` through the safety layer, with a server faked in this process: the decision
stored where the layer overrode one is the executed one, or with ``learn_own_decision`` the
policy's own, charged `override_penalty` either way."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import pytest

from agent_client.drivers.policy import ActionScale, lane_choice
from agent_client.drivers.safety import SafetyLayer
from agent_client.rl.features import FeatureMap
from agent_client.training.sampling.collect import LocalCollector, Slot
from protocol.messages import Neighbour, Observation
from tests.agent_client.drivers.test_safety import observation

CLOSING_IN = observation(25.0, Neighbour(True, 54.0, 0.0, 0.0, "stopped"))
"""25 m/s towards a car standing 54 m ahead: full throttle is overridden (collision rule)."""
REWARD = 0.5
PENALTY = 2.0


class FakeEnv:
    """A server that answers every reset and step with `CLOSING_IN`, `REWARD` per step."""

    episode_seed = 0
    step_length = 0.1

    def __init__(self) -> None:
        self.commands: list[tuple[float, int]] = []

    def send_reset(self, seed: int, options: dict[str, Any]) -> None:
        self.episode_seed = seed

    def receive_reset_observation(self) -> Observation:
        return CLOSING_IN

    def send_command(self, acceleration: float, lane_change: int) -> None:
        self.commands.append((acceleration, lane_change))

    def receive_observation(self) -> tuple[Observation, float]:
        return CLOSING_IN, REWARD


def full_throttle(slots: Sequence[Slot]) -> tuple[np.ndarray, np.ndarray]:
    return np.ones(len(slots)), np.zeros(len(slots), int)


@pytest.mark.parametrize("own", [False, True])
def test_an_overridden_decision_is_stored_executed_or_as_the_policys_own(own: bool) -> None:
    env = FakeEnv()
    scale = ActionScale(-6.0, 3.0)
    collector = LocalCollector(
        [env], FeatureMap("cf"), lane_choice(1, 1, True), scale, full_throttle, lambda: 7,  # type: ignore[list-item]
        safety=SafetyLayer(0.1, -6.0), override_penalty=PENALTY, learn_own_decision=own,
    )  # fmt: skip
    collector.send()  # the reset
    collector.receive()
    collector.send()  # a step at full throttle, overridden
    (stored,) = collector.receive().transitions
    executed = env.commands[-1][0]
    assert executed < 3.0  # the layer braked
    assert stored.reward == pytest.approx(REWARD - PENALTY)
    if own:
        assert stored.u == 1.0  # what the policy chose, charged
    else:
        assert stored.u == pytest.approx(scale.to_policy(executed))  # what was done, charged
        assert stored.u < 1.0
