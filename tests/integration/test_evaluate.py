"""calibrate-idm and evaluate end to end against a real SUMO server (short episodes)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from agent_client.cli.main import main
from agent_client.drivers.episode import run_episode
from agent_client.drivers.idm import IDMDriver
from agent_client.drivers.spec import load_driver
from agent_client.envs.remote_env import RemoteEnv
from agent_client.evaluation.metrics import episode_summary
from tests.conftest import RunningServer

pytestmark = [pytest.mark.sumo, pytest.mark.slow]


def tiny_policy(path: Path, features: str, lane_actions: int) -> Path:
    """An untrained policy file, as `agent-client train` would write one."""
    from agent_client.drivers.policy import ActionScale, save_policy
    from agent_client.rl.features import FeatureMap
    from agent_client.rl.lanes import LaneChoice
    from agent_client.rl.td3 import Agent

    feature_map = FeatureMap(features)
    agent = Agent(feature_map.dim, lane_actions)
    save_policy(
        path, agent.policy_state_dict(), feature_map, ActionScale(-6, 3), LaneChoice(lane_actions)
    )
    return path


def strict_json(path: Path) -> dict:
    def refuse(name: str) -> None:
        raise ValueError(f"non-standard JSON constant {name}")

    return json.loads(path.read_text(), parse_constant=refuse)


def test_calibrate_idm_writes_parameters_that_drive(
    sumo_server: RunningServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "idm.json"
    code = main(
        ["calibrate-idm", "--server", sumo_server.address, "--scenario", "cf", "--out", str(out),
         "--episodes", "3", "--seed", "7", "--maxiter", "3", "--popsize", "4",
         "--option", "max_episode_time=60"]
    )  # fmt: skip
    assert code == 0
    printed = capsys.readouterr().out
    recorded = [line for line in printed.splitlines() if line.startswith("recorded ")]
    assert [line.split()[1] for line in recorded] == ["1/3", "2/3", "3/3"]
    assert "generation 3/3" in printed
    assert f"wrote {out}" in printed
    document = strict_json(out)
    assert document["data"]["seeds"] == [7, 8, 9]
    assert document["data"]["scenario"] == "cf"
    assert document["data"]["samples"] > 500  # three human drivers followed for a while
    assert 0.0 < document["fit"]["gap_rmse_m"] < 15.0
    assert document["fit"]["gap_rmse_m"] <= document["fit"]["global_gap_rmse_m"] + 1e-9
    for name, value in document["params"].items():
        low, high = document["bounds"][name]
        assert low <= value <= high
    assert "1.28" in document["versions"]["backend"]
    driver = load_driver(f"idm:{out}")
    assert isinstance(driver, IDMDriver)
    assert driver.params.v0 == pytest.approx(document["params"]["v0"])
    env = RemoteEnv(sumo_server.address, "cf", max_episode_time=20.0)
    try:
        summary = episode_summary(run_episode(env, driver, seed=3))
    finally:
        env.close()
    assert summary.steps > 100 and summary.collisions == 0
    assert summary.average_speed > 3.0


def test_evaluate_cf_writes_a_full_report(
    sumo_server: RunningServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    policy = tiny_policy(tmp_path / "policy.pt", "cf", 1)
    params = tmp_path / "idm.json"
    params.write_text(json.dumps({"params": {"a": 1.4, "b": 1.8, "T": 1.2, "s0": 2.0, "v0": 20.0}}))
    out = tmp_path / "eval"
    code = main(
        ["evaluate", "--server", sumo_server.address, "--scenario", "cf", "--policy", str(policy),
         "--baseline", f"idm:{params}", "--episodes", "2", "--seed", "11", "--out", str(out),
         "--option", "max_episode_time=20"]
    )  # fmt: skip
    assert code == 0
    printed = capsys.readouterr().out
    assert printed.count("[policy ") == 2 and printed.count("[baseline ") == 2
    assert f"report: {out / 'report.md'}" in printed
    text = (out / "report.md").read_text()
    for needle in ("## Setting and how to rerun", "1.28.0", "--seed 11", "max_episode_time=20",
                   "## Car following", "average speed, m/s", "leader-at-entry ceiling",
                   "jerk samples above 5.6", "time headway < 1 s", "min TTC", "TTC < 4 s",
                   "DRL 12.44, IDM 11.53", "+7.9 %", "On one lane the ego cannot arrive",
                   "speed_distribution.png", "jerk_distribution.png", "Not applicable"):  # fmt: skip
        assert needle in text, needle
    metrics = strict_json(out / "metrics.json")
    assert metrics["seeds"] == [11, 12]
    assert metrics["versions"]["backend version"].startswith("1.28")
    for role in ("policy", "baseline"):
        driver = metrics["drivers"][role]
        assert driver["per_episode"]["seed"] == [11, 12]  # the same seeds for both
        assert driver["average_speed"] > 0.0
        assert driver["ceiling_speed"] is not None
        assert 0.0 <= driver["jerk_share_above_limit"] <= 1.0
        assert driver["headway"]["samples"] > 0
    assert metrics["drivers"]["baseline"]["collisions_per_episode"] == 0.0
    assert metrics["lane_changing"] is None
    for figure in ("speed_distribution.png", "jerk_distribution.png"):
        assert (out / figure).read_bytes()[:4] == b"\x89PNG"


def test_evaluate_cflc_fills_the_lane_change_tables(
    sumo_server: RunningServer, tmp_path: Path
) -> None:
    policy = tiny_policy(tmp_path / "policy.pt", "lc", 3)
    cf_policy = tiny_policy(tmp_path / "cf.pt", "cf", 1)
    run = tmp_path / "run"
    run.mkdir()
    with (run / "episodes.csv").open("w", newline="") as stream:
        writer = csv.DictWriter(
            stream, ["episode", "distance", "lane_changes_started", "lane_changes_refused"]
        )
        writer.writeheader()
        for episode in range(1, 7):
            writer.writerow({"episode": episode, "distance": 1500.0,
                             "lane_changes_started": 1, "lane_changes_refused": 3})  # fmt: skip
    out = tmp_path / "eval"
    code = main(
        ["evaluate", "--server", sumo_server.address, "--scenario", "cflc", "--policy", str(policy),
         "--baseline", "idm", "--cf-policy", str(cf_policy), "--run", str(run),
         "--table2-bins", "3", "--episodes", "2", "--out", str(out),
         "--option", "max_episode_time=20"]
    )  # fmt: skip
    assert code == 0
    text = (out / "report.md").read_text()
    assert "Not computed" not in text and "Not applicable" not in text
    for needle in ("### Table 2", "### Table 3", "US-101", "DRL-LC", "0.81", "12.74"):
        assert needle in text, needle
    metrics = strict_json(out / "metrics.json")
    assert metrics["lanes"] == 3
    rows = metrics["lane_changing"]["table2"]["rows"]
    assert [r["episodes"] for r in rows] == ["1-2", "3-4", "5-6"]
    assert rows[0]["success_rate"] == pytest.approx(0.25)
    assert rows[0]["frequency"] == pytest.approx(2 / (3.0 * 3))
    versus = metrics["lane_changing"]["integrated_vs_cf"]
    assert versus["cf_average_speed"] == metrics["drivers"]["cf_policy"]["average_speed"]
    policy_figures = metrics["drivers"]["policy"]
    assert policy_figures["table3"]["lane_changes"] == policy_figures["lane_changes"]["started"]
    assert metrics["drivers"]["baseline"]["lane_changes"]["started"] == 0  # IDM keeps its lane
