"""Drive episodes through the bridge with any driver and summarise them."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Protocol

import numpy as np

from agent_client.metrics import EpisodeRecorder, EpisodeSummary
from agent_client.remote_env import RemoteEnv
from protocol.messages import Observation


class Driver(Protocol):
    """Anything that maps a named observation to (acceleration m/s^2, lane change)."""

    def act(self, obs: Observation) -> tuple[float, int]: ...


def run_episode(env: RemoteEnv, driver: Driver, seed: int, episode: int = 0) -> EpisodeSummary:
    """Drive one episode from reset to its end; returns its summary."""
    return record_episode(env, driver, seed, episode).summary()


def record_episode(env: RemoteEnv, driver: Driver, seed: int, episode: int = 0) -> EpisodeRecorder:
    """Drive one episode from reset to its end; returns every observation and reward."""
    _, info = env.reset(seed=seed)
    recorder = EpisodeRecorder(episode=episode, seed=seed, step_length=env.step_length)
    obs: Observation = info["observation"]
    recorder.add(obs)
    while True:
        acceleration, lane_change = driver.act(obs)
        action = {"acceleration": np.array([acceleration], np.float32), "lane_change": lane_change}
        _, reward, terminated, truncated, info = env.step(action)
        obs = info["observation"]
        recorder.add(obs, reward)
        if terminated or truncated:
            return recorder


def drive(
    env: RemoteEnv,
    driver: Driver,
    episodes: int,
    first_seed: int = 0,
    on_episode: Callable[[EpisodeSummary], None] | None = None,
) -> Iterator[EpisodeSummary]:
    """Drive `episodes` episodes with seeds first_seed, first_seed + 1, ..."""
    for index in range(episodes):
        summary = run_episode(env, driver, first_seed + index, index)
        if on_episode is not None:
            on_episode(summary)
        yield summary


def aggregate(summaries: list[EpisodeSummary]) -> dict[str, float]:
    """Figures over all episodes (jerk and headway shares weighted by steps)."""
    steps = np.array([s.steps for s in summaries], dtype=float)
    weights = steps / steps.sum() if steps.sum() > 0 else np.full(len(steps), 1 / len(steps))
    ratios = [s.speed_ratio_to_ceiling for s in summaries if s.speed_ratio_to_ceiling is not None]
    ttcs = [s.min_ttc for s in summaries if s.min_ttc is not None]
    return {
        "episodes": float(len(summaries)),
        "average_speed": float(np.mean([s.average_speed for s in summaries])),
        "average_speed_sd": float(np.std([s.average_speed for s in summaries])),
        "collisions_per_episode": float(np.mean([s.collisions for s in summaries])),
        "jerk_share_above_limit": float(
            np.dot(weights, [s.jerk_share_above_limit for s in summaries])
        ),
        "headway_share_below_1s": float(
            np.dot(weights, [s.headway_share_below_1s for s in summaries])
        ),
        "speed_ratio_to_ceiling": float(np.mean(ratios)) if ratios else float("nan"),
        "min_ttc": float(np.min(ttcs)) if ttcs else float("nan"),
        "total_reward": float(np.mean([s.total_reward for s in summaries])),
    }
