"""RemoteEnv against a real sim-server subprocess running SUMO over loopback TCP."""

from __future__ import annotations

import socket
import time

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import ServerError, ServerLost, ServerTimeout
from agent_client.transport import ZmqChannel
from protocol.messages import Hello, Step, Welcome
from tests.conftest import RunningServer

pytestmark = pytest.mark.sumo


def zero_reward(prev: object, obs: object, dt: float) -> float:
    return 0.0


def test_check_env_passes_against_a_live_server(sumo_server: RunningServer) -> None:
    env = RemoteEnv(sumo_server.address, "cf", reward=zero_reward)
    try:
        check_env(env, skip_render_check=True)
    finally:
        env.close()


def test_observation_vector_and_named_observation_agree(sumo_server: RunningServer) -> None:
    env = RemoteEnv(sumo_server.address, "cflc", reward=zero_reward)
    try:
        vector, info = env.reset(seed=3)
        obs = info["observation"]
        assert vector.dtype == np.float32
        assert vector.shape == env.observation_space.shape
        assert vector[env.flatten.index("ego_speed")] == pytest.approx(obs.ego.speed, rel=1e-6)
        assert vector[env.flatten.index("ego_lane_count")] == 3
        action = {"acceleration": np.array([0.3], np.float32), "lane_change": 0}
        _, _, _, _, info = env.step(action)
        assert info["observation"].seq == 1
        assert info["observation"].action.requested_acceleration == pytest.approx(0.3)
    finally:
        env.close()


def test_same_seed_same_observations_over_the_wire(sumo_server: RunningServer) -> None:
    env = RemoteEnv(sumo_server.address, "cf", reward=zero_reward)
    try:
        streams = []
        for _ in range(2):
            vector, _ = env.reset(seed=21)
            stream = [vector]
            for _ in range(100):
                vector, *_ = env.step(
                    {"acceleration": np.array([0.2], np.float32), "lane_change": 0}
                )
                stream.append(vector)
            streams.append(np.stack(stream))
        assert np.array_equal(streams[0], streams[1])
    finally:
        env.close()


def test_step_after_the_end_needs_a_reset(sumo_server: RunningServer) -> None:
    env = RemoteEnv(sumo_server.address, "cf", reward=zero_reward, max_episode_time=0.5)
    try:
        env.reset(seed=1)
        done = False
        while not done:
            _, _, terminated, truncated, _ = env.step(
                {"acceleration": np.zeros(1), "lane_change": 0}
            )
            done = terminated or truncated
        with pytest.raises(gym.error.ResetNeeded):
            env.step({"acceleration": np.zeros(1), "lane_change": 0})
    finally:
        env.close()


def test_unknown_scenario_or_option_is_a_clear_error(sumo_server: RunningServer) -> None:
    with pytest.raises(ValueError, match="offers no scenario"):
        RemoteEnv(sumo_server.address, "mars", reward=zero_reward)
    with pytest.raises(ValueError, match="warp"):
        RemoteEnv(sumo_server.address, "cf", reward=zero_reward, warp=9)


def test_a_silent_server_gives_a_timeout_not_a_hang() -> None:
    # A bound TCP socket that never speaks ZeroMQ: connect succeeds, no reply ever comes.
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen()
        address = f"tcp://127.0.0.1:{silent.getsockname()[1]}"
        started = time.monotonic()
        with pytest.raises(ServerTimeout, match="no reply"):
            RemoteEnv(address, "cf", reward=zero_reward, timeout_s=0.5)
        assert time.monotonic() - started < 5.0


def test_a_dead_server_mid_episode_is_reported_at_once(scenario_cache: object) -> None:
    from tests.conftest import sim_server

    with sim_server("--backend", "fake") as server:
        env = RemoteEnv(server.address, "cf", reward=zero_reward, timeout_s=60.0)
        env.reset(seed=1)
        server.process.kill()
        server.process.wait(timeout=10)
        started = time.monotonic()
        with pytest.raises(ServerLost, match="lost"):
            env.step({"acceleration": np.zeros(1), "lane_change": 0})
        assert time.monotonic() - started < 5.0  # not the 60 s step timeout
        env.close()


def test_a_second_client_is_told_the_server_is_busy(sumo_server: RunningServer) -> None:
    env = RemoteEnv(sumo_server.address, "cf", reward=zero_reward)
    try:
        env.reset(seed=1)
        with ZmqChannel(sumo_server.address, timeout_s=5.0) as other:
            with pytest.raises(ServerError, match="busy"):
                other.hello()
            with pytest.raises(ServerError, match="busy"):
                other.request(Step(1, 0.0))
    finally:
        env.close()
    with ZmqChannel(sumo_server.address, timeout_s=5.0) as other:
        assert isinstance(other.request(Hello((1, 0))), Welcome)
        other.request(__import__("protocol").Close())
