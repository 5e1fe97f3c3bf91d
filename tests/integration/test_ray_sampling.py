"""Sampling workers: in-process on a real server, then one Ray actor per server under the
trainer (`sampling = "ray"`) on a local Ray bound to loopback."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from agent_client.errors import UsageError
from agent_client.training.config import TrainConfig, apply_overrides
from agent_client.training.sampling.worker import SamplingWorker, Settings, WorkerSpec
from agent_client.training.trainer import Trainer
from tests.conftest import RunningServer, sim_server

pytestmark = [pytest.mark.ray, pytest.mark.slow]


def spec(address: str) -> WorkerSpec:
    return WorkerSpec(
        address=address, scenario="cf", reward="safe",
        options={"decision_interval": 0.1, "max_episode_time": 2.0}, reset_options={},
        features="cf", lane_phase_every=1, n_lanes=1, lane_every=1, lane_gap_rule=True, lane_route_masks=True, noise="ou",
        noise_sigma=0.1, noise_theta=0.15, noise_dt=0.01, warmup_policy="idm", seed=0,
        timeout_s=10.0,
    )  # fmt: skip


@pytest.fixture
def fake() -> Iterator[RunningServer]:
    with sim_server("--backend", "fake") as server:
        yield server


def test_a_worker_samples_chunks_with_seeds_of_its_own(fake: RunningServer) -> None:
    worker = SamplingWorker(spec(fake.address), index=1, stride=3, first_seed=100)
    try:
        first = worker.sample(50, Settings(learning=False))
        second = worker.sample(50, Settings(learning=False))
    finally:
        worker.close()
    assert len(first.transitions) >= 50
    assert len(second.transitions) >= 50
    finished = first.finished + second.finished
    assert len(finished) >= 4  # 2 s episodes of 0.1 s steps
    assert [slot.episode.seed for slot in finished][:4] == [101, 104, 107, 110]
    assert {slot.env_index for slot in finished} == {1}
    # the figures travel, the observations stay behind
    assert all(slot.summary is not None for slot in finished)
    assert all(slot.figures().steps == len(slot.states) for slot in finished)
    assert all(not slot.episode.observations for slot in finished)


def test_a_worker_acts_with_the_policy_copy_it_is_sent(fake: RunningServer) -> None:
    from agent_client.rl.td3 import Agent, TD3Config

    agent = Agent(6, 1, TD3Config(compile=False), seed=0)
    with torch.no_grad():
        agent.state.actor[-2].zero_()
        agent.state.actor[-1].fill_(10.0)  # tanh(10): full throttle, whatever the state
    worker = SamplingWorker(spec(fake.address), index=0, stride=1, first_seed=0)
    try:
        chunk = worker.sample(
            30, Settings(learning=True, noise_scale=0.0), agent.policy_state_dict()
        )
    finally:
        worker.close()
    assert np.allclose([t.u for t in chunk.transitions], 1.0, atol=1e-6)


def ray_config(**overrides: object) -> TrainConfig:
    settings = {
        "episodes": 8,
        "eval_every": 0,
        "sampling": "ray",
        "sampling_chunk": 32,
        "policy_sync_every": 100,
        "scenario_options": {"max_episode_time": 5.0},
        "learner": {"learning_starts": 200, "compile": False, "batch_size": 64},
        **overrides,
    }
    return apply_overrides(TrainConfig(), settings)


@pytest.mark.sumo
def test_trainer_samples_on_ray_with_one_worker_per_server(
    local_ray: None, scenario_cache: Path, tmp_path: Path
) -> None:
    with (
        sim_server("--backend", "sumo", cache_dir=scenario_cache) as one,
        sim_server("--backend", "sumo", cache_dir=scenario_cache) as two,
    ):
        # two in flight: each actor has its next chunk queued behind the one it samples
        config = ray_config(chunks_in_flight=2)
        trainer = Trainer(config, [one.address, two.address], tmp_path / "run")
        finished: list[int] = []
        original = trainer._episode_done
        trainer._episode_done = lambda slot, log: (
            finished.append(slot.env_index),
            original(slot, log),
        )  # type: ignore[method-assign]
        try:
            progress = trainer.run()
            collector = trainer.collector
            assert collector.in_flight == 2  # type: ignore[union-attr]
            assert progress.episode >= 8
            assert progress.global_step >= 8 * 40  # 5 s episodes (or fewer on a crash)
            assert progress.updates > 0  # learning started: the policy copies acted
            assert set(finished) == {0, 1}  # both servers, one worker each
            assert collector._policy_version >= 2  # refreshed from the learner
            assert (tmp_path / "run" / "policy_final.pt").exists()
        finally:
            trainer.close()
            trainer.collector.close()  # type: ignore[union-attr]


def test_ray_sampling_needs_evaluation_servers_of_its_own(
    local_ray: None, fake: RunningServer, tmp_path: Path
) -> None:
    with pytest.raises(UsageError, match="--eval-server"):
        Trainer(ray_config(eval_every=10), [fake.address], tmp_path / "run")


def test_sampling_must_be_one_of_the_kinds() -> None:
    with pytest.raises(
        UsageError, match="sampling 'spark' is not one of: auto, local, processes, ray"
    ):
        apply_overrides(TrainConfig(), {"sampling": "spark"})
