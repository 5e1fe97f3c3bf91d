"""The Gymnasium id of `RemoteEnv`: ``gymnasium.make("av_bridge/Remote-v0", server=..., ...)``.

Gymnasium 1.x loads no plugins from installed packages' entry points (0.26-0.29 did, from the
``gymnasium.envs`` group; 1.0 removed it), so installing the package cannot register the id by
itself. It is registered when `agent_client.envs` is imported, and by ``import agent_client``
once gymnasium has been imported; ``gymnasium.make("agent_client:av_bridge/Remote-v0", ...)``
imports the package itself first, so that form needs no import at all.
"""

from __future__ import annotations

from typing import Any

import gymnasium

from agent_client.defaults import DEFAULT_SCENARIO
from protocol.transport.endpoint import DEFAULT_ADDRESS

ENV_ID = "av_bridge/Remote-v0"


def make_remote_env(
    server: str = DEFAULT_ADDRESS, scenario: str = DEFAULT_SCENARIO, **kwargs: Any
) -> Any:
    """The entry point: a `RemoteEnv` on `server` (its other arguments and the scenario
    options as keywords, e.g. ``reward="safe", action_space="hybrid", flow=1200``)."""
    from agent_client.envs.remote_env import RemoteEnv

    return RemoteEnv(server, scenario, **kwargs)


def register() -> str:
    """Register `ENV_ID` with Gymnasium (once) and return it."""
    if ENV_ID not in gymnasium.registry:
        gymnasium.register(ENV_ID, entry_point=make_remote_env)
    return ENV_ID
