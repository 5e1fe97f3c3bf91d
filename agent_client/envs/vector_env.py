"""`RemoteVectorEnv`: N remote simulators stepped at once, as one Gymnasium vector environment.

libsumo runs one simulation per process, so more simulation means more servers
(`sim-server --workers N`, or servers on other hosts). Each step sends one request to every
server and only then waits for the replies, so the servers simulate in parallel while the
learner waits once. Episodes reset automatically in the same step (Gymnasium's ``SAME_STEP``
autoreset): the observation returned for a finished environment is the first of its next
episode, and the last one of the finished episode is in ``info["final_obs"]``.

Actions follow the `RemoteEnv` action space chosen with ``action_space`` (the same for every
server): a batch of that space, or the named form ``{"acceleration": (N, 1), "lane_change": (N,)}``
in m/s².
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from agent_client.defaults import DEFAULT_SCENARIO, RESET_TIMEOUT_S, STEP_TIMEOUT_S
from agent_client.envs.remote_env import RemoteEnv, RewardFn
from agent_client.envs.spaces import DEFAULT_ACCELERATION_LEVELS, decode_named_batch
from protocol.messages import OptionValue
from protocol.transport.security import ClientCredentials


class RemoteVectorEnv(VectorEnv):  # type: ignore[type-arg]
    """One `RemoteEnv` per server address, stepped concurrently."""

    metadata: dict[str, Any] = {"autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(
        self,
        addresses: Sequence[str],
        scenario: str | Sequence[str] = DEFAULT_SCENARIO,
        *,
        reward: str | RewardFn = "safe",
        timeout_s: float = STEP_TIMEOUT_S,
        reset_timeout_s: float = RESET_TIMEOUT_S,
        credentials: ClientCredentials | None = None,
        action_space: str = "auto",
        acceleration_levels: int = DEFAULT_ACCELERATION_LEVELS,
        **options: OptionValue,
    ) -> None:
        """One `RemoteEnv` per address, all with the same scenario, reward, action space (see
        `RemoteEnv`) and options. An address may repeat where it serves a pool (``sim-server
        --pool N``: one session per env); a single server refuses the second as busy."""
        if not addresses:
            raise ValueError("RemoteVectorEnv needs at least one server address")
        self.envs: list[RemoteEnv] = []
        try:
            for address in addresses:
                self.envs.append(
                    RemoteEnv(
                        address,
                        scenario,
                        reward=reward,
                        timeout_s=timeout_s,
                        reset_timeout_s=reset_timeout_s,
                        credentials=credentials,
                        action_space=action_space,
                        acceleration_levels=acceleration_levels,
                        recorder=None,
                        **options,
                    )
                )
        except Exception:
            self.close()
            raise
        first = self.envs[0]
        if any(env.flatten.names != first.flatten.names for env in self.envs):
            self.close()
            raise ValueError("the servers announce different observation schemas")
        self.num_envs = len(self.envs)
        self.single_observation_space = first.observation_space
        self.observation_space = batch_space(first.observation_space, self.num_envs)

    # The action space is the first environment's, fixed when it is first asked for (with
    # "auto", by the lane count of the first observation: `RemoteEnv.action_encoding`).

    @property  # type: ignore[override]
    def single_action_space(self) -> spaces.Space[Any]:
        return self.envs[0].action_space

    @single_action_space.setter
    def single_action_space(self, space: spaces.Space[Any]) -> None:
        raise AttributeError("choose the action space with RemoteVectorEnv(action_space=NAME)")

    @property  # type: ignore[override]
    def action_space(self) -> spaces.Space[Any]:
        return batch_space(self.single_action_space, self.num_envs)

    @action_space.setter
    def action_space(self, space: spaces.Space[Any]) -> None:
        raise AttributeError("choose the action space with RemoteVectorEnv(action_space=NAME)")

    @property
    def addresses(self) -> list[str]:
        return [env.address for env in self.envs]

    def reset(
        self,
        *,
        seed: int | list[int | None] | None = None,
        options: dict[str, Any] | None = None,
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset every environment; an int seed gives environment i the seed `seed + i`."""
        seeds = _seeds(seed, self.num_envs)
        for env, env_seed in zip(self.envs, seeds, strict=True):
            env.send_reset(seed=env_seed, options=options)
        results = [env.receive_reset() for env in self.envs]
        observations = np.stack([vector for vector, _ in results])
        return observations, {"observation": [info["observation"] for _, info in results]}

    def step(
        self, actions: Any
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step all environments at once; finished ones start their next episode."""
        if isinstance(actions, Mapping):
            accelerations, lanes = decode_named_batch(actions, self.num_envs)
        else:
            accelerations, lanes = self.envs[0].action_encoding.decode_batch(actions, self.num_envs)
        results = self.step_each(accelerations, lanes)
        observations = np.stack([r[0] for r in results])
        rewards = np.array([r[1] for r in results], dtype=np.float64)
        terminated = np.array([r[2] for r in results], dtype=bool)
        truncated = np.array([r[3] for r in results], dtype=bool)
        infos: dict[str, Any] = {"observation": [r[4]["observation"] for r in results]}
        done = terminated | truncated
        if done.any():
            infos["final_obs"] = np.where(done[:, None], observations, 0.0)
            infos["final_observation"] = list(infos["observation"])
            infos["_final_obs"] = done
            restarted = self.reset_each({i: None for i in range(self.num_envs) if done[i]})
            for i, (vector, info) in restarted.items():
                observations[i] = vector
                infos["observation"][i] = info["observation"]
        return observations, rewards, terminated, truncated, infos

    def step_each(
        self, accelerations: Sequence[float] | np.ndarray, lane_changes: Sequence[int] | np.ndarray
    ) -> list[tuple[np.ndarray, float, bool, bool, dict[str, Any]]]:
        """One step of every environment, no autoreset: `RemoteEnv.step` results in order."""
        for env, acceleration, lane in zip(self.envs, accelerations, lane_changes, strict=True):
            env.send_command(float(acceleration), int(lane))
        return [env.receive_step() for env in self.envs]

    def reset_each(
        self, seeds: dict[int, int | None]
    ) -> dict[int, tuple[np.ndarray, dict[str, Any]]]:
        """Reset the environments named by index, each with its seed, at once."""
        for i, seed in seeds.items():
            self.envs[i].send_reset(seed=seed)
        return {i: self.envs[i].receive_reset() for i in seeds}

    def close_extras(self, **kwargs: Any) -> None:
        for env in getattr(self, "envs", []):
            env.close()


def _seeds(seed: int | list[int | None] | None, n: int) -> list[int | None]:
    if seed is None:
        return [None] * n
    if isinstance(seed, int):
        return [seed + i for i in range(n)]
    if len(seed) != n:
        raise ValueError(f"{len(seed)} seeds for {n} environments")
    return list(seed)
