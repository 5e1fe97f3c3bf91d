"""``python -m agent_client``: the ``agent-client`` program (`agent_client.cli.main`)."""

from __future__ import annotations

import sys

from agent_client.cli.main import main

if __name__ == "__main__":
    sys.exit(main())
