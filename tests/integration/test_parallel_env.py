"""`RemoteParallelEnv` passes PettingZoo's own API test against live servers: the fake backend's
many egos and, on the `ring`, four of SUMO's vehicles (real subprocesses on free loopback
ports)."""

from __future__ import annotations

import time
import warnings

import pytest

from agent_client import RemoteParallelEnv
from tests.conftest import RunningServer

parallel_api_test = pytest.importorskip("pettingzoo.test").parallel_api_test

OURS = "RemoteParallelEnv.reset ignores option(s) 'options'"
"""The one warning: the API test resets with an option no scenario has ({"options": 1})."""


def api_test(env: RemoteParallelEnv, num_cycles: int) -> None:
    """PettingZoo's test, with no warning of its own (it warns where an env breaks its API)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        parallel_api_test(env, num_cycles=num_cycles)
    others = [str(w.message) for w in caught if not str(w.message).startswith(OURS)]
    assert others == []


def test_the_parallel_api_test_passes_on_the_fake_backend(fake_server: RunningServer) -> None:
    env = RemoteParallelEnv(fake_server.address, "cf", egos=4, max_episode_time=10.0)
    try:
        api_test(env, num_cycles=200)
        assert env.possible_agents == ["ego.0", "ego.1", "ego.2", "ego.3"]
    finally:
        env.close()


@pytest.mark.sumo
def test_four_egos_on_the_sumo_ring(sumo_server: RunningServer) -> None:
    started = time.monotonic()
    env = RemoteParallelEnv(
        sumo_server.address, "ring", egos=4, max_episode_time=10.0, reward="safe"
    )
    try:
        api_test(env, num_cycles=100)
        assert len(env.possible_agents) == 4
        observations, infos = env.reset(seed=3)
        assert set(observations) == set(env.possible_agents) == set(env.agents)
        leaders = {infos[agent]["observation"].neighbours.leader.id for agent in env.agents}
        assert len(leaders) == 4  # spread round the ring: each follows another vehicle
        for seq in range(1, 21):
            before = list(env.agents)
            observations, rewards, _, _, infos = env.step(
                {agent: {"acceleration": [0.0]} for agent in before}
            )
            assert list(observations) == list(rewards) == before  # each ego that drove, in order
            assert {infos[agent]["observation"].seq for agent in before} == {seq}
            if not env.agents:
                break
    finally:
        env.close()
    assert time.monotonic() - started < 30.0


@pytest.mark.sumo
def test_a_share_of_cflc_traffic_with_egos_joining(sumo_server: RunningServer) -> None:
    env = RemoteParallelEnv(
        sumo_server.address, "cflc", ego_share=0.25, warmup=60.0, max_episode_time=20.0
    )
    try:
        observations, _ = env.reset(seed=2)
        first = list(env.agents)
        assert first and set(observations) == set(first) == set(env.possible_agents)
        joiners: list[str] = []
        while env.agents:
            before = list(env.agents)
            observations, rewards, terminations, _, infos = env.step(
                {agent: {"acceleration": [0.3]} for agent in before}
            )
            new = [agent for agent in observations if agent not in before]
            assert list(observations)[: len(before)] == before  # then those that join
            for agent in new:
                assert infos[agent]["joined"] and rewards[agent] == 0.0
                assert not terminations[agent] and agent in env.agents
            joiners += new
        assert joiners  # ~0.6 veh/s enter, a quarter of them join (the backend tests count)
        assert env.possible_agents == [*first, *joiners]  # every ego seen, in order
        env.reset(seed=2)  # the same episode again: the same SUMO ids, none of them new
        while env.agents:
            env.step({agent: {"acceleration": [0.3]} for agent in env.agents})
        assert env.possible_agents == [*first, *joiners]
        api_test(env, num_cycles=50)
    finally:
        env.close()
