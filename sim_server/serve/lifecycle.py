"""Stopping a serving loop: from a signal, another thread, or the death of the parent process."""

from __future__ import annotations

import logging
import os
import threading


class StopFlag:
    """`stop` from signal handlers or other threads; the serving loop watches `stopping`."""

    def __init__(self) -> None:
        self._stop = threading.Event()

    def stop(self) -> None:
        """Ask the loop to return (safe from signal handlers and other threads)."""
        self._stop.set()

    @property
    def stopping(self) -> threading.Event:
        """Set once `stop` was called."""
        return self._stop


def stop_with_parent(server: StopFlag, check_interval_s: float = 0.5) -> None:
    """Stop `server` once this process's parent is gone (the process is re-parented)."""
    parent = os.getppid()

    def watch() -> None:
        while not server.stopping.wait(check_interval_s):
            if os.getppid() != parent:
                logging.getLogger("sim_server").warning("parent %d is gone; stopping", parent)
                server.stop()
                return

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()
