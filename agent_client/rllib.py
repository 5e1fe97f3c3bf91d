"""RLlib on Ray: `RemoteEnv` registered with Ray's registry, one sim-server per env.

    from agent_client import rllib
    from ray.rllib.algorithms.ppo import PPOConfig

    config = (
        PPOConfig()
        .environment(rllib.register(), env_config={"servers": [A, B], "scenario": "cf"})
        .env_runners(num_env_runners=2)
    )

``env_config`` is ``{"servers": [ADDRESS, ...], "scenario": NAME, **options}``; the options are
`RemoteEnv`'s keywords (``reward``, ``action_space``, ``timeout_s``...) and scenario options
(``decision_interval``, ``flow``...). A sim-server serves one client at a time, so every env of
every env runner needs a server (or a session of a ``sim-server --pool N``: its address may be
listed N times) of its own: env runner ``w`` (`EnvContext.worker_index`, 1..N;
0 for the local one) takes ``servers[(max(w, 1) - 1) * k + i]`` for its ``i``-th env, where ``k``
is ``env_config["envs_per_env_runner"]`` (default 1; give RLlib's ``num_envs_per_env_runner``:
RLlib hands every env of a runner the same context). A server that is busy nonetheless (an env
runner restarted while its old env still held it) makes the env try the next ones, in order,
until ``env_config["connect_timeout_s"]`` (default 60 s) has passed. CURVE keys come from
``AV_BRIDGE_SERVER_KEY`` / ``AV_BRIDGE_SECRET_KEY`` in the env runners' environment
(``runtime_env={"env_vars": ...}`` on a cluster; docs/ray.md).

Without ``servers`` every env starts a simulator of its own where its env runner runs (a
``sim-server`` on a private ipc address, ``env_config["simulator_args"]``, default ``--backend
sumo``), stopped when the env closes or its runner's process ends: nothing to start or address
beforehand, on one machine or across a cluster's nodes.

Needs ``pip install 'av-bridge[rllib]'``; importing this module imports Ray.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Mapping
from typing import Any

from ray.tune.registry import register_env

from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import ServerError, UsageError
from agent_client.training.simulators import DEFAULT_SIMULATOR_ARGS, OwnSimulator

ENV_NAME = "av_bridge_remote"
"""The name `register` gives the env in Ray's registry."""
DEFAULT_CONNECT_TIMEOUT_S = 60.0
_CONTROL_KEYS = (
    "servers", "scenario", "envs_per_env_runner", "connect_timeout_s", "num_envs", "simulator_args",
)  # fmt: skip

_created = itertools.count()
"""Envs this process has created: the index of an env within its runner."""


def register(name: str = ENV_NAME) -> str:
    """Register the env creator with Ray's registry under `name`; returns `name`."""
    register_env(name, make_env)
    return name


def make_env(config: Mapping[str, Any]) -> RemoteEnv:
    """The creator Ray calls with an `EnvContext` (a dict of ``env_config`` that also has
    ``worker_index``): a `RemoteEnv` on this env's own server."""
    servers = list(config.get("servers") or [])
    options = {k: v for k, v in config.items() if k not in _CONTROL_KEYS}
    scenario = str(config.get("scenario", "cf"))
    if not servers:
        return _with_own_simulator(
            str(config.get("simulator_args", DEFAULT_SIMULATOR_ARGS)), scenario, options
        )
    per_runner = int(config.get("envs_per_env_runner", 1))
    worker = int(getattr(config, "worker_index", 0))
    first = server_index(worker, next(_created) % per_runner, per_runner, len(servers))
    timeout_s = float(config.get("connect_timeout_s", DEFAULT_CONNECT_TIMEOUT_S))
    return connect_first_free(servers, first, scenario, options, timeout_s)


class OwnSimulatorEnv(RemoteEnv):
    """A `RemoteEnv` on a simulator it started (`OwnSimulator`), which its `close` stops."""

    simulator: OwnSimulator | None = None

    def close(self) -> None:
        try:
            super().close()
        finally:
            if self.simulator is not None:
                self.simulator.close()
                self.simulator = None


def _with_own_simulator(args: str, scenario: str, options: dict[str, Any]) -> RemoteEnv:
    simulator = OwnSimulator(args)
    try:
        env = OwnSimulatorEnv(simulator.address, scenario, **options)
    except BaseException:
        simulator.close()
        raise
    env.simulator = simulator
    return env


def server_index(worker_index: int, env_index: int, envs_per_runner: int, n_servers: int) -> int:
    """The server of env `env_index` of env runner `worker_index` (0: the local runner)."""
    return ((max(worker_index, 1) - 1) * envs_per_runner + env_index) % n_servers


def connect_first_free(
    servers: list[str], first: int, scenario: str, options: dict[str, Any], timeout_s: float
) -> RemoteEnv:
    """A `RemoteEnv` on ``servers[first]``, or on the next free one if it is busy."""
    deadline = time.monotonic() + timeout_s
    while True:
        for offset in range(len(servers)):
            address = servers[(first + offset) % len(servers)]
            try:
                return RemoteEnv(address, scenario, **options)
            except ServerError as exc:
                if exc.code != "busy":
                    raise
        if time.monotonic() >= deadline:
            raise UsageError(
                f"all {len(servers)} servers are busy: an env needs a server of its own "
                "(num_env_runners x num_envs_per_env_runner servers)"
            )
        time.sleep(1.0)
