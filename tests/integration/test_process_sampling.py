"""Sampling in processes of their own (``sampling = "processes"``) on real SUMO: the same
transitions as the lock-step collector, training over a pool, a worker that dies, a run's
end."""

from __future__ import annotations

import itertools
import os
import signal
from collections.abc import Iterator, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from agent_client.drivers.policy import ActionScale, lane_choice
from agent_client.envs.remote_env import RemoteEnv
from agent_client.rl.features import FeatureMap
from agent_client.rl.greedy import NumpyActor
from agent_client.rl.td3 import Agent, TD3Config
from agent_client.training.config import TrainConfig
from agent_client.training.run_log import read_rows
from agent_client.training.sampling.chunks import ChunkCollector
from agent_client.training.sampling.collect import LocalCollector, Slot, Transition
from agent_client.training.sampling.exploration import noise_scale_at
from agent_client.training.sampling.process_workers import ProcessWorkers
from agent_client.training.sampling.worker import (
    SamplingFailed,
    Settings,
    WorkerSpec,
    policy_arrays,
)
from agent_client.training.trainer import Trainer
from tests.conftest import RunningServer, sim_server
from tests.integration.test_ray_sampling import ray_config
from tests.integration.test_ray_sampling import spec as worker_spec
from tests.integration.test_workers import alive

pytestmark = [pytest.mark.sumo, pytest.mark.slow]

SEED = 300


@pytest.fixture(scope="module")
def sumo(scenario_cache: Path) -> Iterator[RunningServer]:
    with sim_server("--backend", "sumo", cache_dir=scenario_cache) as server:
        yield server


def greedy_policy() -> dict[str, object]:
    agent = Agent(FeatureMap("cf").dim, 1, TD3Config(compile=False), seed=3)
    return agent.policy_state_dict()


def process_transitions(address: str, policy: dict[str, object], n: int) -> list[Transition]:
    spec = worker_spec(address)
    collector = ChunkCollector(
        ProcessWorkers(), [spec], lambda: policy, lambda: Settings(True, noise_scale=0.0),
        lambda: SEED, chunk_steps=25,
    )  # fmt: skip
    transitions: list[Transition] = []
    try:
        while len(transitions) < n:
            collector.send()
            transitions += collector.receive().transitions
    finally:
        collector.close()
    return transitions[:n]


def lock_step_transitions(address: str, policy: dict[str, object], n: int) -> list[Transition]:
    """The trainer's `LocalCollector` on the same server, seeds and greedy policy."""
    spec = worker_spec(address)
    env = RemoteEnv(address, "cf", reward=spec.reward, timeout_s=10.0, **spec.options)
    actor = NumpyActor(policy_arrays(policy)["actor"])

    def choose(slots: Sequence[Slot]) -> tuple[np.ndarray, np.ndarray]:
        u = actor(np.stack([slot.x for slot in slots]).astype(np.float32))
        return np.clip(u, -1.0, 1.0), np.zeros(len(slots), int)

    scale = ActionScale.from_schema(env.welcome.action, "", 0.1)
    seeds = itertools.count(SEED)
    local = LocalCollector(
        [env], FeatureMap("cf"), lane_choice(1, 1, True, ""), scale, choose, lambda: next(seeds)
    )
    transitions: list[Transition] = []
    try:
        while len(transitions) < n:
            local.send()
            transitions += local.receive().transitions
    finally:
        env.close()
    return transitions[:n]


def test_process_workers_give_the_lock_step_collectors_transitions(sumo: RunningServer) -> None:
    """A greedy policy (no noise) on the same seeds: the same states, actions and rewards,
    whether the learner's process steps the server or a sampling process does."""
    policy = greedy_policy()
    n = 60  # 2 s episodes of 0.1 s: three episodes, two resets between them
    apart = process_transitions(sumo.address, policy, n)
    together = lock_step_transitions(sumo.address, policy, n)
    assert len(apart) == len(together) == n
    for a, b in zip(apart, together, strict=True):
        np.testing.assert_allclose(a.x, b.x, rtol=1e-6)
        np.testing.assert_allclose(a.next_x, b.next_x, rtol=1e-6)
        assert a.u == pytest.approx(b.u, abs=1e-6)
        assert a.reward == pytest.approx(b.reward, abs=1e-9)
        assert a.terminated == b.terminated
    assert len({round(float(t.u), 4) for t in apart}) > 1  # the policy acted, not a constant


def test_a_worker_that_dies_fails_the_receive_by_name(sumo: RunningServer) -> None:
    spec = replace(worker_spec(sumo.address), timeout_s=5.0)
    workers = ProcessWorkers()
    collector = ChunkCollector(
        workers, [spec], lambda: greedy_policy(), lambda: Settings(False), lambda: 0,
        chunk_steps=20,
    )  # fmt: skip
    try:
        collector.send()
        assert len(collector.receive().transitions) >= 20
        pid = workers.processes[0].pid
        assert pid is not None
        os.kill(pid, signal.SIGKILL)
        collector.send()
        with pytest.raises(SamplingFailed, match=r"sampling worker 0 \(tcp://.*exit code -9"):
            collector.receive()
    finally:
        collector.close()
    assert not alive(pid)


def test_a_ctrl_c_while_the_workers_start_is_not_theirs(
    sumo: RunningServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    """SIGINT reaches a worker that is still importing (the terminal's Ctrl-C, sent to the
    learner's process group, before the worker moved to a group of its own): it lives on."""
    workers = ProcessWorkers()
    wait_ready = ProcessWorkers._wait_ready

    def interrupted_first(self: ProcessWorkers, index: int, spec: WorkerSpec) -> None:
        pid = self.processes[index].pid
        assert pid is not None
        os.kill(pid, signal.SIGINT)
        wait_ready(self, index, spec)

    monkeypatch.setattr(ProcessWorkers, "_wait_ready", interrupted_first)
    collector = ChunkCollector(
        workers, [worker_spec(sumo.address)], lambda: greedy_policy(), lambda: Settings(False),
        lambda: 0, chunk_steps=10,
    )  # fmt: skip
    try:
        collector.send()
        assert len(collector.receive().transitions) >= 10
    finally:
        collector.close()


def test_close_ends_a_long_chunk_and_the_worker_says_goodbye(fake_server: RunningServer) -> None:
    """A close while a worker samples a long chunk: it stops after its current step, sends
    what it took and says goodbye within the grace (`CLOSE_GRACE_S`) that would end in a
    kill: its chunk of 10^7 steps would take hours."""
    workers = ProcessWorkers()
    collector = ChunkCollector(
        workers, [worker_spec(fake_server.address)], lambda: greedy_policy(),
        lambda: Settings(False), lambda: 0, chunk_steps=10**7,
    )  # fmt: skip
    collector.send()
    process = workers.processes[0]
    assert not workers.wait([0], 1.0)  # sampling its chunk
    collector.close()
    assert process.exitcode == 0  # ended by itself, not killed
    RemoteEnv(fake_server.address, "cf").close()  # the server is free again


def test_a_drop_ends_the_chunk_in_hand_and_the_one_asked_ahead(
    fake_server: RunningServer,
) -> None:
    """Two chunks of 10^7 steps in flight, then a drop: the worker ends the one in hand after
    its step and answers the one asked ahead at once (the learner discards both), then samples
    anew."""
    workers = ProcessWorkers()
    collector = ChunkCollector(
        workers, [worker_spec(fake_server.address)], lambda: greedy_policy(),
        lambda: Settings(False), lambda: 0, chunk_steps=10**7, in_flight=2,
    )  # fmt: skip
    collector.chunk_timeout_s = 30.0  # a chunk sampled to its end would take hours
    try:
        collector.send()
        assert not workers.wait([0], 1.0)  # sampling its first chunk
        collector.drop_episodes()
        assert collector.receive().transitions == []  # both asked before the drop
        collector.chunk_steps = 5
        collector.send()
        assert len(collector.receive().transitions) >= 5
    finally:
        collector.close()


def test_a_worker_that_cannot_take_its_server_says_why(sumo: RunningServer) -> None:
    holder = RemoteEnv(sumo.address, "cf")  # the server serves one client at a time
    collector = ChunkCollector(
        ProcessWorkers(), [worker_spec(sumo.address)], lambda: greedy_policy(),
        lambda: Settings(False), lambda: 0,
    )  # fmt: skip
    try:
        with pytest.raises(SamplingFailed, match=r"could not start: .*busy"):
            collector.send()
    finally:
        collector.close()
        holder.close()


def processes_config(**overrides: object) -> TrainConfig:
    """The Ray tests' short run, sampled in processes."""
    return ray_config(**{"sampling": "processes", **overrides})


def test_the_trainer_samples_in_processes_over_a_pool(scenario_cache: Path, tmp_path: Path) -> None:
    """Two sampling processes on one ``--pool 2`` address: both sessions drive, the learner
    learns from what they bring, the episodes log the exploration the workers were given, and
    the processes are gone after the run."""
    config = processes_config(noise_decay_steps=200, noise_final=0.2)
    with sim_server(
        "--backend", "sumo", "--pool", "2", cache_dir=scenario_cache, ready_timeout_s=180
    ) as pool:
        trainer = Trainer(config, [pool.address] * 2, tmp_path / "run")
        collector = trainer.collector
        assert isinstance(collector, ChunkCollector)
        assert isinstance(collector.workers, ProcessWorkers)
        workers = collector.workers
        finished: list[int] = []
        pids: set[int | None] = set()
        original = trainer._episode_done
        trainer._episode_done = lambda slot, log: (  # type: ignore[method-assign]
            finished.append(slot.env_index),
            pids.update(p.pid for p in workers.processes),
            original(slot, log),
        )
        try:
            progress = trainer.run()
            assert len(pids) == 2
            assert not any(alive(pid) for pid in pids if pid is not None)  # released at the end
            assert progress.episode == 8
            assert progress.global_step >= 8 * 40  # 5 s episodes (or fewer on a crash)
            assert progress.updates > 0  # learning started: the policy copies acted
            assert set(finished) == {0, 1}  # both sessions, one worker each
            assert collector._policy_version >= 2  # refreshed from the learner
            rows = read_rows(tmp_path / "run" / "episodes.csv")
            scales = [float(row["noise_scale"]) for row in rows]
            steps = [int(row["global_step"]) for row in rows]
            assert scales == pytest.approx([noise_scale_at(config, step) for step in steps])
            assert scales[-1] == pytest.approx(0.2)  # decayed, as the workers' noise was
            # the trainer has its sessions back: its own connection drives again
            trainer.env.reset(seed=1)
            trainer.env.step(np.zeros(1, np.float32))
        finally:
            trainer.close()
        # all sessions are free again: two more clients take them at once
        first, second = RemoteEnv(pool.address, "cf"), RemoteEnv(pool.address, "cf")
        first.close()
        second.close()


def test_one_server_and_one_seed_give_the_same_run_twice(
    sumo: RunningServer, tmp_path: Path
) -> None:
    """One sampling process asks for a chunk only after the learner has taken the last: the
    policy copies it acts with, and so the run, follow from the seed alone."""

    def episodes(name: str) -> list[tuple[str, ...]]:
        trainer = Trainer(processes_config(episodes=6), sumo.address, tmp_path / name)
        try:
            trainer.run()
        finally:
            trainer.close()
        rows = read_rows(tmp_path / name / "episodes.csv")
        return [(r["global_step"], r["steps"], r["total_reward"], r["q_mean"]) for r in rows]

    first = episodes("first")
    assert len(first) == 6
    assert episodes("second") == first
