"""Stable-Baselines3 through the bridge, as a new user would run it: no adapter, real SUMO."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import gymnasium
import pytest

from agent_client.envs import ENV_ID
from tests.conftest import RunningServer

pytestmark = [pytest.mark.sumo, pytest.mark.sb3]
stable_baselines3 = pytest.importorskip("stable_baselines3")
EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "sb3_td3.py"


@pytest.mark.parametrize("scenario", ["cf", "cflc"])
@pytest.mark.parametrize("algo", ["TD3", "SAC"])
def test_td3_and_sac_take_the_default_spaces_as_they_are(
    sumo_server: RunningServer, scenario: str, algo: str
) -> None:
    env = gymnasium.make(ENV_ID, server=sumo_server.address, scenario=scenario)
    try:
        model = getattr(stable_baselines3, algo)("MlpPolicy", env, learning_starts=10)
        model.learn(total_timesteps=20)  # a few real steps and one update through the bridge
        assert model.num_timesteps == 20
    finally:
        env.close()


@pytest.mark.slow
def test_td3_improves_on_its_untrained_start(sumo_server: RunningServer) -> None:
    """3000 steps of 0.5 s decisions: the greedy return on held-out seeds must rise (the
    untrained actor brakes until the episode ends as an unreasonable stop)."""
    command = [
        sys.executable, str(EXAMPLE), "--server", sumo_server.address, "--algo", "td3",
        "--steps", "3000", "--learning-starts", "1000", "--decision-interval", "0.5",
        "--episode-seconds", "60", "--eval-episodes", "5", "--json",
    ]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["return_after"] > result["return_before"] + 20.0, result
