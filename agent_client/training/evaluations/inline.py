"""Greedy evaluations during training: what one is (`EvaluationJob`), how its seeds are judged,
and `Evaluator`, which drives one inline on the training servers while training waits.

On servers of their own (`agent-client train --eval-server`) `EvaluationPool` runs the same
jobs, one worker process per server, in the background or while training waits.

A job with a `screen` ends as soon as its first seeds have certainly failed
(`EvaluationJob.screen`, `judge_in_order`): the episodes left could not change the verdict, and
run inline they are time the learner does not get.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from agent_client.drivers.episode import Driver, Episode
from agent_client.envs.remote_env import RemoteEnv
from agent_client.evaluation.metrics import EpisodeSummary, episode_summary
from agent_client.evaluation.targets import FailureScreen
from protocol.messages import Observation


@dataclass
class EvaluationJob:
    """One evaluation: who drives, on which seeds, and what the trainer keeps with the result."""

    name: str
    """"idm" for the baseline, "policy" for the learner's greedy policy."""
    driver: Driver
    seeds: list[int]
    context: dict[str, Any] = field(default_factory=dict)
    """The trainer's bookkeeping (the episode it started at, the policy state evaluated...)."""
    stop_on_collision: bool = False
    """End the evaluation once its first seeds, judged in order, include a collision: it has
    failed, the rest would not change it. The replies in flight on the other servers are read
    first; the summaries are those of the seeds judged (the aggregate's ``episodes`` says how
    many)."""
    screen: FailureScreen | None = None
    """End the evaluation as soon as its first seeds fail a target whatever the others give
    (`FailureScreen`; a collision among them). Read the same way as `stop_on_collision`."""
    stopped: str | None = None
    """Set when the evaluation ended early: the target it had failed for certain."""


def certain_failure(
    job: EvaluationJob, done: Sequence[EpisodeSummary], remaining: Sequence[int]
) -> str | None:
    """The target the finished episodes `done` have failed for certain, whatever the seed
    indices in `remaining` give, if the job screens (`screen`, or `stop_on_collision`)."""
    if job.screen is not None:
        return job.screen.failed(done, remaining)
    if job.stop_on_collision and any(s.collisions for s in done):
        return "no_collisions"
    return None


def judge_in_order(
    job: EvaluationJob, done: Mapping[int, EpisodeSummary], judged: int
) -> tuple[int, str | None]:
    """Judge the seeds finished in order after the first `judged`: how many are now judged,
    and the target the first of them have failed for certain, if any (`certain_failure`).

    In seed order, not in the order episodes finish, so the same policy gets the same verdict,
    episodes and steps however its episodes are spread over servers and processes.
    """
    seeds = len(job.seeds)
    while judged < seeds and judged in done:
        judged += 1
        if judged < seeds:
            first = [done[i] for i in range(judged)]
            failed = certain_failure(job, first, range(judged, seeds))
            if failed is not None:
                return judged, failed
    return judged, None


@dataclass
class _Running:
    seed_index: int
    episode: Episode
    obs: Observation | None = None
    """None until the reset's reply arrives."""


class Evaluator:
    """Runs `EvaluationJob`s on its environments, one at a time."""

    def __init__(self, envs: Sequence[RemoteEnv]) -> None:
        if not envs:
            raise ValueError("an evaluator needs at least one environment")
        self.envs = list(envs)
        self.job: EvaluationJob | None = None
        self._next_seed = 0
        self._running: list[_Running | None] = [None] * len(self.envs)
        self._sent: list[str | None] = [None] * len(self.envs)
        self._done: dict[int, EpisodeSummary] = {}
        self._judged = 0
        self._drivers: list[Driver] = []
        """The job's driver, one copy per environment: a driver may keep an episode's state
        (IDM + MOBIL its decision times), which episodes in lock-step must not share."""

    @property
    def busy(self) -> bool:
        return self.job is not None

    def start(self, job: EvaluationJob) -> None:
        if self.job is not None:
            raise RuntimeError("an evaluation is already running")
        self.job = job
        self._next_seed = 0
        self._done = {}
        self._judged = 0
        self._drivers = [copy.deepcopy(job.driver) for _ in self.envs]

    def send(self) -> None:
        """Start the next step (or episode) of the running job on every environment."""
        job = self.job
        if job is None:
            return
        for index, env in enumerate(self.envs):
            running = self._running[index]
            if running is None and self._next_seed < len(job.seeds):
                seed_index, self._next_seed = self._next_seed, self._next_seed + 1
                seed = job.seeds[seed_index]
                env.send_reset(seed=seed)
                episode = Episode(episode=seed_index, seed=seed, step_length=env.step_length)
                self._running[index] = _Running(seed_index, episode)
                self._sent[index] = "reset"
            elif running is not None and running.obs is not None:
                driver = self._drivers[index]
                acceleration, lane_change = driver.act(running.obs)
                override = getattr(driver, "override", None)  # as `run_episode` counts it
                if override is not None:
                    running.episode.overrides.append(override)
                env.send_command(acceleration, lane_change)
                self._sent[index] = "step"

    def receive(self) -> tuple[EvaluationJob, list[EpisodeSummary]] | None:
        """Read what `send` started; the job and its summaries (in seed order) once it is done."""
        job = self.job
        if job is None:
            return None
        finished = False
        for index, env in enumerate(self.envs):  # every reply in flight is read, even after a crash
            sent, self._sent[index] = self._sent[index], None
            running = self._running[index]
            if sent is None or running is None:
                continue
            if sent == "reset":
                running.obs = env.receive_reset_observation()
                running.episode.add(running.obs)
                continue
            running.obs, reward = env.receive_observation()
            running.episode.add(running.obs, reward)
            if running.obs.terminated or running.obs.truncated:
                self._done[running.seed_index] = episode_summary(running.episode)
                self._running[index] = None
                finished = True
        if finished:
            self._judged, job.stopped = judge_in_order(job, self._done, self._judged)
        if job.stopped is not None or self._judged == len(job.seeds):
            return self._finish(job)
        return None

    def _finish(self, job: EvaluationJob) -> tuple[EvaluationJob, list[EpisodeSummary]]:
        """The summaries of the judged seeds, in seed order; episodes still running, and any
        finished beyond the judged ones, are given up."""
        summaries = [self._done[i] for i in range(self._judged)]
        self.abort()
        return job, summaries

    def run(self, job: EvaluationJob) -> list[EpisodeSummary]:
        """The whole evaluation at once (nothing else runs on these servers meanwhile)."""
        self.start(job)
        while True:
            self.send()
            result = self.receive()
            if result is not None:
                return result[1]

    def abort(self) -> None:
        """Give the running evaluation up; `start` may begin another."""
        self.job = None
        self._running = [None] * len(self.envs)
        self._sent = [None] * len(self.envs)
