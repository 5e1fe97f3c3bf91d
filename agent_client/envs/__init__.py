"""Gymnasium environments over the wire: one ego (`RemoteEnv`), several servers at once
(`RemoteVectorEnv`)."""

from agent_client.envs.remote_env import RemoteEnv
from agent_client.envs.vector_env import RemoteVectorEnv

__all__ = ["RemoteEnv", "RemoteVectorEnv"]
