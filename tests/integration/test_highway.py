"""`sim-server --backend highway` as a real process: the same learner runs against it unchanged.

The conformance kit, `agent-client train` and `agent-client evaluate` are exactly those used
against the SUMO server; only the server's `--backend` differs.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.importorskip("highway_env")

from agent_client.cli.main import main
from agent_client.conformance.checks import PASS, run_checks
from agent_client.drivers.episode import run_episode
from agent_client.drivers.mobil import IDMMobilDriver
from agent_client.envs.remote_env import RemoteEnv
from agent_client.training.run_log import read_rows
from protocol.messages import ROAD_RANGE, EndReason
from tests.conftest import RunningServer, sim_server

pytestmark = pytest.mark.slow

CHECKS = {
    "handshake", "version_refusal", "schema", "reset", "step", "termination", "bad_requests",
    "determinism", "close",
}  # fmt: skip
"""Checks the kit runs at least (it may grow: every check it runs must pass)."""


@pytest.fixture(scope="module")
def highway_server() -> Iterator[RunningServer]:
    with sim_server("--backend", "highway") as server:
        yield server


def test_check_command_against_the_highway_server(highway_server: RunningServer) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "agent_client.cli.main", "check", "--server", highway_server.address,
         "--json", "--timeout", "60"],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout + result.stderr
    report = json.loads(result.stdout)
    assert report["ok"] is True and report["scenario"] == "cf"
    assert {c["name"] for c in report["checks"]} >= CHECKS
    assert {c["status"] for c in report["checks"]} == {PASS}
    details = {c["name"]: c["detail"] for c in report["checks"]}
    assert "backend highway 1.12" in details["handshake"]


@pytest.mark.parametrize("scenario", ["cflc", "merge"])
def test_the_multi_lane_scenarios_conform(highway_server: RunningServer, scenario: str) -> None:
    report = run_checks(highway_server.address, scenario, timeout_s=60.0)
    statuses = {r.name: r.status for r in report.results}
    assert set(statuses) >= CHECKS and set(statuses.values()) == {PASS}, report.format_table()


def train(server: str, out: Path, scenario: str, episodes: int, *extra: str) -> None:
    """`agent-client train` as a user runs it (the command of tests/integration/test_train.py).

    Small scenes without the ceiling keep it fast (the ceiling makes highway-env simulate each
    leader-at-entry to the end of the road); `evaluate` below checks the ceiling via the bridge.
    """
    result = subprocess.run(
        [sys.executable, "-m", "agent_client.cli.main", "train", "--server", server, "--out", str(out),
         "--scenario", scenario, "--episodes", str(episodes), "--quiet",
         "--decision-interval", "1.0", "--option", "max_episode_time=30",
         "--option", "report_ceiling=false", "--option", "vehicles_count=8",
         "--option", "vehicles_behind=2",
         "--set", "eval_every=0", "--set", "checkpoint_every=1",
         "--set", "learner.learning_starts=20", "--set", "learner.batch_size=16", "--set", "learner.compile=false", *extra],
        capture_output=True, text=True, timeout=600, check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout + result.stderr


def test_train_then_evaluate_on_cf(
    highway_server: RunningServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = tmp_path / "run"
    train(highway_server.address, run, "cf", 2)
    rows = read_rows(run / "episodes.csv")
    assert [int(r["episode"]) for r in rows] == [1, 2]
    assert all(int(r["steps"]) > 0 for r in rows)
    assert json.loads((run / "config.json").read_text())["scenario"] == "cf"
    assert (run / "policy.pt").stat().st_size > 0

    out = tmp_path / "eval"
    code = main(
        ["evaluate", "--server", highway_server.address, "--scenario", "cf",
         "--policy", str(run / "policy.pt"), "--baseline", "idm", "--episodes", "2",
         "--seed", "11", "--out", str(out), "--option", "max_episode_time=20",
         "--option", "vehicles_count=8", "--option", "vehicles_behind=1",
         "--option", "report_ceiling=true"]  # (training ran without it)
    )  # fmt: skip
    assert code == 0
    printed = capsys.readouterr().out
    assert printed.count("[policy ") == 2 and printed.count("[baseline ") == 2
    assert (out / "report.md").read_text().startswith("#")
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["versions"]["backend"] == "highway"
    baseline = metrics["drivers"]["baseline"]
    assert baseline["per_episode"]["seed"] == [11, 12]
    assert baseline["collisions_per_episode"] == 0.0
    assert baseline["average_speed"] > 5.0
    assert baseline["ceiling_speed"] is not None, printed  # the leader-at-entry, via the bridge
    assert metrics["drivers"]["policy"]["average_speed"] >= 0.0


def test_lane_changing_training_runs_on_cflc(highway_server: RunningServer, tmp_path: Path) -> None:
    # Without the gap rule, which let this one-episode run ask for no change at all: the test is
    # that lane changes are asked for and logged on the other simulator.
    rule = ("--set", "lane_gap_rule=false")
    train(highway_server.address, tmp_path, "cflc", 1, "--reward", "rlc", *rule)
    rows = read_rows(tmp_path / "episodes.csv")
    assert len(rows) == 1
    assert int(rows[0]["lane_changes_started"]) + int(rows[0]["lane_changes_refused"]) > 0


@pytest.mark.parametrize("scenario", ["merge", "exit"])
def test_idm_mobil_makes_the_lane_changes_its_route_needs(
    highway_server: RunningServer, scenario: str
) -> None:
    """The client's IDM+MOBIL reads the road ahead off the wire (protocol 1.6) and leaves the
    lane that ends: onto the motorway from the acceleration lane, off it by the exit."""
    env = RemoteEnv(highway_server.address, scenario, reward=lambda *_: 0.0, report_ceiling=False)
    try:
        episodes = [run_episode(env, IDMMobilDriver(), seed) for seed in range(3)]
    finally:
        env.close()
    for episode in episodes:
        stream = episode.observations
        assert all(o.road is not None for o in stream)
        assert stream[-1].reason == EndReason.END_OF_ROAD, (episode.seed, stream[-1].road)
        assert not any(o.events.collision for o in stream)
        assert any(o.events.lane_change_started for o in stream), episode.seed
        last = stream[-1].road
        assert last is not None and last.lanes_to_change == 0 and last.lane_end == ROAD_RANGE
        asked = stream[0].road
        assert asked is not None
        assert asked.lanes_to_change == 0 if scenario == "merge" else asked.lanes_to_change <= 0
