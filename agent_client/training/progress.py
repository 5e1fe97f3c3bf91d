"""What a training run reports and keeps: counters, where the time went, progress lines."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

PHASES = ("act_and_send", "evaluation", "update", "wait_and_receive", "bookkeeping")
"""The parts of a training iteration `Profile` times, in the order they run."""


class Reporter(Protocol):
    """Where a run reports progress; the CLI draws a progress bar, tests stay quiet."""

    def message(self, text: str) -> None:
        """A line for the user."""

    def episode(self, row: dict[str, Any]) -> None:
        """Metrics of a finished training episode."""


class QuietReporter:
    """Reports nothing."""

    def message(self, text: str) -> None:
        pass

    def episode(self, row: dict[str, Any]) -> None:
        pass


@dataclass
class Progress:
    """Counters that a checkpoint restores."""

    episode: int = 0
    global_step: int = 0
    updates: int = 0
    wall_time: float = 0.0
    passed_in_a_row: int = 0
    converged_episode: int | None = None
    converged_time: float | None = None
    converged_step: int | None = None
    best_score: float = -float("inf")
    evaluations: list[dict[str, Any]] = field(default_factory=list)
    reconnects: int = 0
    failed_episodes: int = 0
    evaluation_steps: int = 0
    """Env steps the policy's evaluations drove."""
    evaluation_resume_step: int = 0
    """After a failed evaluation, no other before this training step (`TrainConfig.eval_budget`)."""
    learning_episode: int | None = None
    """Episodes finished when learning began (None before): the first policy evaluation comes
    `TrainConfig.eval_every` episodes later, not while the policy is still the initial one."""


@dataclass
class Profile:
    """Wall time per phase of the training iterations (s), and how many there were."""

    seconds: dict[str, float] = field(default_factory=lambda: dict.fromkeys(PHASES, 0.0))
    iterations: int = 0
    blocking_evaluation: float = 0.0
    """Seconds training waited for evaluations (run while it waited, or a background one's
    end); the ``evaluation`` phase is the background's polls between iterations."""
    baseline_evaluation: float = 0.0
    """Of `blocking_evaluation`, the seconds of the IDM baseline's evaluation."""

    def reset(self) -> None:
        """Count afresh from now (a benchmark's measured iterations only), in place: whoever
        holds this profile (the trainer, its evaluations) goes on counting into it."""
        self.seconds = dict.fromkeys(PHASES, 0.0)
        self.iterations = 0
        self.blocking_evaluation = self.baseline_evaluation = 0.0

    @property
    def total(self) -> float:
        return sum(self.seconds.values()) + self.blocking_evaluation

    @property
    def evaluation_seconds(self) -> float:
        """Seconds evaluations took from the loop: the background's polls plus the waits."""
        return self.seconds["evaluation"] + self.blocking_evaluation

    def evaluation_share(self) -> float:
        """The share of the loop's time that evaluations took (polls and waits)."""
        total = self.total
        return self.evaluation_seconds / total if total else 0.0

    def to_dict(self) -> dict[str, Any]:
        total = self.total
        per_iteration = (
            {name: 1e6 * seconds / self.iterations for name, seconds in self.seconds.items()}
            if self.iterations
            else {}
        )
        return {
            "iterations": self.iterations,
            "seconds": {
                **self.seconds,
                "blocking_evaluation": self.blocking_evaluation,
                "baseline_evaluation": self.baseline_evaluation,
            },
            "share": {name: seconds / total for name, seconds in self.seconds.items()}
            if total
            else {},
            "us_per_iteration": per_iteration,
            "evaluation_share": self.evaluation_share(),
        }

    def line(self) -> str:
        """One line for the user: where a training iteration's time went."""
        if not self.iterations:
            return "no training iterations"
        parts = ", ".join(
            f"{name.replace('_', ' ')} {1e6 * seconds / self.iterations:.0f}"
            for name, seconds in self.seconds.items()
        )
        return (
            f"time per iteration (us): {parts}; evaluations "
            f"{100 * self.evaluation_share():.1f} % of the loop"
        )


def evaluation_line(evaluation: dict[str, Any]) -> str:
    passed = [
        k.removeprefix("target_") for k, v in evaluation.items() if k.startswith("target_") and v
    ]
    arrived = float(evaluation.get("arrival_share", 1.0))
    failed = evaluation.get("failed_scenarios")
    return (
        f"  eval @ {evaluation['episode']}: speed {evaluation['average_speed']:.2f} m/s "
        f"({evaluation['speed_ratio_to_idm']:.3f}x reference, "
        f"{evaluation['speed_ratio_to_ceiling']:.3f}x ceiling), "
        f"collisions/ep {evaluation['collisions_per_episode']:.2f}, "
        f"jerk>5.6 {100 * evaluation['jerk_share_above_limit']:.2f}%, "
        f"headway<1s {100 * evaluation['headway_share_below_1s']:.2f}% | "
        + (f"arrived {100 * arrived:.0f}% | " if evaluation.get("route_lanes") else "")
        + f"passed: {', '.join(passed) or 'none'} | in a row: {evaluation['passed_in_a_row']}"
        + ("" if evaluation.get("trained", True) else " (the actor's burn-in: not counted)")
        + (f" | failed: {failed}" if failed else "")
        + (
            f" | stopped after {evaluation['episodes']} episodes: {evaluation['stopped']} failed"
            if evaluation.get("stopped")
            else ""
        )
    )
