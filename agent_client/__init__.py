"""The learner side of the bridge: Gymnasium envs over the wire (and a PettingZoo one for many
egos), drivers, a TD3 learner, evaluation and a conformance kit for servers.

This package never imports the simulator side (`sim_server`) or SUMO: only the protocol. The
names below are imported lazily, so that `agent-client --help` does not pay for gymnasium or
torch. Imported after gymnasium, the package registers ``av_bridge/Remote-v0`` with it
(`agent_client.envs.registration`).
"""

from __future__ import annotations

import importlib
import sys
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

_EXPORTS = {
    "RemoteEnv": "agent_client.envs.remote_env",
    "RemoteVectorEnv": "agent_client.envs.vector_env",
    "RemoteParallelEnv": "agent_client.envs.parallel_env",
    "connect": "agent_client.transport",
    "Channel": "agent_client.transport",
    "IDMDriver": "agent_client.drivers.idm",
    "IDMParams": "agent_client.drivers.idm",
    "load_driver": "agent_client.drivers.spec",
    "run_episode": "agent_client.drivers.episode",
    "run_checks": "agent_client.conformance",
    "BridgeError": "agent_client.errors",
    "UsageError": "agent_client.errors",
    "ServerUnavailable": "agent_client.errors",
    "ServerTimeout": "agent_client.errors",
    "ServerLost": "agent_client.errors",
    "ServerError": "agent_client.errors",
    "MalformedReply": "agent_client.errors",
    "InvalidReply": "agent_client.errors",
    "InsertionFailed": "agent_client.errors",
    "AuthenticationFailed": "agent_client.errors",
}

__all__ = [
    "AuthenticationFailed",
    "BridgeError",
    "Channel",
    "IDMDriver",
    "IDMParams",
    "InsertionFailed",
    "InvalidReply",
    "MalformedReply",
    "RemoteEnv",
    "RemoteParallelEnv",
    "RemoteVectorEnv",
    "ServerError",
    "ServerLost",
    "ServerTimeout",
    "ServerUnavailable",
    "UsageError",
    "__version__",
    "connect",
    "load_driver",
    "run_checks",
    "run_episode",
]

if TYPE_CHECKING:
    from agent_client.conformance import run_checks
    from agent_client.drivers.episode import run_episode
    from agent_client.drivers.idm import IDMDriver, IDMParams
    from agent_client.drivers.spec import load_driver
    from agent_client.envs.parallel_env import RemoteParallelEnv
    from agent_client.envs.remote_env import RemoteEnv
    from agent_client.envs.vector_env import RemoteVectorEnv
    from agent_client.errors import (
        AuthenticationFailed,
        BridgeError,
        InsertionFailed,
        InvalidReply,
        MalformedReply,
        ServerError,
        ServerLost,
        ServerTimeout,
        ServerUnavailable,
        UsageError,
    )
    from agent_client.transport import Channel, connect


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'agent_client' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


if "gymnasium" in sys.modules:  # a learner's script: make gymnasium.make("av_bridge/...") work
    importlib.import_module("agent_client.envs")
