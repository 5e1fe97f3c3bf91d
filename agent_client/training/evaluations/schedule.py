"""When a training run evaluates its policy.

Every `eval_every` training episodes once learning has gone on that long, if the last
`eval_gate` training episodes had no collision (an evaluation of a policy that still crashes in
training would fail anyway: one due behind a closed gate is skipped). After a failed evaluation
the next waits until training has outweighed what it cost (`eval_budget`); after a pass there is
no wait, since a run of passes is what convergence needs. An evaluation the budget held back
starts at the first episode's end where the wait is over and the gate is open.
"""

from __future__ import annotations

import math
from collections import deque

from agent_client.training.config import TrainConfig
from agent_client.training.progress import Progress


class EvaluationSchedule:
    """Decides, at the end of each training episode, whether a policy evaluation starts."""

    def __init__(self, config: TrainConfig) -> None:
        self.config = config
        self.due = False
        """An evaluation is due but waits for the budget (and then for the gate)."""
        self.wanted = False
        """An evaluation is to start (at the next episode's end, if the run stops now)."""
        self._recent_collisions: deque[bool] = deque(maxlen=max(config.eval_gate, 1))

    def episode_ended(self, progress: Progress, collided: bool, learning: bool) -> bool:
        """Book a finished training episode (`learning`: learning has begun); whether a policy
        evaluation is to start now."""
        self._recent_collisions.append(collided)
        if progress.learning_episode is None and learning:
            progress.learning_episode = progress.episode - 1  # it began during this one
        every = self.config.eval_every
        on_time = every > 0 and progress.episode % every == 0
        if on_time and self._learned_for(progress, every) and self.gate_open():
            self.due = True
        if (
            self.due
            and self.gate_open()
            and progress.global_step >= progress.evaluation_resume_step
        ):
            self.due, self.wanted = False, True
        return self.wanted

    def started(self, progress: Progress) -> int:
        """An evaluation starts now; returns the episode at which its verdict must be known:
        the next one at which another may be due (one the gate or the budget held back started
        after a multiple of `eval_every`, and the next is due sooner)."""
        self.wanted = False
        every = self.config.eval_every
        return (progress.episode // every + 1) * every

    def judged(self, progress: Progress, passes: bool, steps: int, started_at: int) -> None:
        """Book an evaluation's verdict: the passes in a row, and after a failure the budget's
        wait (`steps` it drove, counted from the env step `started_at` it was taken at)."""
        progress.passed_in_a_row = progress.passed_in_a_row + 1 if passes else 0
        budget = self.config.eval_budget
        if budget is not None and not passes:  # wait for training to outweigh what it cost
            progress.evaluation_resume_step = started_at + math.ceil(steps / budget)

    def could_converge(self, progress: Progress) -> bool:
        """Whether a pass now would complete convergence (then training waits for it, so that
        convergence is declared where a blocking evaluation would declare it)."""
        return progress.converged_episode is None and (
            progress.passed_in_a_row + 1 >= self.config.converged_evals
        )

    def converged(self, progress: Progress) -> bool:
        """Whether the last `converged_evals` evaluations all passed."""
        return progress.passed_in_a_row >= self.config.converged_evals

    def gate_open(self) -> bool:
        """No collision in the last `eval_gate` training episodes."""
        gate = self.config.eval_gate
        recent = list(self._recent_collisions)[-gate:] if gate else []
        return len(recent) >= gate and not any(recent)

    @staticmethod
    def _learned_for(progress: Progress, episodes: int) -> bool:
        """Whether learning began at least `episodes` episodes ago (an evaluation before would
        judge the initial policy, or one a few hundred updates old)."""
        began = progress.learning_episode
        return began is not None and progress.episode - began >= episodes
