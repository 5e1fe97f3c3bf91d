"""When the trainer evaluates: after a failed evaluation `eval_budget` makes the next wait until
training has outweighed it (later, never fewer episodes each), and every evaluation row says
how many of its episodes ran and why it stopped, and a background evaluation that failed runs
again; against a live ``sim-server --backend fake``."""

from __future__ import annotations

from itertools import pairwise
from pathlib import Path
from typing import Any

import pytest

from agent_client.errors import UsageError
from agent_client.training.config import TrainConfig, apply_overrides
from agent_client.training.evaluations import reference as reference_module
from agent_client.training.evaluations.pool import EvaluationPool
from agent_client.training.run_log import read_rows
from agent_client.training.trainer import Trainer
from tests.agent_client.training import short_runs
from tests.conftest import RunningServer, sim_server

FAST = {
    "episodes": 16,
    "eval_every": 1,
    "eval_episodes": 2,
    "eval_gate": 0,
    "checkpoint_every": 50,
    "scenario_options": {"max_episode_time": 3.0},
    "learner": {"learning_starts": 32, "batch_size": 32, "compile": False},
}


def train(address: str, out: Path, **changes: object) -> Trainer:
    return short_runs.train(address, out, FAST, **changes)


def test_the_budget_postpones_the_evaluation_after_a_failed_one(
    fake_server: RunningServer, tmp_path: Path
) -> None:
    free = train(fake_server.address, tmp_path / "free", eval_budget=None)
    held = train(fake_server.address, tmp_path / "held", eval_budget=0.2)
    assert len(held.progress.evaluations) < len(free.progress.evaluations)
    assert len(held.progress.evaluations) >= 1  # the first always runs
    for trainer in (free, held):
        rows = read_rows(trainer.out / "evaluations.csv")
        assert sum(int(r["steps"]) for r in rows) == trainer.progress.evaluation_steps
        assert all(int(r["episodes"]) + int(r["episodes_saved"]) == 2 for r in rows)
    # After a failed evaluation training drove its steps / budget before the next one began
    # (inline, no training step passes during an evaluation).
    rows = read_rows(held.out / "evaluations.csv")
    for before, after in pairwise(rows):
        if int(before["passed_in_a_row"]) == 0:
            waited = int(after["global_step"]) - int(before["global_step"])
            assert waited >= int(before["steps"]) / 0.2


def test_a_stopped_evaluation_is_recorded_as_a_failure_of_its_target(
    fake_server: RunningServer, tmp_path: Path
) -> None:
    # six episodes each: enough for the screen to be certain before the last (two are not)
    trainer = train(fake_server.address, tmp_path / "run", eval_budget=None, eval_episodes=6)
    rows = read_rows(tmp_path / "run" / "evaluations.csv")
    assert any(row["stopped"] for row in rows)  # the path under test was taken
    for row in rows:
        if row["stopped"]:
            assert row[f"target_{row['stopped']}"] == "False"
            assert int(row["passed_in_a_row"]) == 0
        else:
            assert int(row["episodes_saved"]) == 0
    assert trainer.progress.evaluation_steps > 0


def test_the_first_evaluation_comes_eval_every_episodes_after_learning_began(
    fake_server: RunningServer, tmp_path: Path
) -> None:
    trainer = train(fake_server.address, tmp_path / "run", eval_budget=None, eval_every=4)
    began = trainer.progress.learning_episode
    assert began is not None and began >= 1  # learning_starts lies beyond the first episode
    rows = read_rows(tmp_path / "run" / "evaluations.csv")
    assert rows, "the run evaluated nothing"
    first = int(rows[0]["episode"])
    assert first - began >= 4 and first % 4 == 0
    assert (first - 4) - began < 4  # the one due four episodes earlier came too soon: skipped


@pytest.mark.parametrize("budget", [0.0, -0.5])
def test_a_budget_must_be_positive(budget: float) -> None:
    with pytest.raises(UsageError, match="eval_budget must be > 0"):
        apply_overrides(TrainConfig(), {"eval_budget": budget})


def test_a_background_evaluation_whose_worker_died_runs_again_when_its_verdict_is_due(
    fake_server: RunningServer, tmp_path: Path
) -> None:
    config = apply_overrides(TrainConfig(), {**FAST, "eval_every": 2, "episodes": 12})
    runs: dict[str, Trainer] = {}
    killed: list[int] = []
    with sim_server("--backend", "fake", "--idle-priority") as evaluate:
        for name in ("undisturbed", "disturbed"):
            trainer = Trainer(config, fake_server.address, tmp_path / name, timeout_s=5.0,
                              retry_for_s=5.0, eval_servers=[evaluate.address])  # fmt: skip
            pool = trainer.eval_pool
            assert pool is not None
            said: list[str] = []
            trainer.say = said.append  # type: ignore[method-assign]
            if name == "disturbed":
                poll = pool.poll

                def kill_once(pool: EvaluationPool = pool, poll: Any = poll) -> bool:
                    """The first policy evaluation's worker dies under it (SIGKILL)."""
                    job = pool.job
                    # While a seed is still to come: the death cannot go unseen.
                    if job is not None and job.name == "policy" and pool._queue and not killed:
                        killed.append(int(job.context["episode"]))
                        pool.workers[0].process.kill()
                        pool.workers[0].process.wait(5.0)
                    return bool(poll())

                pool.poll = kill_once  # type: ignore[method-assign]
            try:
                trainer.run()
            finally:
                trainer.close()
            runs[name] = trainer
            if name == "disturbed":
                assert any("the background evaluation failed" in text for text in said), said
    assert killed, "no policy evaluation ran in the background"
    assert runs["disturbed"].progress.reconnects >= 1  # its worker was replaced
    timing = {"wall_time", "seconds", "evaluation_share"}
    undisturbed, disturbed = (
        [{k: v for k, v in e.items() if k not in timing} for e in runs[name].progress.evaluations]
        for name in ("undisturbed", "disturbed")
    )
    # The evaluation given up ran again, from its start, on the policy it was started with,
    # and training went on undisturbed: the same episodes, the same verdicts.
    assert disturbed == undisturbed
    assert int(disturbed[0]["episode"]) == killed[0]
    assert (
        read_rows(tmp_path / "disturbed" / "episodes.csv")[-1]["global_step"]
        == (read_rows(tmp_path / "undisturbed" / "episodes.csv")[-1]["global_step"])
    )


def test_a_resumed_run_starts_again_the_evaluation_that_was_running_when_it_stopped(
    fake_server: RunningServer, tmp_path: Path
) -> None:
    config = apply_overrides(TrainConfig(), {**FAST, "eval_every": 2, "episodes": 30})
    with sim_server("--backend", "fake", "--idle-priority") as evaluate:
        trainer = Trainer(config, fake_server.address, tmp_path, timeout_s=5.0,
                          eval_servers=[evaluate.address])  # fmt: skip
        started: list[dict[str, Any]] = []
        start = trainer.evaluations.start_background

        def stop_after_the_first(job: Any, start: Any = start) -> None:
            """Ctrl-C right after the first policy evaluation went to the background."""
            start(job)
            if job.name == "policy" and not started:
                started.append(dict(job.context))
                trainer.request_stop()
                trainer._interrupted = True  # as the signal handler does

        trainer.evaluations.start_background = stop_after_the_first  # type: ignore[method-assign]
        try:
            trainer.run()
        finally:
            trainer.close()
        assert started and not trainer.progress.evaluations  # given up, not waited for
        again = Trainer(config, fake_server.address, tmp_path, timeout_s=5.0,
                        eval_servers=[evaluate.address])  # fmt: skip
        try:
            progress = again.run(resume=True)
        finally:
            again.close()
    first = progress.evaluations[0]
    assert (first["episode"], first["global_step"]) == (
        started[0]["episode"], started[0]["global_step"]
    )  # fmt: skip


def test_a_residual_policys_passes_in_its_burn_in_do_not_count(
    fake_server: RunningServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Before its actor learns, a residual policy drives as its reference: a pass then says
    nothing of what was learned, and does not count towards convergence (every target is met
    here, whatever the figures)."""
    met = {"no_collisions": True, "as_fast_as_idm": True}
    monkeypatch.setattr(reference_module, "judge", lambda scenarios, whole, gain: (dict(met), ""))
    waiting = train(fake_server.address, tmp_path / "burn", eval_budget=None,
                    residual="idm+mobil", residual_burn_in=10**6)  # fmt: skip
    rows = read_rows(tmp_path / "burn" / "evaluations.csv")
    assert len(rows) >= 3 and all(r["trained"] == "False" for r in rows)
    assert all(int(r["passed_in_a_row"]) == 0 for r in rows)
    assert waiting.progress.converged_episode is None
    learned = train(fake_server.address, tmp_path / "learned", eval_budget=None,
                    residual="idm+mobil", residual_burn_in=0)  # fmt: skip
    rows = read_rows(tmp_path / "learned" / "evaluations.csv")
    assert rows and all(r["trained"] == "True" for r in rows)
    assert learned.progress.converged_episode is not None
