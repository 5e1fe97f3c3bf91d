"""The learner side of the bridge: a Gymnasium env over the wire, drivers and a DDPG learner.

This package never imports the simulator side (`sim_server`) or SUMO: only the protocol.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

__all__ = ["RemoteEnv", "__version__"]

if TYPE_CHECKING:
    from agent_client.remote_env import RemoteEnv


def __getattr__(name: str) -> Any:
    # Lazy, so that `agent-client --help` does not pay for gymnasium (and later torch).
    if name == "RemoteEnv":
        from agent_client.remote_env import RemoteEnv

        return RemoteEnv
    raise AttributeError(name)
