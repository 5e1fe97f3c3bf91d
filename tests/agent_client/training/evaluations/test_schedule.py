"""When a run evaluates: every `eval_every` episodes once learning has gone on that long, behind
the collision gate and, after a failure, the budget's wait."""

from __future__ import annotations

from agent_client.training.config import TrainConfig
from agent_client.training.evaluations.schedule import EvaluationSchedule
from agent_client.training.progress import Progress


def drive(
    schedule: EvaluationSchedule, progress: Progress, episodes: int, collided: bool = False
) -> list[int]:
    """`episodes` more training episodes of 100 steps, learning from the first; the episodes
    after which an evaluation was to start (each started at once)."""
    starts = []
    for _ in range(episodes):
        progress.episode += 1
        progress.global_step += 100
        if schedule.episode_ended(progress, collided, learning=True):
            schedule.started(progress)
            starts.append(progress.episode)
    return starts


def test_evaluations_come_every_eval_every_episodes_once_learning_has_gone_on_that_long() -> None:
    schedule = EvaluationSchedule(TrainConfig(eval_every=10, eval_gate=0))
    progress = Progress()
    assert drive(schedule, progress, 35) == [10, 20, 30]
    assert progress.learning_episode == 0
    late = Progress(episode=3)  # learning began during episode 4: the first comes 10 later
    assert drive(EvaluationSchedule(TrainConfig(eval_every=10, eval_gate=0)), late, 27) == [20, 30]


def test_an_evaluation_due_behind_a_closed_gate_is_skipped() -> None:
    schedule = EvaluationSchedule(TrainConfig(eval_every=10, eval_gate=3))
    progress = Progress()
    assert drive(schedule, progress, 9) == []
    assert drive(schedule, progress, 1, collided=True) == []  # due at 10, the gate closed
    assert drive(schedule, progress, 10) == [20]  # three clean ones since: the next is on time
    assert schedule.started(progress) == 30  # its verdict must be known where the next is due


def test_after_a_failure_the_budget_holds_the_next_evaluation_back_and_a_pass_does_not() -> None:
    schedule = EvaluationSchedule(TrainConfig(eval_every=10, eval_gate=1, eval_budget=0.5))
    progress = Progress()
    assert drive(schedule, progress, 10) == [10]
    schedule.judged(progress, passes=False, steps=1500, started_at=progress.global_step)
    assert progress.evaluation_resume_step == 1000 + 3000  # 1500 steps at a budget of 0.5
    assert drive(schedule, progress, 29) == []  # at 20 and 30 training had not had its 3000
    assert drive(schedule, progress, 1, collided=True) == []  # the wait is over, the gate not
    assert drive(schedule, progress, 1) == [41]  # a held-back one starts as soon as both allow
    schedule.judged(progress, passes=True, steps=1500, started_at=progress.global_step)
    assert progress.passed_in_a_row == 1
    assert drive(schedule, progress, 9) == [50]  # after a pass, no wait


def test_a_pass_that_would_complete_convergence_is_said_so() -> None:
    schedule = EvaluationSchedule(TrainConfig(converged_evals=2))
    progress = Progress()
    assert schedule.could_converge(progress) is False
    schedule.judged(progress, passes=True, steps=100, started_at=0)
    assert schedule.could_converge(progress) is True and not schedule.converged(progress)
    schedule.judged(progress, passes=True, steps=100, started_at=0)
    assert schedule.converged(progress)
    schedule.judged(progress, passes=False, steps=100, started_at=0)
    assert progress.passed_in_a_row == 0 and not schedule.converged(progress)
