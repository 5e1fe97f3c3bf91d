"""`Evaluations` on its own, inline on a live ``sim-server --backend fake``: the reference is
evaluated first and its figures kept, a policy evaluation starts where the schedule says and
books its verdict, the best policy is saved, and passes in a row converge the run."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from agent_client.drivers.idm import IDMDriver
from agent_client.envs.remote_env import RemoteEnv
from agent_client.training.config import TrainConfig, apply_overrides
from agent_client.training.evaluations import reference as reference_module
from agent_client.training.evaluations.reference import Reference
from agent_client.training.evaluations.runner import Evaluations, TrainingSide
from agent_client.training.progress import Profile, Progress
from agent_client.training.run_log import RunLog, read_rows
from tests.conftest import RunningServer

CONFIG = {"eval_every": 2, "eval_episodes": 2, "eval_gate": 0, "eval_budget": None,
          "converged_evals": 2, "stop_when_converged": True}  # fmt: skip


class Recorder:
    """The training side's hooks, recording what the evaluations asked of them."""

    def __init__(self) -> None:
        self.dropped = 0
        self.saved: list[str] = []

    def hooks(self, env: RemoteEnv) -> TrainingSide:
        def drop() -> None:
            self.dropped += 1

        def save(name: str, state: dict[str, Any]) -> None:
            self.saved.append(f"{name}:{state['label']}")

        def retry(work: Callable[[], Any]) -> Any:
            return work()

        return TrainingSide(
            envs=[env], resilient=retry, drop_episodes=drop,
            policy_state=lambda: {"label": "now"}, trained=lambda: True,
            driver=lambda state: IDMDriver(), save_policy=save, elapsed=lambda: 1.0,
            one_lane=True,
        )  # fmt: skip


@pytest.fixture
def env(fake_server: RunningServer) -> Iterator[RemoteEnv]:
    env = RemoteEnv(fake_server.address, "cf", reward="safe", timeout_s=5.0)
    try:
        yield env
    finally:
        env.close()


def evaluations(env: RemoteEnv, out: Path, recorder: Recorder, **changes: object) -> Evaluations:
    config = apply_overrides(TrainConfig(), {**CONFIG, **changes})
    seeds = [config.eval_seed + i for i in range(config.eval_episodes)]
    figures = Reference(seeds, env.scenario_for)
    return Evaluations(
        config, out, IDMDriver(), figures, None, recorder.hooks(env), Profile(), lambda _: None
    )


def end_episodes(runs: Evaluations, progress: Progress, count: int) -> None:
    for _ in range(count):
        progress.episode += 1
        progress.global_step += 100
        runs.episode_ended(collided=False, learning=True, interrupted=False)


def test_the_reference_is_evaluated_first_and_its_figures_kept(
    env: RemoteEnv, tmp_path: Path
) -> None:
    recorder = Recorder()
    runs = evaluations(env, tmp_path, recorder)
    log = RunLog(tmp_path)
    try:
        runs.begin(Progress(), log)
    finally:
        log.close()
    assert runs.figures.known and (tmp_path / "idm_eval.json").exists()
    assert recorder.dropped == 1  # the training episodes under way did not see it


def test_policy_evaluations_start_on_schedule_book_their_verdicts_and_converge(
    env: RemoteEnv, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(
        reference_module, "judge", lambda scenarios, whole, gain: ({"all": True}, "")
    )
    recorder, progress = Recorder(), Progress()
    runs = evaluations(env, tmp_path, recorder)
    log = RunLog(tmp_path)
    try:
        runs.begin(progress, log)
        end_episodes(runs, progress, 1)  # learning began in episode 1: one is due at 2
        assert len(progress.evaluations) == 0
        end_episodes(runs, progress, 1)
        assert [e["episode"] for e in progress.evaluations] == [2]
        assert progress.passed_in_a_row == 1 and not runs.converged
        end_episodes(runs, progress, 2)
    finally:
        log.close()
    assert [e["episode"] for e in progress.evaluations] == [2, 4]
    assert runs.converged and progress.converged_episode == 4
    assert recorder.saved == ["policy.pt:now", "policy.pt:now"]  # each as good as the best
    assert recorder.dropped == 3  # after the reference's and after each inline evaluation
    rows = read_rows(tmp_path / "evaluations.csv")
    assert [int(r["passed_in_a_row"]) for r in rows] == [1, 2]


def test_an_interrupted_run_starts_no_evaluation(env: RemoteEnv, tmp_path: Path) -> None:
    recorder, progress = Recorder(), Progress()
    runs = evaluations(env, tmp_path, recorder)
    log = RunLog(tmp_path)
    try:
        runs.begin(progress, log)
        for _ in range(4):
            progress.episode += 1
            runs.episode_ended(collided=False, learning=True, interrupted=True)
    finally:
        log.close()
    assert progress.evaluations == []


def test_a_resumed_runs_evaluation_is_kept_until_it_has_run_again(
    env: RemoteEnv, tmp_path: Path
) -> None:
    recorder, progress = Recorder(), Progress()
    runs = evaluations(env, tmp_path, recorder)
    running = {"policy_state": {"label": "saved"},
               "context": {"episode": 7, "global_step": 700, "collect_at": 8}}  # fmt: skip
    runs.resume(running)
    assert runs.running() == running  # a checkpoint before it runs keeps it
    log = RunLog(tmp_path)
    try:
        runs.begin(progress, log)
    finally:
        log.close()
    assert [(e["episode"], e["global_step"]) for e in progress.evaluations] == [(7, 700)]
    assert runs.running() is None
    assert recorder.saved == ["policy.pt:saved"]  # the first verdict is the best so far


def test_a_trained_policy_is_kept_over_the_reference_it_started_as(
    env: RemoteEnv, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Before its actor learns, a residual policy drives as its reference and may meet every
    # target; `policy.pt` must still be what was learned once something was, even if worse.
    verdicts = iter([True, False])
    monkeypatch.setattr(
        reference_module, "judge", lambda scenarios, whole, gain: ({"all": next(verdicts)}, "")
    )
    recorder, progress, learned = Recorder(), Progress(), [False]
    runs = evaluations(env, tmp_path, recorder)
    hooks = recorder.hooks(env)
    runs.training = dataclasses.replace(
        hooks,
        trained=lambda: learned[0],
        policy_state=lambda: {"label": "trained" if learned[0] else "clone"},
    )
    log = RunLog(tmp_path)
    try:
        runs.begin(progress, log)
        end_episodes(runs, progress, 2)
        learned[0] = True
        end_episodes(runs, progress, 2)
    finally:
        log.close()
    assert [e["trained"] for e in progress.evaluations] == [False, True]
    assert recorder.saved == ["policy.pt:clone", "policy.pt:trained"]
