"""`RemoteEnv` as the field's libraries see it: the Gymnasium id, the default spaces, the
checker, and the vector env following the chosen action space (real server processes)."""

from __future__ import annotations

import subprocess
import sys
import warnings
from collections.abc import Iterator

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from agent_client.envs import ENV_ID, RemoteEnv, RemoteVectorEnv
from tests.conftest import RunningServer, sim_server

MAKE = """
import gymnasium
{imports}
env = gymnasium.make({env_id!r}, server={address!r}, scenario="cf")
observation, _ = env.reset(seed=1)
_, reward, *_ = env.step(env.action_space.sample())
print(env.action_space, observation.shape, type(env.unwrapped).__name__)
env.close()
"""


def run_fresh(code: str) -> subprocess.CompletedProcess[str]:
    """`code` in a new interpreter: nothing imported or registered beforehand."""
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False
    )


@pytest.fixture(scope="module")
def fake(scenario_cache: object) -> Iterator[RunningServer]:
    with sim_server("--backend", "fake") as server:
        yield server


@pytest.mark.parametrize(
    ("env_id", "imports"),
    [
        (f"agent_client:{ENV_ID}", ""),  # gymnasium imports the package itself
        (ENV_ID, "import agent_client"),  # imported after gymnasium: registers
        (ENV_ID, "from agent_client import RemoteEnv"),
    ],
)
def test_gymnasium_make_works_in_a_fresh_interpreter(
    fake: RunningServer, env_id: str, imports: str
) -> None:
    result = run_fresh(MAKE.format(imports=imports, env_id=env_id, address=fake.address))
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "Box(-1.0, 1.0, (1,), float32) (40,) RemoteEnv"


def test_without_any_import_the_bare_id_is_not_found(fake: RunningServer) -> None:
    """Gymnasium 1.x loads no entry points: the docs say which forms work, and this is why."""
    result = run_fresh(MAKE.format(imports="", env_id=ENV_ID, address=fake.address))
    assert result.returncode != 0
    assert "NamespaceNotFound" in result.stderr


def test_importing_the_package_alone_imports_no_gymnasium() -> None:
    result = run_fresh("import sys, agent_client; print('gymnasium' in sys.modules)")
    assert result.stdout.strip() == "False", result.stderr


def test_make_passes_options_through(fake: RunningServer) -> None:
    env = gymnasium.make(ENV_ID, server=fake.address, action_space="dict", max_episode_time=1.0)
    try:
        assert isinstance(env.action_space, gymnasium.spaces.Dict)
        env.reset(seed=2)
        steps, done = 0, False
        while not done:
            *_, terminated, truncated, _ = env.step({"acceleration": [0.0], "lane_change": 0})
            done, steps = terminated or truncated, steps + 1
        assert steps == 10  # 1 s of 0.1 s decisions
    finally:
        env.close()


@pytest.mark.sumo
@pytest.mark.parametrize(("scenario", "width"), [("cf", 1), ("cflc", 2)])
def test_default_spaces_pass_the_checker_without_a_warning(
    sumo_server: RunningServer, scenario: str, width: int
) -> None:
    env = RemoteEnv(sumo_server.address, scenario)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            check_env(env, skip_render_check=True)
        assert [str(w.message) for w in caught] == []
        assert env.action_space == gymnasium.spaces.Box(-1.0, 1.0, (width,), np.float32)
        assert np.isfinite(env.observation_space.low).all()
        assert np.isfinite(env.observation_space.high).all()
    finally:
        env.close()


@pytest.mark.sumo
def test_hybrid_box_asks_the_server_for_the_lane_change(sumo_server: RunningServer) -> None:
    env = RemoteEnv(sumo_server.address, "cflc")
    try:
        env.reset(seed=4)
        _, _, _, _, info = env.step(np.array([0.0, 0.9], np.float32))
        applied = info["observation"].action
        assert applied.requested_lane_change == 1
        assert applied.requested_acceleration == pytest.approx(-1.5)
        _, _, _, _, info = env.step(np.array([1.0, -0.9], np.float32))
        assert info["observation"].action.requested_lane_change == -1
        assert info["observation"].action.requested_acceleration == pytest.approx(3.0)
    finally:
        env.close()


def test_vector_env_follows_the_chosen_action_space(scenario_cache: object) -> None:
    with sim_server("--backend", "fake") as one, sim_server("--backend", "fake") as two:
        vec = RemoteVectorEnv([one.address, two.address], "cf", action_space="discrete")
        try:
            assert vec.single_action_space == gymnasium.spaces.Discrete(7)
            assert vec.action_space == gymnasium.spaces.MultiDiscrete([7, 7])
            vec.reset(seed=0)
            _, _, _, _, infos = vec.step(np.array([0, 6]))
            requested = [o.action.requested_acceleration for o in infos["observation"]]
            assert requested == [-6.0, 3.0]
            _, _, _, _, infos = vec.step({"acceleration": [[1.0], [2.0]], "lane_change": [0, 0]})
            assert [o.action.requested_acceleration for o in infos["observation"]] == [1.0, 2.0]
        finally:
            vec.close()
