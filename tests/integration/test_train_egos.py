"""`agent-client train --egos 4` on SUMO's ring: four of its vehicles driven by one shared
policy in one simulation, every ego's steps learned from (a real server on a free loopback
port, its readiness line awaited, stopped afterwards)."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from agent_client.training.run_log import read_rows
from tests.conftest import sim_server

pytestmark = [pytest.mark.sumo, pytest.mark.slow]


def test_a_few_episodes_with_four_egos_on_the_ring(scenario_cache: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    started = time.monotonic()
    with sim_server("--backend", "sumo", cache_dir=scenario_cache) as server:
        trained = subprocess.run(
            [
                sys.executable, "-m", "agent_client.cli.main", "train", "--server", server.address,
                "--scenario", "ring", "--egos", "4", "--episodes", "8", "--out", str(out),
                "--quiet", "--decision-interval", "0.5", "--option", "max_episode_time=30",
                "--set", "eval_every=0", "--set", "learner.learning_starts=150",
                "--set", "learner.batch_size=64", "--set", "learner.compile=false",
            ],
            capture_output=True, text=True, timeout=120, check=False,
        )  # fmt: skip
    elapsed = time.monotonic() - started
    assert trained.returncode == 0, trained.stderr
    rows = read_rows(out / "episodes.csv")
    assert [int(r["episode"]) for r in rows] == list(range(1, 9))
    assert sorted({r["ego"] for r in rows}) == ["ego.0", "ego.1", "ego.2", "ego.3"]
    steps = [int(r["global_step"]) for r in rows]
    assert steps == sorted(steps) and steps[-1] == sum(int(r["steps"]) for r in rows)
    assert steps[-1] > 150 and any(r["critic_loss"] != "nan" for r in rows)  # it learned
    assert (out / "policy.pt").exists() and (out / "checkpoint.pt").exists()
    assert elapsed < 60.0, elapsed
