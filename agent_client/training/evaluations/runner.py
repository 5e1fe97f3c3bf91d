"""A training run's evaluations: the reference's once, then the policy's, and their verdicts.

`EvaluationSchedule` says at which episode's end a policy evaluation starts; this module runs
it and books what it found. On evaluation servers of their own (`EvaluationPool`) an evaluation
runs in the background while training goes on, its workers in the kernel's idle scheduling
class, its verdict read at the episode where the next may be due; one that could complete
convergence, and every one without such servers (inline, on the training servers) or with
`eval_while_training` off, runs while training waits. So the run (episodes, verdicts, the
converged episode) is the same either way. Each verdict is judged against the reference's
figures on the same seeds (`Reference`; with several scenarios, each on seeds of its own,
against its own figures), keeps the best policy so far (`policy.pt`), and counts towards
convergence.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, TypeVar

from agent_client.drivers.episode import Driver
from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import BridgeError, ServerError, ServerUnavailable
from agent_client.evaluation.metrics import EpisodeSummary, aggregate
from agent_client.evaluation.targets import FailureScreen
from agent_client.training.config import TrainConfig
from agent_client.training.evaluations.inline import EvaluationJob, Evaluator
from agent_client.training.evaluations.pool import EvaluationPool
from agent_client.training.evaluations.reference import Reference
from agent_client.training.evaluations.schedule import EvaluationSchedule
from agent_client.training.progress import Profile, Progress, evaluation_line
from agent_client.training.run_log import RunLog
from agent_client.training.sampling.collect import EPISODE_FAILURES, MAX_FAILURES_IN_A_ROW

T = TypeVar("T")
UNTRAINED = 100.0
"""Taken off the score of an evaluation before the actor learned (it drives as its reference):
`policy.pt` is the best trained policy once there is one."""


class Retrying(Protocol):
    """Runs work on the training servers, reconnecting or restarting episodes on a failure."""

    def __call__(self, work: Callable[[], T]) -> T: ...


@dataclass(frozen=True)
class TrainingSide:
    """What the evaluations need of the training run they judge."""

    envs: Sequence[RemoteEnv]
    """The training servers' connections: inline evaluations drive them."""
    resilient: Retrying
    """The training side's retry of work on those servers."""
    drop_episodes: Callable[[], None]
    """Forget the training episodes under way (an inline evaluation took their servers)."""
    policy_state: Callable[[], dict[str, Any]]
    """The policy to evaluate now (the deployed networks' state)."""
    trained: Callable[[], bool]
    """Whether the policy has learned anything yet (a residual's actor waits for its burn-in:
    until then it drives as its reference, and its passes do not count)."""
    driver: Callable[[dict[str, Any]], Driver]
    """The driver of a policy state."""
    save_policy: Callable[[str, dict[str, Any]], None]
    """Save a policy state under a name in the run folder."""
    elapsed: Callable[[], float]
    """The run's wall time so far, in seconds."""
    one_lane: bool
    """Every scenario is one lane: nobody passes the leader-at-entry, whose speed then bounds
    any driver's (`Reference.screen`)."""


class Evaluations:
    """Starts, runs and books a training run's evaluations."""

    def __init__(
        self,
        config: TrainConfig,
        out: Path,
        reference: Driver,
        figures: Reference,
        pool: EvaluationPool | None,
        training: TrainingSide,
        profile: Profile,
        say: Callable[[str], None],
        retry_for_s: float = 0.0,
    ) -> None:
        """`reference`: the driver the policy is compared with, its figures on the evaluation
        seeds `figures`; `pool`: the evaluation servers' workers (None: evaluations run inline,
        on the training servers); `retry_for_s` > 0: how long to wait for a lost evaluation
        server to come back."""
        self.config = config
        self.out = out
        self.reference = reference
        self.figures = figures
        self.pool = pool
        self.training = training
        self.profile = profile
        self.say = say
        self.retry_for_s = retry_for_s
        self.schedule = EvaluationSchedule(config)
        self.converged = False
        """Converged with `stop_when_converged` on: the run is to stop."""
        self.restored: dict[str, Any] | None = None
        """A resumed run's evaluation that was under way when it stopped (`running`)."""
        self.pending: EvaluationJob | None = None
        """The evaluation running in the background (its verdict due at episode
        ``context["collect_at"]``; the reference's before the first policy evaluation)."""
        self._run_state: tuple[Progress, RunLog] | None = None
        """The run's progress and log (`begin`)."""

    @property
    def _progress(self) -> Progress:
        assert self._run_state is not None, "begin() first"
        return self._run_state[0]

    @property
    def _log(self) -> RunLog:
        assert self._run_state is not None, "begin() first"
        return self._run_state[1]

    @property
    def background(self) -> bool:
        """Whether evaluations run in the background (on evaluation servers of their own)."""
        return self.pool is not None and self.config.eval_while_training

    # ----------------------------------------------------------------------- the run

    def begin(self, progress: Progress, log: RunLog) -> None:
        """Book into the run's `progress` (a resumed run's, restored) and `log` from now on;
        evaluate the reference first if its figures are not known yet (the training episodes
        under way are dropped after it), then an evaluation a resumed run had under way."""
        self._run_state = progress, log
        if not self.figures.known and self.config.eval_every > 0:
            servers = len(self.pool.workers if self.pool is not None else self.training.envs)
            job = EvaluationJob("idm", self.reference, self.figures.seeds)
            name = f"the reference ({getattr(self.reference, 'name', 'a policy')})"
            if self.background:
                self.say(f"evaluating {name} in the background ({servers} servers)")
                self.start_background(job)
            else:
                self.say(f"evaluating {name} on the evaluation seeds ({servers} servers)")
                self._book_reference(self._resilient(lambda: self._run(job)))
            self.training.drop_episodes()
        running = self.restored
        if running is not None:  # it was under way when the run stopped
            self._evaluate(self._policy_job(running["policy_state"], running["context"]))
            self.restored = None  # a checkpoint before this keeps it

    def resume(self, running: dict[str, Any]) -> None:
        """A resumed run's checkpoint had `running` under way (`running()`): `begin` starts it
        again (until then, a checkpoint keeps it)."""
        self.restored = running

    def poll(self) -> None:
        """Let the background evaluation's workers have their next seeds. A failure there gives
        the evaluation up; it runs again, training waiting, when its verdict is due."""
        pool = self.pool
        if pool is None or pool.job is None:
            return
        started = time.perf_counter()
        try:
            pool.poll()
        except BridgeError as exc:  # the pool has stopped the job's episodes
            self.say(f"the background evaluation failed ({exc}); it runs again when due")
        finally:
            self.profile.seconds["evaluation"] += time.perf_counter() - started

    def episode_ended(self, collided: bool, learning: bool, interrupted: bool) -> None:
        """A training episode ended (`collided`: with a collision; `learning`: learning has
        begun): read a background verdict due now, start a policy evaluation if one is due.
        `interrupted` (Ctrl-C): neither wait for one nor start one."""
        progress, pending = self._progress, None if interrupted else self.pending
        if pending is not None and progress.episode >= pending.context.get("collect_at", math.inf):
            self.collect()  # before the next is due: its verdict decides when that one runs
        if self.schedule.episode_ended(progress, collided, learning) and not interrupted:
            self._start_policy_evaluation()

    def collect(self) -> None:
        """Wait for the background evaluation's end and book its verdict."""
        job = self.pending
        assert job is not None
        summaries = self._resilient(lambda: self._run(job))
        self.pending = None
        self._book(job, summaries)

    def cancel(self) -> None:
        """Give the background evaluation up (the run ends without its verdict)."""
        self.pending = None
        if self.pool is not None:
            self.pool.cancel()

    def running(self) -> dict[str, Any] | None:
        """The policy evaluation under way in the background (its policy and context), which a
        resumed run starts again: else it would resume without the verdict blocking gives."""
        job = self.pending
        if job is None and self.restored is not None:  # not started again yet
            return self.restored
        if job is None or job.name != "policy":
            return None  # the reference's runs again anyway: the checkpoint has none
        keep = ("episode", "global_step", "collect_at")
        return {"policy_state": job.context["policy_state"],
                "context": {key: job.context[key] for key in keep}}  # fmt: skip

    def start_background(self, job: EvaluationJob) -> None:
        """Hand `job` to the pool's workers (training waits while they take its driver)."""
        pool = self.pool
        assert pool is not None
        with self._training_waits(job):
            self._resilient(lambda: pool.start(job))
        self.pending = job

    # ----------------------------------------------------------------------- starting

    def _start_policy_evaluation(self) -> None:
        """Evaluate the current policy: in the background, its verdict read where the next
        evaluation may be due, or now while training waits (inline, with `eval_while_training`
        off, or when a pass would complete convergence)."""
        if self.pending is not None:  # the reference's, or a verdict due at this episode
            self.collect()
        progress = self._progress
        context = {
            "episode": progress.episode,
            "global_step": progress.global_step,
            "trained": self.training.trained(),
            "collect_at": self.schedule.started(progress),  # its verdict must be known there
        }
        self._evaluate(self._policy_job(self.training.policy_state(), context))

    def _evaluate(self, job: EvaluationJob) -> None:
        """Start policy evaluation `job` in the background, or run and book it now."""
        if self.background and not self.schedule.could_converge(self._progress):
            self.start_background(job)
            return
        summaries = self._resilient(lambda: self._run(job))
        if self.pool is None:
            self.training.drop_episodes()  # the evaluation used the training servers
        self._book(job, summaries)

    def _policy_job(self, state: dict[str, Any], context: dict[str, Any]) -> EvaluationJob:
        """The evaluation of policy `state` on the held-out seeds (`context`: the episode and
        the env step it was taken at, and where its verdict is due)."""
        screen = self._screen() if self.config.eval_screen else None
        context = {**context, "policy_state": state,
                   "evaluation_seconds_before": self.profile.evaluation_seconds}  # fmt: skip
        driver = self.training.driver(state)
        return EvaluationJob(
            "policy", driver, self.figures.seeds, context, stop_on_collision=True, screen=screen
        )

    def _screen(self) -> FailureScreen:
        """What stops an evaluation that has certainly failed (`Reference.screen`): the
        scenario's time limit bounds an episode's steps (the env's options, as the server has
        them)."""
        options = self.training.envs[0].scenario_options
        limit = _number(options.get("max_episode_time"))
        interval = _number(options.get("decision_interval"))
        max_steps = math.ceil(limit / interval) + 10 if limit and interval else None
        return self.figures.screen(max_steps, self.training.one_lane)

    # ----------------------------------------------------------------------- running

    def _run(self, job: EvaluationJob) -> list[EpisodeSummary]:
        """Run `job` to its end (or wait for its end, if it runs in the background) while
        training waits: on the evaluation servers' workers, else in lock-step on the training
        servers."""
        with self._training_waits(job):
            if self.pool is None:
                return Evaluator(self.training.envs).run(job)
            if self.pool.job is job:
                return self.pool.finish()
            return self.pool.run(job)  # from its start: a failure ended it in the background

    @contextmanager
    def _training_waits(self, job: EvaluationJob) -> Iterator[None]:
        """Book the time training waits for `job` (the reference's apart, too)."""
        started = time.perf_counter()
        try:
            yield
        finally:
            waited = time.perf_counter() - started
            self.profile.blocking_evaluation += waited
            if job.name == "idm":
                self.profile.baseline_evaluation += waited

    def _resilient(self, work: Callable[[], T]) -> T:
        """Run `work`; where it runs on the evaluation servers, a failure there reconnects or
        restarts only their workers (training's episodes go on), and a failure that repeats
        (the same policy on the same seeds: not luck) ends the run. Inline, the training
        side's retry."""
        pool = self.pool
        if pool is None:
            return self.training.resilient(work)
        failures = 0
        while True:
            try:
                return work()
            except ServerUnavailable as exc:
                failures += 1
                if self.retry_for_s <= 0 or failures >= MAX_FAILURES_IN_A_ROW:
                    raise
                self.say(f"{exc}; waiting up to {self.retry_for_s:g} s for the evaluation servers")
                pool.reconnect(self.retry_for_s)
                self._progress.reconnects += 1
                addresses = ", ".join(worker.address for worker in pool.workers)
                self.say(f"reconnected to {addresses}; the evaluation starts again")
            except ServerError as exc:
                failures += 1
                if exc.code not in EPISODE_FAILURES or failures >= MAX_FAILURES_IN_A_ROW:
                    raise
                self._progress.failed_episodes += 1
                self.say(f"the simulator failed in an evaluation ({exc}); it starts again")

    # ----------------------------------------------------------------------- verdicts

    def _book_reference(self, summaries: list[EpisodeSummary]) -> None:
        """Keep the reference's figures on the evaluation seeds (and in idm_eval.json)."""
        overall = self.figures.book(summaries)
        (self.out / "idm_eval.json").write_text(json.dumps(overall, indent=2))

    def _book(self, job: EvaluationJob, summaries: list[EpisodeSummary]) -> None:
        """Book `job`'s verdict: the reference's figures, or the policy's evaluation (its row
        in the log, the best policy so far, convergence)."""
        if job.name == "idm":
            self._book_reference(summaries)
            return
        progress, complete = self._progress, len(summaries) == len(job.seeds)
        met, failed_scenarios = self.figures.targets(summaries)
        if job.stopped is not None:  # failed for certain, whatever the partial figures say
            met[job.stopped] = False
        steps = sum(s.steps for s in summaries)
        progress.evaluation_steps += steps
        progress.wall_time = self.training.elapsed()
        passes = complete and all(met.values()) and job.context.get("trained", True)
        self.schedule.judged(progress, passes, steps, job.context["global_step"])
        result = aggregate(summaries)
        ratio = result["speed_ratio_to_ceiling"]  # NaN where no ceiling is reported (the ring)
        score = sum(met.values()) + (ratio if math.isfinite(ratio) else 0.0)
        if not job.context.get("trained", True):
            score -= UNTRAINED  # the reference's clone: any trained policy is kept over it
        if complete and score >= progress.best_score:  # a stopped one's figures are partial
            progress.best_score = score
            self.training.save_policy("policy.pt", job.context["policy_state"])
        evaluation = {
            "episode": job.context["episode"],
            "global_step": job.context["global_step"],
            "wall_time": progress.wall_time,
            **result,
            "speed_ratio_to_idm": result["average_speed"] / self.figures.speed_on(summaries),
            **{f"target_{name}": passed for name, passed in met.items()},
            "passed_in_a_row": progress.passed_in_a_row,
            "trained": job.context.get("trained", True),
            "stopped": job.stopped or "",
            "failed_scenarios": failed_scenarios if len(self.config.scenarios) > 1 else "",
            "episodes_saved": len(job.seeds) - len(summaries),
            "steps": steps,
            # the learner's seconds from the job's start: all of it if training waited, else
            # the polls and the wait for its end
            "seconds": self.profile.evaluation_seconds - job.context["evaluation_seconds_before"],
            "evaluation_share": self.profile.evaluation_share(),
        }
        progress.evaluations.append(evaluation)
        self._log.evaluation(evaluation)
        self.say(evaluation_line(evaluation))
        self._check_convergence()

    def _check_convergence(self) -> None:
        progress = self._progress
        if not self.schedule.converged(progress):
            return
        if progress.converged_episode is None:
            progress.converged_episode = progress.episode
            progress.converged_time = progress.wall_time
            progress.converged_step = progress.global_step
            self.say(
                f"converged: {self.config.converged_evals} passing evaluations in a row at "
                f"episode {progress.episode} ({progress.wall_time / 60:.1f} min, "
                f"{progress.global_step} steps)"
            )
        if self.config.stop_when_converged:
            self.converged = True


def _number(value: object) -> float | None:
    """An option's number (None for a missing or non-numeric one)."""
    if isinstance(value, int | float) and not isinstance(value, bool):
        return float(value)
    return None
