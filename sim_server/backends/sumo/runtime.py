"""How SUMO runs behind `SumoBackend`: in this process (libsumo) or in a sumo / sumo-gui process.

libsumo and TraCI have the same API; each runtime here hands `SumoBackend` that API object (the
``libsumo`` module, or a `traci.Connection`) and knows how to start, reload and close its SUMO,
which exceptions it raises, and whether it may be restarted after a failure.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import IO, Any

import libsumo

from sim_server.backends.sumo.gui import GuiView, Viewer

TRACI_START_TIMEOUT_S = 60.0
"""Longest wait for a sumo / sumo-gui process to accept the TraCI connection."""
TRACI_STOP_TIMEOUT_S = 10.0
"""Longest wait for a sumo / sumo-gui process to quit once its TraCI connection is closed."""


class InProcess:
    """SUMO in this process: `libsumo` is the API object; one simulation per process."""

    name = "sumo"
    errors: tuple[type[BaseException], ...] = (libsumo.TraCIException, libsumo.FatalTraCIError)
    restarts = True

    def survives(self, error: BaseException) -> bool:
        return False  # start afresh after any failure

    def version(self) -> str:
        _, version = libsumo.simulation.getVersion()
        return str(version).removeprefix("SUMO ").strip()

    def start(self, args: list[str]) -> Any:
        libsumo.start(["sumo", *args])
        return libsumo

    def load(self, api: Any, args: list[str]) -> None:
        api.simulation.load(args)

    def ego_ready(self, api: Any, ego_id: str) -> None:
        """Called once the ego of a new episode is in the simulation (nothing to show here)."""

    def stepped(self, api: Any, ego_id: str) -> None:
        """Called after each decision's simulation steps (nothing to show here)."""

    def close(self, api: Any) -> None:
        api.close()


class OverTraci:
    """SUMO in a ``sumo`` / ``sumo-gui`` process, over a TraCI socket (a `traci.Connection`).

    With `port` it attaches to a SUMO another tool started with ``--remote-port PORT`` instead.
    """

    name = "sumo-traci"

    def __init__(
        self,
        gui: bool,
        port: int | None,
        host: str,
        binary: str | None,
        view: GuiView | None = None,
    ) -> None:
        import traci
        import traci.connection

        self._traci = traci
        # Importing libsumo rebinds traci.exceptions.TraCIException to libsumo's class, while
        # traci's connection still raises its own: catch both.
        self._refused: tuple[type[Exception], ...] = tuple(
            {traci.connection.TraCIException, traci.exceptions.TraCIException}
        )
        self.errors = (*self._refused, traci.exceptions.FatalTraCIError, OSError)
        self.gui = gui
        self.port = port
        self.host = host
        # An attached SUMO is not ours to restart, and a GUI window should stay open: reload.
        self.restarts = port is None and not gui
        self.binary = None if port is not None else binary or find_sumo_binary(gui)
        self._process: subprocess.Popen[bytes] | None = None
        self._log: IO[bytes] | None = None
        self._attached: Any = None
        self.view = view
        self._viewer = Viewer(view) if gui and view is not None else None

    def ego_ready(self, api: Any, ego_id: str) -> None:
        """Called once the ego of a new episode is in the simulation: the view follows it."""
        if self._viewer is not None:
            self._viewer.ego_ready(api, ego_id)

    def stepped(self, api: Any, ego_id: str) -> None:
        """Called after each decision's simulation steps: the view's pace and pictures."""
        if self._viewer is not None:
            self._viewer.stepped(api, ego_id)

    def attach(self) -> Any:
        """Connect to the SUMO at `port` now (it keeps running its own scenario until reset)."""
        assert self.port is not None
        self._attached = self._connect(self.port, None)
        return self._attached

    def survives(self, error: BaseException) -> bool:
        """An attached SUMO is not ours to restart: keep it unless the connection broke."""
        return self.port is not None and isinstance(error, self._refused)

    def version(self) -> str:
        if self._attached is not None:
            _, version = self._attached.getVersion()
            return str(version).removeprefix("SUMO ").strip()
        if self.binary is None:
            return "unknown"
        try:
            out = subprocess.run(
                [self.binary, "--version"], capture_output=True, text=True, timeout=30, check=False
            ).stdout
        except (OSError, subprocess.TimeoutExpired):
            return "unknown"
        first = out.splitlines()[0] if out else ""
        return first.rsplit(" ", 1)[-1] if first else "unknown"

    def start(self, args: list[str]) -> Any:
        if self.binary is None:  # (re)attach to the running SUMO, then load our scenario
            connection = self.attach()
            connection.load(args)
            return connection
        port = free_port()
        command = [self.binary, *args, *self._gui_args(), "--remote-port", str(port)]
        if self.gui and self.view is not None:  # at start only: a reload keeps the user's size
            command += self.view.sumo_args()
        self._log = tempfile.TemporaryFile()  # noqa: SIM115 - kept open while SUMO runs
        self._process = subprocess.Popen(
            command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=self._log
        )
        try:
            return self._connect(port, self._process)
        except BaseException:
            self._stop_process()
            raise

    def _connect(self, port: int, process: subprocess.Popen[bytes] | None) -> Any:
        """Connect within `TRACI_START_TIMEOUT_S`; fails at once if the process exits."""
        traci = self._traci
        deadline = time.monotonic() + TRACI_START_TIMEOUT_S
        while True:
            try:
                # One try per call: traci's own retries print to stdout and sleep 1 s.
                return traci.connect(port, numRetries=0, host=self.host, proc=process)
            except (*self._refused, traci.exceptions.FatalTraCIError) as exc:
                if process is not None and process.poll() is not None:
                    raise traci.exceptions.FatalTraCIError(
                        f"{Path(self.binary or 'sumo').name} exited with code "
                        f"{process.returncode} during start-up: {self._log_tail()}"
                    ) from exc
                if time.monotonic() >= deadline:
                    where = f"{self.host}:{port}"
                    raise traci.exceptions.FatalTraCIError(
                        f"no TraCI server at {where} within {TRACI_START_TIMEOUT_S:.0f} s"
                        + ("" if process else " (start SUMO with --remote-port first)")
                    ) from exc
                time.sleep(0.02)

    def _log_tail(self) -> str:
        if self._log is None:
            return ""
        self._log.seek(0)
        text = self._log.read().decode(errors="replace").strip()
        return " | ".join(text.splitlines()[-5:]) or "(no message)"

    def _gui_args(self) -> list[str]:
        """sumo-gui's own options, at start and at every load: without ``--start`` a reloaded
        sumo-gui waits for its Run button and answers no TraCI command until then."""
        return ["--start", "--quit-on-end"] if self.gui else []

    def load(self, api: Any, args: list[str]) -> None:
        api.load([*args, *self._gui_args()])

    def close(self, api: Any) -> None:
        self._attached = None
        try:
            api.close(wait=False)
        finally:
            self._stop_process()
            if self._viewer is not None:  # sumo-gui has written its last pictures
                self._viewer.close()

    def _stop_process(self) -> None:
        process, self._process = self._process, None
        if process is not None:  # closing TraCI makes it quit; a failed start may not: kill it
            try:
                process.wait(timeout=TRACI_STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(timeout=TRACI_STOP_TIMEOUT_S)
        if self._log is not None:
            self._log.close()
            self._log = None


def find_sumo_binary(gui: bool = False) -> str:
    """``sumo`` or ``sumo-gui`` from the eclipse-sumo wheel, $SUMO_HOME/bin or the PATH."""
    name = "sumo-gui" if gui else "sumo"
    homes = []
    with contextlib.suppress(ImportError):
        import sumo  # the eclipse-sumo wheel

        homes.append(Path(sumo.SUMO_HOME))
    if os.environ.get("SUMO_HOME"):
        homes.append(Path(os.environ["SUMO_HOME"]))
    for home in homes:
        candidate = home / "bin" / name
        if candidate.is_file() and os.access(candidate, os.X_OK):
            return str(candidate)
    found = shutil.which(name)
    if found:
        return found
    raise FileNotFoundError(f"{name} not found: install eclipse-sumo (pip install eclipse-sumo)")


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def check_display() -> None:
    """sumo-gui needs a display: say so instead of failing later (or hanging)."""
    if sys.platform.startswith(("linux", "freebsd")) and not (
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    ):
        raise ValueError(
            "sumo-gui needs a display but DISPLAY is not set: run sim-server on a desktop, over "
            "`ssh -X`, or under `xvfb-run`; without --gui the headless sumo binary is used"
        )
