"""Collecting experience: training episodes on one or more servers, one step at a time, split
into a send half and a receive half.

The trainer sends every server its next command, runs its gradient updates while the servers
simulate, and only then receives (`LocalCollector`). A `Collector` is anything with that shape:
the same loop drives remote sampling workers (`agent_client.training.sampling.ray_workers`),
which is the same idea at the scale of machines.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from agent_client.drivers.episode import Episode
from agent_client.drivers.policy import ActionScale
from agent_client.drivers.safety import NONE as NO_OVERRIDE
from agent_client.drivers.safety import Override, SafetyLayer
from agent_client.envs.remote_env import RemoteEnv
from agent_client.evaluation.metrics import EpisodeSummary, episode_summary
from agent_client.rl.features import FeatureMap
from agent_client.rl.lanes import LaneChoice
from protocol.errors import ErrorCode
from protocol.messages import Observation, OptionValue

EPISODE_FAILURES = (ErrorCode.SIMULATOR_ERROR.value,)
"""Error codes after which the server's next reset starts afresh: a new episode is tried. (An
ego that cannot enter is retried on other seeds by `RemoteEnv` itself, then `InsertionFailed`.)"""
MAX_FAILURES_IN_A_ROW = 5
"""Failed episodes in a row after which the error is raised."""


@dataclass
class Transition:
    """One step as the replay buffer stores it (normalised acceleration, lane choice index)."""

    x: np.ndarray
    u: float
    lane: int
    reward: float
    next_x: np.ndarray
    terminated: bool
    mask: np.ndarray
    next_mask: np.ndarray


@dataclass
class Slot:
    """The training episode running on one server."""

    env_index: int
    obs: Observation
    x: np.ndarray
    mask: np.ndarray
    episode: Episode
    """Its observations and rewards so far (let go by `summarise`: read `figures()`)."""
    states: list[np.ndarray] = field(default_factory=list)
    accelerations: list[float] = field(default_factory=list)
    lanes: list[int] = field(default_factory=list)
    ended_at: int | None = None
    """Once finished: how many of the transitions that came with it, in their order, were
    taken up to its last one (None: all of them); its row's env step count."""
    summary: EpisodeSummary | None = None
    """Once finished where it ran (`summarise`): its figures, its observations let go."""

    def summarise(self) -> None:
        """Keep the finished episode's figures and let its observations go: what crosses
        between processes is then a few numbers, not every observation of the episode."""
        self.summary = episode_summary(self.episode)
        self.episode = Episode(self.episode.episode, self.episode.seed, self.episode.step_length)

    def figures(self) -> EpisodeSummary:
        """The finished episode's figures (computed here unless `summarise` did already)."""
        return self.summary if self.summary is not None else episode_summary(self.episode)


@dataclass
class Collected:
    """What one receive brought: new transitions and the training episodes that ended."""

    transitions: list[Transition] = field(default_factory=list)
    finished: list[Slot] = field(default_factory=list)
    failed_episodes: int = 0
    """Simulator episodes that failed and were started again (by a sampling worker)."""
    reconnects: int = 0
    """Lost servers a sampling worker connected to again (or its own simulator restarted)."""

    def extend(self, other: Collected) -> None:
        """Append what another receive brought, keeping where each finished episode ended
        among all the transitions (`Slot.ended_at`)."""
        offset = len(self.transitions)
        for slot in other.finished:
            ended = slot.ended_at if slot.ended_at is not None else len(other.transitions)
            slot.ended_at = offset + ended
        self.transitions += other.transitions
        self.finished += other.finished
        self.failed_episodes += other.failed_episodes
        self.reconnects += other.reconnects


Chooser = Callable[[Sequence[Slot]], tuple[np.ndarray, np.ndarray]]
"""Actions for the running episodes: normalised accelerations (N,) and lane choice indices (N,)."""


class Collector(Protocol):
    """Experience from simulators, in two halves around the learner's updates."""

    def send(self) -> None:
        """Start the next step (or episode) on every simulator; does not wait."""

    def receive(self) -> Collected:
        """Wait for what `send` started; the transitions and finished episodes it gave."""

    def drop_episodes(self) -> None:
        """Forget the running episodes (after a failure); the next `send` starts new ones."""

    def close(self) -> None:
        """Release what the collector holds of its own (workers, connections)."""


class LocalCollector:
    """Training episodes on the servers of this process's `RemoteEnv`s."""

    def __init__(
        self,
        envs: Sequence[RemoteEnv],
        features: FeatureMap,
        lanes: LaneChoice,
        scale: ActionScale,
        choose: Chooser,
        next_seed: Callable[[], int],
        on_start: Callable[[int], None] | None = None,
        reset_options: Mapping[str, OptionValue] | None = None,
        safety: SafetyLayer | None = None,
        override_penalty: float = 0.0,
        learn_own_decision: bool = False,
    ) -> None:
        self.envs = list(envs)
        self.safety = safety
        """Applied to every decision, as when the policy drives (None: none in training)."""
        self.override_penalty = override_penalty
        """Taken off the reward of a decision the safety layer overrode."""
        self.learn_own_decision = learn_own_decision
        """Store the policy's decision where the layer overrode it (else the executed one)."""
        self.features = features
        self.lanes = lanes
        self.scale = scale
        self.choose = choose
        self.next_seed = next_seed
        self.on_start = on_start
        self.reset_options = dict(reset_options or {})
        self.slots: list[Slot | None] = [None] * len(self.envs)
        self._sent: list[tuple[float, int, Override] | int | None] = [None] * len(self.envs)
        """Per server: (u, lane, what the safety layer overrode) of a step in flight, the seed
        of a reset in flight, or None."""

    def send(self) -> None:
        running = [slot for slot in self.slots if slot is not None]
        for index, slot in enumerate(self.slots):
            if slot is None:
                seed = self.next_seed()
                self.envs[index].send_reset(seed=seed, options=self.reset_options)
                self._sent[index] = seed
        if not running:
            return
        us, lane_choices = self.choose(running)
        for slot, u, lane in zip(running, us, lane_choices, strict=True):
            command = self.lanes.command(int(lane), slot.obs)
            acceleration = self.scale.to_env(float(u), slot.obs)
            override = NO_OVERRIDE
            if self.safety is not None:  # the executed action is learned from, or the own
                acceleration, command, override = self.safety.apply(slot.obs, acceleration, command)
                if override.acceleration and not self.learn_own_decision:
                    u = self.scale.to_policy(acceleration, slot.obs)
                if override.lane_change and not self.learn_own_decision:
                    lane = self.lanes.index_of(command, slot.obs)
            self.envs[slot.env_index].send_command(acceleration, command)
            self._sent[slot.env_index] = (float(u), int(lane), override)

    def receive(self) -> Collected:
        collected = Collected()
        for index, env in enumerate(self.envs):
            sent, self._sent[index] = self._sent[index], None
            if isinstance(sent, int):
                self._start(index, env)
            elif sent is not None:
                self._step(index, env, sent, collected)
        return collected

    def _start(self, index: int, env: RemoteEnv) -> None:
        obs = env.receive_reset_observation()  # may have retried the insertion on another seed
        episode = Episode(seed=env.episode_seed, step_length=env.step_length)
        episode.add(obs)
        self.slots[index] = Slot(index, obs, self.features(obs), self.lanes.mask(obs), episode)
        if self.on_start is not None:
            self.on_start(index)

    def _step(
        self,
        index: int,
        env: RemoteEnv,
        sent: tuple[float, int, Override],
        collected: Collected,
    ) -> None:
        slot = self.slots[index]
        assert slot is not None
        u, lane, override = sent
        next_obs, reward = env.receive_observation()
        if self.safety is not None:
            slot.episode.overrides.append(override)
            if override.any:
                reward -= self.override_penalty
        terminated, truncated = next_obs.terminated, next_obs.truncated
        next_x, next_mask = self.features(next_obs), self.lanes.mask(next_obs)
        collected.transitions.append(
            Transition(slot.x, u, lane, reward, next_x, terminated, slot.mask, next_mask)
        )
        slot.states.append(slot.x)
        slot.accelerations.append(u)
        slot.lanes.append(lane)
        slot.episode.add(next_obs, reward)
        slot.obs, slot.x, slot.mask = next_obs, next_x, next_mask
        if terminated or truncated:
            slot.ended_at = len(collected.transitions)
            collected.finished.append(slot)
            self.slots[index] = None

    def drop_episodes(self) -> None:
        self.slots = [None] * len(self.envs)
        self._sent = [None] * len(self.envs)

    def drop_episode(self, index: int) -> None:
        """Forget the episode on server `index` (something else used that server meanwhile)."""
        self.slots[index] = None
        self._sent[index] = None

    def close(self) -> None:
        """Nothing of its own: the environments belong to the trainer."""
