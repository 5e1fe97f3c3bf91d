"""RLlib's PPO (new API stack) with two env runners, each on its own real SUMO server."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from tests.conftest import sim_server
from tests.integration.test_own_simulators import simulators_under, wait_until_gone

pytestmark = [pytest.mark.ray, pytest.mark.slow]
rllib = pytest.importorskip("agent_client.rllib")


@pytest.mark.parametrize(
    ("worker", "env", "per_runner", "servers", "expected"),
    [
        (0, 0, 1, 2, 0),  # the local env runner (if it makes an env) shares runner 1's
        (1, 0, 1, 2, 0),
        (2, 0, 1, 2, 1),
        (1, 1, 2, 4, 1),
        (2, 0, 2, 4, 2),
        (2, 1, 2, 4, 3),
        (3, 0, 1, 2, 0),  # more envs than servers: wraps around (and then waits for a free one)
    ],
)
def test_env_runner_and_env_index_choose_the_server(
    worker: int, env: int, per_runner: int, servers: int, expected: int
) -> None:
    assert rllib.server_index(worker, env, per_runner, servers) == expected


@pytest.mark.sumo
def test_without_servers_each_env_runs_a_simulator_of_its_own(
    local_ray: None, scenario_cache: Path
) -> None:
    from ray.rllib.algorithms.ppo import PPOConfig

    # The cache folder on their command lines tells this test's simulators from any other.
    env_config = {"scenario": "cf", "max_episode_time": 10.0,
                  "simulator_args": f"--backend sumo --cache-dir {scenario_cache}"}  # fmt: skip
    config = (
        PPOConfig()
        .environment(rllib.register(), env_config=env_config)
        .env_runners(num_env_runners=2, num_envs_per_env_runner=1)
        .training(train_batch_size_per_learner=400, minibatch_size=100, num_epochs=1)
        .rl_module(model_config={"fcnet_hiddens": [16]})
    )
    algo = config.build_algo()
    try:
        result = algo.train()
        used = [a for a in algo.env_runner_group.foreach_env_runner(addresses) if a]
        assert len(simulators_under(scenario_cache)) == 2
    finally:
        algo.stop()
    assert len({address for runner in used for address in runner}) == 2  # one each
    assert all(address.startswith("ipc://") for runner in used for address in runner)
    assert result["env_runners"]["num_env_steps_sampled_lifetime"] >= 400
    wait_until_gone(scenario_cache, 60.0)


def addresses(runner: Any) -> list[str] | None:
    if runner.env is None:  # the local env runner has no env
        return None
    return [env.unwrapped.address for env in runner.env.unwrapped.envs]


@pytest.mark.sumo
def test_ppo_trains_with_one_server_per_env_runner(local_ray: None, scenario_cache: Path) -> None:
    from ray.rllib.algorithms.ppo import PPOConfig

    with (
        sim_server("--backend", "sumo", cache_dir=scenario_cache) as one,
        sim_server("--backend", "sumo", cache_dir=scenario_cache) as two,
    ):
        env_config = {"servers": [one.address, two.address], "scenario": "cf",
                      "max_episode_time": 10.0}  # fmt: skip
        config = (
            PPOConfig()
            .environment(rllib.register(), env_config=env_config)
            .env_runners(num_env_runners=2, num_envs_per_env_runner=1)
            .training(train_batch_size_per_learner=400, minibatch_size=100, num_epochs=2)
            .rl_module(model_config={"fcnet_hiddens": [32, 32]})
        )
        algo = config.build_algo()
        try:
            results = [algo.train() for _ in range(2)]
            used = [a for a in algo.env_runner_group.foreach_env_runner(addresses) if a]
        finally:
            algo.stop()
    assert sorted(address for runner in used for address in runner) == sorted(
        [one.address, two.address]
    )
    sampled = results[-1]["env_runners"]["num_env_steps_sampled_lifetime"]
    assert sampled >= 800
    assert results[-1]["learners"]["default_policy"]["num_module_steps_trained"] > 0
