"""Roads with a lane end through the bridge (protocol 1.6): the road ahead on the wire, IDM +
MOBIL merging, SUMO's own driver as a reference, and one env over several scenarios."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from agent_client.drivers.episode import run_episode
from agent_client.drivers.spec import load_driver
from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import UsageError
from protocol.messages import ROAD_RANGE, EndReason
from tests.conftest import RunningServer

pytestmark = pytest.mark.sumo

MERGE = {"flow": 600.0, "warmup": 40.0}


def test_idm_with_mobil_merges_from_the_ramp_where_idm_stands_at_the_lane_end(
    sumo_server: RunningServer,
) -> None:
    env = RemoteEnv(sumo_server.address, "merge", **MERGE, lane_end_patience=2.0)
    try:
        for seed in (11, 12, 13):
            merged = run_episode(env, load_driver("idm+mobil"), seed)
            last = merged.observations[-1]
            assert last.reason == EndReason.END_OF_ROAD
            assert sum(o.events.collision for o in merged.observations) == 0
            roads = [o.road for o in merged.observations]
            assert all(road is not None for road in roads)
            assert any(road.lanes_to_change == 1 for road in roads if road is not None)
            kept = run_episode(env, load_driver("idm"), seed)
            assert kept.observations[-1].reason == EndReason.LANE_END
    finally:
        env.close()


def test_one_env_draws_its_scenario_from_the_seed(sumo_server: RunningServer) -> None:
    env = RemoteEnv(sumo_server.address, ["merge", "cflc"], ramp_flow=100.0, max_episode_time=2.0)
    try:
        assert env.scenarios == ("merge", "cflc")
        for seed in (4, 7):
            _, info = env.reset(seed=seed)
            assert env.scenario == env.scenario_for(seed) == ("merge", "cflc")[seed % 2]
            assert info["observation"].road is not None
        env.reset(seed=4)
        assert env.scenario == "merge" and env.options["ramp_flow"] == 100.0
        env.reset(seed=7)
        assert env.scenario == "cflc" and "ramp_flow" not in env.options  # cflc has no ramp
        assert env.observation_space.shape == (40,)
        _, info = env.reset(seed=7)
        assert info["observation"].road.lane_end == ROAD_RANGE
    finally:
        env.close()
    with pytest.raises(UsageError, match="no scenario of merge, cflc has option 'banana'"):
        RemoteEnv(sumo_server.address, ["merge", "cflc"], banana=1.0)


def test_drive_runs_the_model_drivers_by_name(sumo_server: RunningServer) -> None:
    for spec in ("idm+mobil", "sumo"):
        result = subprocess.run(
            [sys.executable, "-m", "agent_client.cli.main", "drive", "--server",
             sumo_server.address, "--scenario", "lanedrop", "--policy", spec, "--episodes", "1",
             "--seed", "3", "--json", "--option", "drop_distance=500",
             "--option", "dropped_lane=right", "--option", "ego_lane=0"],
            capture_output=True, text=True, timeout=300, check=False,
        )  # fmt: skip
        assert result.returncode == 0, result.stderr
        (episode,) = [json.loads(line) for line in result.stdout.splitlines()]
        assert episode["reason"] == "end_of_road" and episode["collisions"] == 0
        assert episode["route_lanes"] == 1  # it started in the lane that ends, and left it
