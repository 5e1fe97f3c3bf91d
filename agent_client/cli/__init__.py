"""``agent-client``: one module per command, the shared options once (`common`)."""

from agent_client.cli.main import main

__all__ = ["main"]
