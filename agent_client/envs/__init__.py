"""Gymnasium environments over the wire: one ego (`RemoteEnv`), several servers at once
(`RemoteVectorEnv`); importing this package registers ``av_bridge/Remote-v0`` with Gymnasium."""

from agent_client.envs.registration import ENV_ID, register
from agent_client.envs.remote_env import RemoteEnv
from agent_client.envs.vector_env import RemoteVectorEnv

register()

__all__ = ["ENV_ID", "RemoteEnv", "RemoteVectorEnv", "register"]
