"""`RemoteVectorEnv` and training on several servers at once (real subprocesses)."""

from __future__ import annotations

import csv
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import pytest

from agent_client.envs.vector_env import RemoteVectorEnv
from agent_client.errors import ServerError
from agent_client.training.config import TrainConfig, apply_overrides
from agent_client.training.trainer import Trainer
from tests.conftest import RunningServer, sim_server


@pytest.fixture(scope="module")
def fake_servers() -> Iterator[list[RunningServer]]:
    with ExitStack() as stack:
        yield [stack.enter_context(sim_server("--backend", "fake")) for _ in range(3)]


def test_the_vector_env_steps_every_server_and_resets_finished_ones(
    fake_servers: list[RunningServer],
) -> None:
    addresses = [s.address for s in fake_servers]
    env = RemoteVectorEnv(addresses, "cf", reward="ra3", max_episode_time=1.0)
    try:
        assert env.num_envs == 3 and env.observation_space.shape == (3, 40)
        first, info = env.reset(seed=5)
        assert [o.ego.speed for o in info["observation"]] == list(first[:, 1])
        actions = {"acceleration": np.array([[1.0], [0.0], [-1.0]]), "lane_change": np.zeros(3)}
        _, _, _, _, info = env.step(actions)
        requested = [o.action.requested_acceleration for o in info["observation"]]
        assert requested == [1.0, 0.0, -1.0]  # each server got its own action
        for _ in range(20):  # 1 s episodes at 0.1 s: all end, all restart in the same step
            _, _, _, truncated, info = env.step(actions)
            if truncated.any():
                break
        assert truncated.all() and info["_final_obs"].all()
        assert all(o.seq == 0 for o in info["observation"])  # already the next episode
        assert all(o.truncated for o in info["final_observation"])
    finally:
        env.close()


def test_a_single_server_twice_is_refused_as_busy_and_left_free(
    fake_servers: list[RunningServer],
) -> None:
    # An address may repeat where it serves a pool (tests/integration/test_pool.py); one
    # simulator refuses the second session, and the first is let go.
    with pytest.raises(ServerError, match=r"busy.*--pool"):
        RemoteVectorEnv([fake_servers[0].address] * 2)
    RemoteVectorEnv([fake_servers[0].address]).close()


def test_training_on_three_servers_fills_one_buffer(
    fake_servers: list[RunningServer], tmp_path: Path
) -> None:
    config = apply_overrides(
        TrainConfig(),
        {"episodes": 9, "eval_every": 0, "scenario_options": {"length": 300.0},
         "learner": {"learning_starts": 100, "compile": False}},
    )  # fmt: skip
    trainer = Trainer(config, [s.address for s in fake_servers], tmp_path)
    try:
        progress = trainer.run()
    finally:
        trainer.close()
    with (tmp_path / "episodes.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert [int(r["episode"]) for r in rows] == list(range(1, 10))
    assert progress.global_step == len(trainer.buffer) >= sum(int(r["steps"]) for r in rows)
    assert len({r["seed"] for r in rows}) == 9  # every episode had its own seed
    assert trainer.agent.n_updates > 0
