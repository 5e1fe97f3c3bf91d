"""The simulator side of the bridge: a server loop and simulator backends."""

from __future__ import annotations

__version__ = "0.1.0"
