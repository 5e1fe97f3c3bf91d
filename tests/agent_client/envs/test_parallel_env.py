"""`RemoteParallelEnv` against in-process servers: our serving loop and `Session` with the fake
backend's many egos in a thread (`tests.agent_client.conformance.toys`), and variants that are
too old, offer no egos, stay silent or break a rule of §3.1."""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Iterator

import gymnasium as gym
import numpy as np
import pytest

from agent_client import RemoteEnv, RemoteParallelEnv
from agent_client.errors import InvalidReply, ServerError, ServerTimeout, UsageError
from agent_client.rl.rewards import make_reward
from protocol.messages import Observation
from tests.agent_client.conformance.toys import (
    ListsEgosTwice,
    ManyEgosProtocol,
    NoEgos,
    OldProtocol,
    SilentOnMultiStep,
    ToyServer,
    zero_reward,
)

IDS = ["ego.0", "ego.1", "ego.2"]


@pytest.fixture
def toy() -> Iterator[ToyServer]:
    with ToyServer() as server:
        yield server


@pytest.fixture
def env(toy: ToyServer) -> Iterator[RemoteParallelEnv]:
    parallel = RemoteParallelEnv(toy.address, "cf", egos=3, max_episode_time=3.0)
    try:
        yield parallel
    finally:
        parallel.close()


def named(acceleration: float) -> dict[str, object]:
    return {"acceleration": [acceleration], "lane_change": 0}


def test_every_ego_is_an_agent_with_remote_envs_spaces(env: RemoteParallelEnv) -> None:
    observations, infos = env.reset(seed=4)
    assert env.possible_agents == env.agents == list(observations) == list(infos) == IDS
    assert env.max_num_agents == env.num_agents == 3
    for agent in IDS:
        space = env.observation_space(agent)
        assert space is env.observation_space(agent) and space.contains(observations[agent])
        assert env.action_space(agent) is env.action_space(agent)
        assert env.action_space(agent) == gym.spaces.Box(-1.0, 1.0, (1,), np.float32)  # one lane
        obs = infos[agent]["observation"]
        assert isinstance(obs, Observation) and obs.seq == 0 and infos[agent]["seed"] == 4
        speed = observations[agent][env.flatten.index("ego_speed")]
        assert speed == pytest.approx(obs.ego.speed, rel=1e-6)
    assert env.action_space("ego.0") is not env.action_space("ego.1")  # seeded apart
    with pytest.raises(ValueError, match=r"no agent 'ego\.9'"):
        env.observation_space("ego.9")


def test_possible_agents_before_any_reset_reset_once_to_find_out(toy: ToyServer) -> None:
    env = RemoteParallelEnv(toy.address, "cf", egos=2)
    try:
        assert env.possible_agents == ["ego.0", "ego.1"] and env.agents == []
        assert env.action_space("ego.1").shape == (1,)
        _, infos = env.reset(seed=1)
        assert infos["ego.1"]["observation"].seq == 0
        _, _, _, _, infos = env.step({agent: named(0.0) for agent in env.agents})
        assert infos["ego.1"]["observation"].seq == 1
    finally:
        env.close()


def test_each_agent_gets_its_own_command_and_reward(toy: ToyServer) -> None:
    reward = make_reward("safe")
    env = RemoteParallelEnv(toy.address, "cf", egos=3, reward=reward)
    try:
        _, infos = env.reset(seed=2)
        before = {agent: infos[agent]["observation"] for agent in IDS}
        actions = {"ego.0": named(1.0), "ego.1": np.array([0.0], np.float32), "ego.2": named(-1.0)}
        _, rewards, terminations, truncations, infos = env.step(actions)
        requested = {a: infos[a]["observation"].action.requested_acceleration for a in IDS}
        assert requested == {"ego.0": 1.0, "ego.1": pytest.approx(-1.5), "ego.2": -1.0}
        for agent in IDS:
            obs = infos[agent]["observation"]
            assert rewards[agent] == reward(before[agent], obs, obs.time - before[agent].time)
        assert not any(terminations.values()) and not any(truncations.values())
        assert env.last_frame is not None and env.last_frame.seq == 1
    finally:
        env.close()


def test_an_ego_that_crashes_leaves_and_the_time_limit_ends_the_others(toy: ToyServer) -> None:
    env = RemoteParallelEnv(toy.address, "cf", egos=3, reward=zero_reward, max_episode_time=60.0)
    try:
        env.reset(seed=5)
        seen: list[str] = []
        while env.agents:
            actions = {agent: named(3.0 if agent == "ego.0" else 0.0) for agent in env.agents}
            observations, rewards, terminations, truncations, _ = env.step(actions)
            assert list(observations) == list(rewards) == list(terminations) == list(actions)
            if terminations.get("ego.0"):
                seen.append("crash")
                assert env.agents == ["ego.1", "ego.2"]
        assert seen == ["crash"]  # listed once, then gone
        assert truncations == {"ego.1": True, "ego.2": True}
        assert env.last_frame is not None and env.last_frame.reason == "time_limit"
        with pytest.raises(gym.error.ResetNeeded):
            env.step({})
    finally:
        env.close()


def test_actions_must_name_exactly_the_running_agents(env: RemoteParallelEnv) -> None:
    env.reset(seed=1)
    with pytest.raises(ValueError, match=r"no action for 'ego\.2'"):
        env.step({"ego.0": named(0.0), "ego.1": named(0.0)})
    with pytest.raises(ValueError, match=r"no running agent 'ego\.7'"):
        env.step({**{agent: named(0.0) for agent in IDS}, "ego.7": named(0.0)})
    with pytest.raises(ValueError, match="finite"):
        env.step({**{agent: named(0.0) for agent in IDS}, "ego.1": named(float("nan"))})
    _, _, _, _, infos = env.step({agent: named(0.0) for agent in IDS})  # nothing was sent
    assert infos["ego.0"]["observation"].seq == 1


def test_the_same_seed_gives_the_same_episode(env: RemoteParallelEnv) -> None:
    streams = []
    for _ in range(2):
        observations, _ = env.reset(seed=21)
        stream = [np.stack([observations[a] for a in IDS])]
        for _ in range(10):
            observations, *_ = env.step({agent: named(0.3) for agent in env.agents})
            stream.append(np.stack([observations[a] for a in IDS]))
        streams.append(np.stack(stream))
    assert np.array_equal(streams[0], streams[1])
    env.reset()  # without a seed: drawn from the generator of the last one
    assert env.episode_seed != 21


def test_reset_options_the_scenario_lacks_are_ignored_with_a_warning(
    env: RemoteParallelEnv,
) -> None:
    with pytest.warns(UserWarning, match=r"ignores option\(s\) 'options'"):
        env.reset(seed=0, options={"options": 1, "max_episode_time": 0.5})
    steps = 0
    while env.agents:
        env.step({agent: named(0.0) for agent in env.agents})
        steps += 1
    assert steps == 5  # max_episode_time 0.5 s held for this episode
    with pytest.raises(UsageError, match="egos is fixed"):
        env.reset(options={"egos": 2})


def test_one_ego_is_the_servers_single_ego(toy: ToyServer) -> None:
    env = RemoteParallelEnv(toy.address, "cf", egos=1)
    try:
        observations, _ = env.reset(seed=1)
        assert list(observations) == env.possible_agents == ["ego"]
    finally:
        env.close()


@pytest.mark.parametrize(
    ("server_class", "words"),
    [
        (OldProtocol, "speaks protocol 1.3: RemoteParallelEnv needs 1.4 or newer"),
        (NoEgos, "scenario cf at tcp://127.0.0.1:"),
    ],
)
def test_a_server_without_many_egos_is_refused_before_any_reset(
    server_class: type[ToyServer], words: str
) -> None:
    with server_class() as server:
        with pytest.raises(UsageError, match=words):
            RemoteParallelEnv(server.address, "cf", egos=2)
        assert server.session.owner is None  # the env said goodbye


def test_a_share_of_the_traffic_needs_a_server_of_protocol_1_5() -> None:
    with ManyEgosProtocol() as server:
        with pytest.raises(UsageError, match=r"speaks protocol 1\.4: ego_share needs 1\.5"):
            RemoteParallelEnv(server.address, "cf", ego_share=0.5)
        assert server.session.owner is None  # the env said goodbye
        RemoteParallelEnv(server.address, "cf", egos=2).close()  # a number it can serve


def test_bad_arguments_are_usage_errors(toy: ToyServer) -> None:
    for egos in (0, True, 1.5):
        with pytest.raises(UsageError, match="egos must be an integer >= 1"):
            RemoteParallelEnv(toy.address, "cf", egos=egos)  # type: ignore[arg-type]
    with pytest.raises(UsageError, match="has no option 'flow'"):
        RemoteParallelEnv(toy.address, "cf", egos=2, flow=1200.0)
    with pytest.raises(UsageError, match="action_space 'wheel'"):
        RemoteParallelEnv(toy.address, "cf", egos=2, action_space="wheel")
    with pytest.raises(UsageError, match=r"give egos .* or ego_share"):
        RemoteParallelEnv(toy.address, "cf")
    with pytest.raises(UsageError, match=r"give egos .* or ego_share"):
        RemoteParallelEnv(toy.address, "cf", egos=2, ego_share=0.5)
    for share in (0.0, 1.5, "half", True):
        with pytest.raises(UsageError, match="ego_share must be"):
            RemoteParallelEnv(toy.address, "cf", ego_share=share)  # type: ignore[arg-type]
    with pytest.raises(UsageError, match="has no option ego_share: its server places"):
        RemoteParallelEnv(toy.address, "cf", ego_share=0.5)  # the fake places its egos


def test_too_many_egos_is_the_servers_refusal(toy: ToyServer) -> None:
    env = RemoteParallelEnv(toy.address, "cf", egos=999)
    try:
        with pytest.raises(ServerError, match="invalid_option: option egos 999"):
            env.reset(seed=1)
    finally:
        env.close()


def test_a_broken_frame_is_an_invalid_reply_naming_the_field() -> None:
    with ListsEgosTwice() as server:
        env = RemoteParallelEnv(server.address, "cf", egos=2)
        try:
            with pytest.raises(InvalidReply) as caught:
                env.reset(seed=1)
            assert caught.value.field == "multi_observation.egos[1].id"
        finally:
            env.close()


def test_a_silent_server_times_out_at_the_step_deadline() -> None:
    with SilentOnMultiStep() as server:
        env = RemoteParallelEnv(server.address, "cf", egos=2, timeout_s=0.5)
        try:
            env.reset(seed=1)
            start = time.monotonic()
            with pytest.raises(ServerTimeout, match=r"within 0\.5 s"):
                env.step({agent: named(0.0) for agent in env.agents})
            assert time.monotonic() - start < 2.0
        finally:
            env.close()


def test_ctrl_c_ends_a_wait_at_once() -> None:
    main = threading.main_thread().ident
    assert main is not None
    interrupt = threading.Timer(0.3, signal.pthread_kill, (main, signal.SIGINT))
    with SilentOnMultiStep() as server:
        env = RemoteParallelEnv(server.address, "cf", egos=2, timeout_s=600.0)
        try:
            env.reset(seed=1)
            start = time.monotonic()
            interrupt.start()
            with pytest.raises(KeyboardInterrupt):
                env.step({agent: named(0.0) for agent in env.agents})
            assert time.monotonic() - start < 3.0
        finally:
            interrupt.cancel()
            env.close()


def test_remote_env_sends_many_egos_to_the_parallel_env(toy: ToyServer) -> None:
    with pytest.raises(UsageError, match="RemoteParallelEnv"):
        RemoteEnv(toy.address, "cf", egos=2)
    assert toy.session.owner is None  # it said goodbye
