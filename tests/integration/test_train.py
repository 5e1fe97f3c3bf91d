"""The learner through a real SUMO server: it learns, it checkpoints, it resumes, its policy drives."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agent_client.drivers.policy import PolicyDriver, load_policy_driver
from agent_client.training.config import TrainConfig, apply_overrides
from agent_client.training.run_log import read_rows
from agent_client.training.trainer import Trainer
from tests.conftest import RunningServer, sim_server

pytestmark = [pytest.mark.sumo, pytest.mark.slow]

# One-second decisions keep these runs short: ~130 decisions per episode. IDM's warm-up drives
# whole episodes (random actions stop within ~10 s), so that learning starts within a few of them.
FAST = {
    "decision_interval": 1.0,
    "warmup_policy": "idm",
    "eval_every": 0,
    "checkpoint_every": 1,
    "learner": {
        "learning_starts": 300,
        "batch_size": 64,
        "updates_per_step": 2.0,
        "compile": False,  # the compiled update is tested on its own; here it would only add time
    },
}


def fast_config(**changes: object) -> TrainConfig:
    return apply_overrides(apply_overrides(TrainConfig(), FAST), dict(changes))


def greedy_return(trainer: Trainer, seeds: range) -> float:
    """Mean return of the current greedy policy on `seeds` (reward of the run)."""
    from agent_client.drivers.episode import run_episode
    from agent_client.evaluation.metrics import episode_summary

    driver = PolicyDriver(trainer.agent.policy(), trainer.features, trainer.scale, trainer.lanes)
    return float(
        np.mean([episode_summary(run_episode(trainer.env, driver, s)).total_reward for s in seeds])
    )


def test_a_short_run_improves_on_its_untrained_start(
    sumo_server: RunningServer, tmp_path: Path
) -> None:
    # 60 episodes: TD3 first goes through a crash phase (its warm-up data are IDM's, so the
    # critic has not seen where full throttle leads) and leaves it around episode 40-50.
    trainer = Trainer(fast_config(episodes=60, seed=1), sumo_server.address, tmp_path / "run")
    try:
        before = greedy_return(trainer, range(500, 505))
        trainer.run()
        after = greedy_return(trainer, range(500, 505))
    finally:
        trainer.close()
    assert after > before + 5.0, (before, after)
    rows = read_rows(tmp_path / "run" / "episodes.csv")
    assert [int(r["episode"]) for r in rows] == list(range(1, 61))
    gamma = trainer.config.learner.gamma
    assert all(float(r["q_upper_bound"]) == pytest.approx(1.0 / (1.0 - gamma)) for r in rows)


def train_command(server: str, out: Path, *extra: str) -> list[str]:
    return [
        sys.executable, "-m", "agent_client.cli.main", "train", "--server", server, "--out", str(out),
        "--quiet", "--decision-interval", "1.0", "--set", "eval_every=0", "--set", "warmup_policy=idm",
        "--set", "checkpoint_every=1", "--set", "learner.learning_starts=200",
        "--set", "learner.batch_size=64", "--set", "learner.compile=false", *extra,
    ]  # fmt: skip


def wait_for_episodes(path: Path, count: int, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if path.exists() and len(read_rows(path)) >= count:
            return
        time.sleep(0.2)
    raise TimeoutError(f"{path} did not reach {count} episodes within {timeout_s} s")


def test_sigterm_checkpoints_and_resume_continues(
    sumo_server: RunningServer, tmp_path: Path
) -> None:
    out = tmp_path / "run"
    process = subprocess.Popen(
        train_command(sumo_server.address, out, "--episodes", "20"),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        wait_for_episodes(out / "episodes.csv", 3, timeout_s=240)
        process.send_signal(signal.SIGTERM)
        _, stderr = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert process.returncode == 0, stderr
    interrupted = read_rows(out / "episodes.csv")
    assert 3 <= len(interrupted) < 20
    resumed = subprocess.run(
        train_command(sumo_server.address, out, "--resume", str(out)),
        capture_output=True, text=True, timeout=600, check=False,
    )  # fmt: skip
    assert resumed.returncode == 0, resumed.stderr
    rows = read_rows(out / "episodes.csv")
    assert [int(r["episode"]) for r in rows] == list(range(1, 21))
    steps = [int(r["global_step"]) for r in rows]
    assert steps == sorted(steps) and len(set(steps)) == len(steps)
    # Nothing lost: the resumed part continues the counters of the interrupted part.
    assert int(rows[len(interrupted)]["global_step"]) > int(interrupted[-1]["global_step"])


def test_sigkill_loses_at_most_the_episodes_since_the_last_checkpoint(
    scenario_cache: Path, tmp_path: Path
) -> None:
    out = tmp_path / "run"
    # Its own server: the killed client never says goodbye, so the session stays taken until
    # the server's session timeout.
    with sim_server(
        "--backend", "sumo", "--session-timeout", "2", cache_dir=scenario_cache
    ) as server:
        process = subprocess.Popen(
            train_command(server.address, out, "--episodes", "50"),
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        try:
            wait_for_episodes(out / "episodes.csv", 3, timeout_s=240)
            process.kill()
            process.wait(timeout=30)
        finally:
            if process.poll() is None:
                process.kill()
    from agent_client.rl.checkpoint import load_checkpoint

    state = load_checkpoint(out / "checkpoint.pt")
    logged = len(read_rows(out / "episodes.csv"))
    assert logged - 1 <= state["progress"]["episode"] <= logged


def test_the_saved_policy_reloads_and_drives(sumo_server: RunningServer, tmp_path: Path) -> None:
    out = tmp_path / "run"
    trained = subprocess.run(
        train_command(sumo_server.address, out, "--episodes", "2"),
        capture_output=True, text=True, timeout=600, check=False,
    )  # fmt: skip
    assert trained.returncode == 0, trained.stderr
    assert (out / "training.png").stat().st_size > 10_000
    assert json.loads((out / "config.json").read_text())["decision_interval"] == 1.0
    driven = subprocess.run(
        [sys.executable, "-m", "agent_client.cli.main", "drive", "--server", sumo_server.address,
         "--policy", str(out / "policy.pt"), "--episodes", "1", "--json"],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert driven.returncode == 0, driven.stderr
    episode = json.loads(driven.stdout.splitlines()[0])
    assert episode["steps"] > 0
    # It drives with the decision interval it was trained with (the run's config.json).
    assert episode["duration"] / episode["steps"] == pytest.approx(1.0, rel=0.05)


def test_reward_params_shape_the_reward_of_the_same_drive(
    sumo_server: RunningServer, tmp_path: Path
) -> None:
    totals = []
    for knee in (1.2, 3.0):  # IDM follows at ~1.5 s: below a 3 s knee its steps earn less
        config = fast_config(episodes=1, reward_params={"desired_headway": knee})
        trainer = Trainer(config, sumo_server.address, tmp_path / str(knee))
        try:
            assert trainer.env.reward_fn.desired_headway == knee  # type: ignore[attr-defined]
            trainer.run()  # one warm-up episode: IDM with the seed's noise, the same drive
        finally:
            trainer.close()
        totals.append(float(read_rows(tmp_path / str(knee) / "episodes.csv")[0]["total_reward"]))
        saved = json.loads((tmp_path / str(knee) / "config.json").read_text())
        assert saved["reward_params"] == {"desired_headway": knee}
    assert totals[1] < 0.95 * totals[0]


def test_lane_changing_training_runs_on_cflc(sumo_server: RunningServer, tmp_path: Path) -> None:
    trainer = Trainer(
        fast_config(scenario="cflc", episodes=2, reward="rlc"), sumo_server.address, tmp_path
    )
    try:
        assert trainer.agent.n_lane_actions == 3
        assert trainer.features.name == "lc"  # several lanes, no lane end: as measured
        trainer.run()
    finally:
        trainer.close()
    rows = read_rows(tmp_path / "episodes.csv")
    assert len(rows) == 2
    assert sum(int(r["lane_changes_started"]) + int(r["lane_changes_refused"]) for r in rows) > 0


def test_a_run_on_merge_learns_a_residual_policy_that_merges(
    sumo_server: RunningServer, tmp_path: Path
) -> None:
    """On the on-ramp the policy corrects IDM + MOBIL's acceleration (residual = auto) and
    changes lanes as it does; after its actor has learned, it still merges on held-out seeds,
    without a collision, and drives differently from its untrained start."""
    # 0.1 s decisions: at 1 s IDM + MOBIL itself misses gaps (2 of 12 seeds end at the lane end)
    config = fast_config(
        scenario="merge", episodes=4, decision_interval=0.1, residual_burn_in=100,
        learner={"learning_starts": 1000, "updates_per_step": 0.5},
    )  # fmt: skip
    trainer = Trainer(config, sumo_server.address, tmp_path / "run")
    try:
        assert trainer.scale.residual == "idm+mobil" and trainer.lanes.reference is not None
        before = [p.clone() for p in trainer.agent.actor]
        trainer.run()
        moved = sum(
            float((p - q).abs().sum()) for p, q in zip(trainer.agent.actor, before, strict=True)
        )
        driver = PolicyDriver(
            trainer.agent.policy(), trainer.features, trainer.scale, trainer.lanes
        )
        from agent_client.drivers.episode import run_episode
        from agent_client.evaluation.metrics import episode_summary

        summaries = [episode_summary(run_episode(trainer.env, driver, s)) for s in (901, 902)]
    finally:
        trainer.close()
    assert trainer.progress.updates > config.residual_burn_in
    assert moved > 0.1  # the actor learned after its burn-in
    assert [s.reason for s in summaries] == ["end_of_road"] * 2, summaries
    assert all(s.collisions == 0 for s in summaries)


def test_the_wave_reward_trains_on_the_ring_and_its_evaluations_rank_policies(
    sumo_server: RunningServer, tmp_path: Path
) -> None:
    """``report_traffic`` is asked for by the trainer itself (the reward reads every vehicle's
    speed), and an evaluation without a ceiling (the ring reports none) still scores."""
    config = fast_config(
        scenario="ring", reward="wave", episodes=2, eval_every=1, eval_episodes=1, eval_gate=0,
        eval_budget=None,
        scenario_options={"warmup": 10.0, "max_episode_time": 20.0},
        learner={"learning_starts": 10},
    )  # fmt: skip
    trainer = Trainer(config, sumo_server.address, tmp_path)
    try:
        assert trainer.env.options["report_traffic"] is True
        trainer.run()
    finally:
        trainer.close()
    rows = read_rows(tmp_path / "episodes.csv")
    assert len(rows) == 2 and all(float(r["total_reward"]) != 0.0 for r in rows)
    assert len(trainer.progress.evaluations) == 2
    assert np.isfinite(trainer.progress.best_score)  # the ring's NaN ceiling ratio counts 0
    assert (tmp_path / "policy.pt").exists()


def record_messages(trainer: Trainer) -> list[tuple[int, str]]:
    """The trainer's messages from now on, each with the episode count when it was said."""
    said: list[tuple[int, str]] = []

    def say(text: str) -> None:
        said.append((trainer.progress.episode, text))

    trainer.say = say  # type: ignore[method-assign]
    return said


def run_rows(folder: Path) -> list[dict[str, str]]:
    """episodes.csv without the wall-clock column."""
    return [{k: v for k, v in row.items() if k != "wall_time"} for row in read_rows(folder)]


def test_the_same_seed_and_configuration_give_the_same_run(
    sumo_server: RunningServer, tmp_path: Path
) -> None:
    # The compiled update, inline evaluations and a checkpoint in between: all of it repeats.
    config = fast_config(
        episodes=6, seed=3, eval_every=3, eval_episodes=2,
        learner={"learning_starts": 150, "batch_size": 32, "compile": True,
                 "hidden_sizes": [16, 16]},
    )  # fmt: skip
    policies = []
    for name in ("first", "second"):
        trainer = Trainer(config, sumo_server.address, tmp_path / name)
        try:
            trainer.run()
        finally:
            trainer.close()
        policies.append(trainer.agent.policy_state_dict())
    first, second = (
        run_rows(tmp_path / "first" / "episodes.csv"),
        run_rows(tmp_path / "second" / "episodes.csv"),
    )
    assert first == second
    assert len(first) == 6 and float(first[-1]["critic_loss"]) > 0  # it did learn
    evaluations = [read_rows(tmp_path / name / "evaluations.csv") for name in ("first", "second")]
    assert [r["average_speed"] for r in evaluations[0]] == [
        r["average_speed"] for r in evaluations[1]
    ]
    for mine, theirs in zip(policies[0]["actor"], policies[1]["actor"], strict=True):
        assert mine.equal(theirs)


def test_background_evaluations_give_the_run_that_blocking_ones_give(
    scenario_cache: Path, tmp_path: Path
) -> None:
    # Evaluations on an idle-priority server of their own: in the background (the default) a
    # verdict is read when the next evaluation is due, blocking (eval_while_training off) at
    # once. The episodes, the verdicts, when they ran and the policy are the same.
    config = fast_config(episodes=30, seed=5, eval_every=2, eval_episodes=2, eval_gate=0,
                         eval_budget=2.0)  # fmt: skip
    runs: dict[str, dict[str, Any]] = {}
    with (
        sim_server("--backend", "sumo", "--idle-priority", cache_dir=scenario_cache) as evaluate,
        sim_server("--backend", "sumo", cache_dir=scenario_cache) as train,
    ):
        assert os.sched_getscheduler(evaluate.process.pid) == os.SCHED_IDLE
        for name, background in (("background", True), ("blocking", False)):
            changed = apply_overrides(config, {"eval_while_training": background})
            trainer = Trainer(changed, train.address, tmp_path / name,
                              eval_servers=[evaluate.address])  # fmt: skip
            said = record_messages(trainer)
            try:
                progress = trainer.run()
                assert trainer.eval_pool is not None
                classes = {os.sched_getscheduler(w.process.pid) for w in trainer.eval_pool.workers}
            finally:
                trainer.close()
            runs[name] = {"progress": progress, "said": said, "classes": classes,
                          "policy": trainer.agent.policy_state_dict(), "profile": trainer.profile}  # fmt: skip
    background, blocking = runs["background"], runs["blocking"]
    assert background["classes"] == {os.SCHED_IDLE}
    assert os.SCHED_IDLE not in blocking["classes"]
    assert run_rows(tmp_path / "background" / "episodes.csv") == run_rows(
        tmp_path / "blocking" / "episodes.csv"
    )
    timing = {"wall_time", "seconds", "evaluation_share"}
    evaluations = [
        [{k: v for k, v in e.items() if k not in timing} for e in run["progress"].evaluations]
        for run in (background, blocking)
    ]
    assert len(evaluations[0]) >= 3 and evaluations[0] == evaluations[1]
    # One the gate or the budget held back (it started between two multiples of eval_every):
    # its verdict is due at the next multiple, sooner than eval_every episodes on.
    assert any(int(e["episode"]) % 2 for e in evaluations[1]), "no evaluation was held back"
    for mine, theirs in zip(
        background["policy"]["actor"], blocking["policy"]["actor"], strict=True
    ):
        assert mine.equal(theirs)

    def booked(run: dict[str, Any]) -> list[tuple[int, int]]:
        """(episode it started at, episode when its verdict was read) per evaluation."""
        return [(int(text.split()[2].rstrip(":")), at) for at, text in run["said"]
                if text.startswith("  eval @")]  # fmt: skip

    assert all(start == at for start, at in booked(blocking))
    assert any(at > start for start, at in booked(background)), "nothing ran in the background"
    assert background["profile"].seconds["evaluation"] > 0  # the polls between iterations
    counters = [
        {k: v for k, v in dataclasses.asdict(run["progress"]).items()
         if k not in {"wall_time", "converged_time", "evaluations"}}
        for run in (background, blocking)
    ]  # fmt: skip
    assert counters[0] == counters[1]  # budget, passes in a row, best score, steps, updates
    saved = [load_policy_driver(tmp_path / name / "policy.pt").policy for name in runs]
    x = np.linspace(-1.0, 1.0, saved[0].obs_dim * 4).reshape(4, -1)
    kept = [policy.act_batch(x)[0] for policy in saved]
    assert np.array_equal(kept[0], kept[1])  # the same best policy kept


def test_with_eval_while_training_off_evaluations_block_on_their_own_server(
    scenario_cache: Path, tmp_path: Path
) -> None:
    with (
        sim_server("--backend", "sumo", cache_dir=scenario_cache) as first,
        sim_server("--backend", "sumo", cache_dir=scenario_cache) as second,
        sim_server("--backend", "sumo", cache_dir=scenario_cache) as evaluate,
    ):
        # lock-step: the trainer's own connections reset the training episodes, and are watched
        config = fast_config(episodes=8, eval_every=2, eval_episodes=2, eval_gate=0,
                             eval_budget=None, eval_while_training=False,
                             sampling="local")  # fmt: skip
        trainer = Trainer(
            config, [first.address, second.address], tmp_path, eval_servers=[evaluate.address]
        )
        seeds: dict[str, list[int]] = {"train0": [], "train1": []}
        envs = [("train0", trainer.vec.envs[0]), ("train1", trainer.vec.envs[1])]
        for name, env in envs:
            send_reset = env.send_reset

            def recording(*args: Any, _into: list[int] = seeds[name], _send: Any = send_reset,
                          **kwargs: Any) -> None:  # fmt: skip
                _into.append(kwargs["seed"])
                _send(*args, **kwargs)

            env.send_reset = recording  # type: ignore[method-assign]
        try:
            progress = trainer.run()
        finally:
            trainer.close()
    assert trainer.eval_pool is not None and not trainer.eval_pool.idle_priority
    assert len(progress.evaluations) >= 3
    # The blocking time is the IDM baseline's and the evaluations' own, each counted once.
    profile = trainer.profile
    assert 0 < profile.baseline_evaluation < profile.blocking_evaluation
    assert profile.blocking_evaluation == pytest.approx(
        profile.baseline_evaluation + sum(e["seconds"] for e in progress.evaluations), abs=0.05
    )
    held_out = set(range(config.eval_seed, config.eval_seed + config.eval_episodes))
    # Every evaluation, the IDM baseline's too, ran on the evaluation server alone.
    trained = {name: [s for s in seeds[name] if s not in held_out] for name in seeds}
    assert seeds["train0"] and seeds["train1"]
    assert trained["train0"] == seeds["train0"] and trained["train1"] == seeds["train1"]
    # No training episode was cut short to make room for an evaluation: on each training
    # server every episode but the one under way at the end ran to its end (inline on the
    # training servers, each evaluation would give up the one running on the other server).
    ended = {int(row["seed"]) for row in read_rows(tmp_path / "episodes.csv")}
    assert len(ended) == 8
    for name in ("train0", "train1"):
        assert set(trained[name][:-1]) <= ended, name


def test_a_lane_change_is_asked_for_only_when_it_can_happen(
    sumo_server: RunningServer, tmp_path: Path
) -> None:
    """Untrained, with lane exploration at every lane decision: no request into a lane that does
    not exist, none while a change is under way, none between two lane decisions. (The gap rule
    is off: on this seed the ego spends the episode beside a car, where it masks every change;
    tests/agent_client/rl/test_lanes.py tests it.)"""
    from agent_client.drivers.episode import run_episode
    from agent_client.rl.td3 import TD3Config

    trainer = Trainer(
        fast_config(scenario="cflc", episodes=1, decision_interval=0.1, lane_gap_rule=False,
                    learner={"compile": False, "lane_epsilon": 1.0}),
        sumo_server.address, tmp_path,
    )  # fmt: skip
    assert trainer.lanes.every == 10
    try:
        agent = trainer.agent
        assert isinstance(agent.config, TD3Config)

        class Exploring:
            def act(self, obs: object) -> tuple[float, int]:
                x, mask = trainer.features(obs), trainer.lanes.mask(obs)  # type: ignore[arg-type]
                u, lane = agent.act(x, explore=True, mask=mask)
                return trainer.scale.to_env(max(u, 0.0)), (0, 1, -1)[lane]

        episode = run_episode(trainer.env, Exploring(), seed=11, options={"max_episode_time": 60.0})
    finally:
        trainer.close()
    reasons = [o.action.lane_change_refused for o in episode.observations[1:]]
    requests = [o.action.requested_lane_change for o in episode.observations[1:]]
    assert sum(r != 0 for r in requests) > 5  # it did ask
    assert "no_lane" not in reasons
    assert "in_progress" not in reasons
    asked_at = [o.seq for o, r in zip(episode.observations[:-1], requests, strict=True) if r]
    assert all(seq % 10 == 0 for seq in asked_at)
