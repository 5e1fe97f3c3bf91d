"""Simulators a learner starts for itself: a ``sim-server`` process on a private address.

Where Ray places a sampling worker (or an RLlib env runner), the worker starts the simulator it
drives beside it: no address to pass, none exposed (an ipc socket in a directory only this user
may enter). The server runs with ``--exit-with-parent``, so it stops with the process that
started it however that one ends (closed, killed by Ray, SIGKILL), and `OwnSimulator.close`
stops it at once. The server is another program (`sim-server`, from this environment), started
as a process: the learner imports nothing of it.
"""

from __future__ import annotations

import shlex
import shutil
import subprocess
import sys
import tempfile

from agent_client.errors import BridgeError
from protocol.readiness import LISTENING, NotReady, stop_process, wait_for_line

READY_TIMEOUT_S = 180.0
"""The longest a simulator may take to print its readiness line (SUMO builds a scenario's
network on first use)."""
DEFAULT_SIMULATOR_ARGS = "--backend sumo"


class SimulatorFailed(BridgeError):
    """A simulator this process started did not become ready."""


class OwnSimulator:
    """One ``sim-server`` started by this process for itself; `address` is where it serves."""

    def __init__(
        self, args: str = DEFAULT_SIMULATOR_ARGS, ready_timeout_s: float = READY_TIMEOUT_S
    ) -> None:
        """`args`: the sim-server command line (as one string, shell-quoted), without
        ``--bind``."""
        self._folder = tempfile.mkdtemp(prefix="av-bridge-sim-")
        command = [
            sys.executable, "-m", "sim_server.cli", *shlex.split(args),
            "--bind", f"ipc://{self._folder}/simulator", "--exit-with-parent",
        ]  # fmt: skip
        self.process = subprocess.Popen(command, stdout=subprocess.PIPE, text=True)
        try:
            self.address = wait_for_line(self.process, LISTENING, ready_timeout_s)
        except NotReady as exc:
            self.close()
            why = f"the simulator `sim-server {args}` did not start: {exc}"
            raise SimulatorFailed(why) from exc

    def close(self) -> None:
        """Stop the simulator (SIGTERM, then SIGKILL after a grace period) and remove its
        socket's directory; safe to call twice."""
        stop_process(self.process)
        shutil.rmtree(self._folder, ignore_errors=True)

    def __enter__(self) -> OwnSimulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
