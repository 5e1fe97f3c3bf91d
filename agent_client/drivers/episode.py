"""The one episode loop: reset, then ask the driver and step until the episode ends.

Driving, evaluating, recording human drivers for calibration and collecting demonstrations for
pre-training all run their episodes through `run_episode`; a `StepHook` sees every transition.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Protocol

from agent_client.drivers.safety import Override
from agent_client.envs.remote_env import RemoteEnv
from protocol.messages import Observation, OptionValue


@dataclass
class Episode:
    """An episode as it was driven: every observation, and the reward of every step."""

    episode: int = 0
    seed: int = 0
    step_length: float | None = None
    """The simulator's step (s), for jerk at its resolution; None spreads it over the decision."""
    observations: list[Observation] = field(default_factory=list)
    rewards: list[float] = field(default_factory=list)
    """rewards[i] is the reward of the step from observations[i] to observations[i + 1]."""
    overrides: list[Override] = field(default_factory=list)
    """overrides[i]: what a safety layer changed of the decision taken on observations[i]
    (`agent_client.drivers.safety`; empty for a driver without one)."""

    def add(self, obs: Observation, reward: float = 0.0) -> None:
        """Append an observation (the reward of the step to it is ignored for the first)."""
        if self.observations:
            self.rewards.append(reward)
        self.observations.append(obs)


class Driver(Protocol):
    """Anything that maps a named observation to (acceleration m/s^2, lane change).

    A driver may also name reset options its episodes need (`reset_options`): the simulator's
    own driver asks for ``ego_driver``; and one with a safety layer says what it overrode in its
    last decision (`override`, read after each `act`)."""

    def act(self, obs: Observation) -> tuple[float, int]: ...


StepHook = Callable[[Observation, tuple[float, int], float, Observation], None]
"""Called after every step with (observation before, action, reward, observation after)."""


def run_episode(
    env: RemoteEnv,
    driver: Driver,
    seed: int,
    episode: int = 0,
    *,
    options: dict[str, OptionValue] | None = None,
    on_step: StepHook | None = None,
) -> Episode:
    """Drive one episode from reset to its end; returns every observation and reward."""
    own = getattr(driver, "reset_options", None)
    if own:
        options = {**(options or {}), **own}
    env.send_reset(seed=seed, options=options)
    recorder = Episode(episode=episode, seed=seed, step_length=env.step_length)
    obs = env.receive_reset_observation()
    recorder.add(obs)
    while True:
        action = driver.act(obs)
        override = getattr(driver, "override", None)
        if override is not None:
            recorder.overrides.append(override)
        env.send_command(*action)
        after, reward = env.receive_observation()
        recorder.add(after, reward)
        if on_step is not None:
            on_step(obs, action, reward, after)
        obs = after
        if after.terminated or after.truncated:
            return recorder


def drive(env: RemoteEnv, driver: Driver, episodes: int, first_seed: int = 0) -> Iterator[Episode]:
    """Drive `episodes` episodes with seeds first_seed, first_seed + 1, ..."""
    for index in range(episodes):
        yield run_episode(env, driver, first_seed + index, index)


class Idle:
    """A driver that asks for nothing: for episodes in which the simulator drives the ego."""

    name = "idle"

    def act(self, obs: Observation) -> tuple[float, int]:
        return 0.0, 0


class SimulatorDriver(Idle):
    """The simulator's own driver model drives the ego (reset option ``ego_driver``); the client
    watches: a reference to compare learned drivers with (``sumo`` as a driver spec)."""

    name = "sumo"
    reset_options: dict[str, OptionValue] = {"ego_driver": "sumo"}
