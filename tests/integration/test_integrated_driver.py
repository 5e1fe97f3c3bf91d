"""The integrated driver on real SUMO: its own lane changes are executed, the safety layer's
overrides are counted, a shipped policy drives by name, and the table's command runs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from agent_client.drivers import pretrained
from agent_client.drivers.episode import run_episode
from agent_client.drivers.policy import ActionScale, PolicyDriver, lane_choice
from agent_client.envs.remote_env import RemoteEnv
from agent_client.evaluation.metrics import episode_summary
from agent_client.rl.features import FeatureMap
from protocol.messages import EndReason, Observation
from tests.conftest import RunningServer

pytestmark = pytest.mark.sumo

ROOT = Path(__file__).resolve().parents[2]

KEEP, OWN_LEFT, OWN_RIGHT = 1, 2, 3
"""With four lane choices (`residual_lanes = "default"`): 0 the reference's, 1 keep, 2 left, 3
right of the policy's own."""


class FixedPolicy:
    """A policy's output, fixed: `throttle` (residual: 0 is the reference's acceleration;
    absolute: 1 is full throttle), and a lane change of its own wherever one can happen, left
    first (or keep: choice `keep`)."""

    def __init__(self, throttle: float = 0.0, changes_lanes: bool = True, keep: int = KEEP) -> None:
        self.throttle = throttle
        self.changes_lanes = changes_lanes
        self.keep = keep

    def act(self, features: np.ndarray, mask: np.ndarray | None = None) -> tuple[float, int]:
        assert mask is not None
        for choice in (OWN_LEFT, OWN_RIGHT) if self.changes_lanes else ():
            if mask[choice]:
                return self.throttle, choice
        return self.throttle, self.keep


def integrated_driver(env: RemoteEnv, policy: FixedPolicy) -> PolicyDriver:
    """The integrated driver's parametrisation around `policy`: residual on IDM + MOBIL, the
    whole action range, four lane choices with the reference's first, no route masks."""
    schema = env.welcome.action
    scale = ActionScale(schema.acceleration_min, schema.acceleration_max, "idm+mobil", 0.1, 9.0,
                        shield=False)  # fmt: skip
    lanes = lane_choice(4, 10, False, "idm+mobil", route_masks=False, residual_lanes="default")
    return PolicyDriver(policy, FeatureMap("drive", lane_phase_every=10), scale, lanes)  # type: ignore[arg-type]


def test_a_policys_own_lane_change_is_executed_where_the_reference_keeps_its_lane(
    sumo_server: RunningServer,
) -> None:
    env = RemoteEnv(sumo_server.address, "cflc", warmup=30.0)
    driver = integrated_driver(env, FixedPolicy())
    decided: list[tuple[int, int, bool]] = []  # (the reference's, executed, layer's change)

    def watch(
        obs: Observation, action: tuple[float, int], reward: float, after: Observation
    ) -> None:
        decided.append((driver.lanes.command(0, obs), action[1], driver.override.lane_change))

    try:
        episode = run_episode(env, driver, seed=3, on_step=watch)
    finally:
        env.close()
    own = [k for k, (reference, executed, layer) in enumerate(decided)
           if executed != 0 and reference != executed and not layer]  # fmt: skip
    assert own, "the policy never asked for a change the reference would not make"
    lanes = [obs.ego.lane for obs in episode.observations]
    first = own[0]
    moved = lanes[first + 1 :]
    assert any(lane != lanes[first] for lane in moved), "its own change was not executed"
    assert any(obs.events.lane_change_started for obs in episode.observations[first + 1 :])
    summary = episode_summary(episode)
    assert summary.collisions == 0 and summary.safety_lane_changes == 0


def test_the_safety_layer_overrides_a_policy_that_would_crash_and_the_episode_counts_it(
    sumo_server: RunningServer,
) -> None:
    env = RemoteEnv(sumo_server.address, "cflc", warmup=30.0)
    schema = env.welcome.action
    full_throttle = ActionScale(schema.acceleration_min, schema.acceleration_max)  # absolute
    lanes = lane_choice(3, 10, False, route_masks=False)  # keep is choice 0
    policy = FixedPolicy(throttle=1.0, changes_lanes=False, keep=0)
    driver = PolicyDriver(policy, FeatureMap("drive", lane_phase_every=10), full_throttle, lanes)  # type: ignore[arg-type]
    overridden: list[bool] = []  # counted here, step by step, as the driver reports them

    def count(before: object, action: object, reward: float, after: object) -> None:
        overridden.append(driver.override.any)

    try:
        episode = run_episode(env, driver, seed=4, on_step=count)
    finally:
        env.close()
    summary = episode_summary(episode)
    rules = [o.rule for o in episode.overrides if o.acceleration]
    assert "collision" in rules, "full throttle into traffic was never braked for"
    assert 0 < summary.safety_steps == sum(overridden) < len(overridden)
    assert summary.safety_steps > 0 and "collision:" in summary.safety_rules
    assert summary.collisions == 0
    assert episode.observations[-1].reason != EndReason.COLLISION


@pytest.mark.skipif(not pretrained.names(), reason="no policy shipped")
def test_a_shipped_policy_drives_by_name(sumo_server: RunningServer) -> None:
    name = "cflc" if "cflc" in pretrained.names() else pretrained.names()[0]
    scenario = pretrained.settings(name).get("scenario", "cflc")
    if isinstance(scenario, list):
        scenario = scenario[0]
    done = subprocess.run(
        [sys.executable, "-m", "agent_client", "drive", "--server", sumo_server.address,
         "--scenario", scenario, "--policy", f"pretrained:{name}", "--episodes", "1",
         "--seed", "7", "--json"],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    row = json.loads(done.stdout.splitlines()[-1])
    assert row["collisions"] == 0 and row["steps"] > 0
    assert "safety_steps" in row and "red_lights" in row


def test_an_unknown_shipped_policy_is_one_line_and_status_2() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "agent_client", "drive", "--server", "tcp://127.0.0.1:1",
         "--policy", "pretrained:nosuch"],
        capture_output=True, text=True, timeout=60, cwd=ROOT,
    )  # fmt: skip
    assert done.returncode == 2
    assert len(done.stderr.strip().splitlines()) == 1 and "nosuch" in done.stderr


def test_the_table_on_a_small_grid(tmp_path: Path, scenario_cache: Path) -> None:
    out = tmp_path / "table.json"
    done = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "table.py"), "--maps", "cflc",
         "--drivers", "idm", "idm+mobil", "--episodes", "2", "--option", "warmup=20",
         "--out", str(out)],
        capture_output=True, text=True, timeout=600, cwd=ROOT,
        env={**os.environ, "XDG_CACHE_HOME": str(scenario_cache)},
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    saved = json.loads(out.read_text())
    row = saved["results"]["cflc"]["idm+mobil"]
    assert row["trips"] == 2 and 0.0 <= row["arrivals"] <= 1.0
    assert len(row["arrivals_ci"]) == 2 and row["arrivals_ci"][0] <= row["arrivals"]
    assert row["speed_ci"][0] <= row["speed"] <= row["speed_ci"][1]
    assert out.with_suffix(".png").stat().st_size > 0
    assert "cflc" in done.stdout and "idm+mobil" in done.stdout
    # IDM + MOBIL's lane changes are MOBIL's own decisions: none counted as the driver's own
    assert row["lane_changes"] > 0 and row["own_lane_changes"] == 0.0
    assert row["safety_layer"] == 0.0 and row["safety_rules"] == {}  # no layer, no rule
    assert saved["results"]["cflc"]["idm"]["lane_changes"] == 0
