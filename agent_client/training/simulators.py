"""Simulators a learner starts for itself: a ``sim-server`` process on a private address.

Where Ray places a sampling worker (or an RLlib env runner), the worker starts the simulator it
drives beside it: no address to pass, none exposed (an ipc socket in a directory only this user
may enter). A run given no evaluation server starts one for its evaluations, in the kernel's
idle class, where it offers the run's scenarios as the training server does
(`evaluation_simulator`): they then run in the background, as the recommended setup runs them.
The server runs with ``--exit-with-parent``, so it stops with the process that started it
however that one ends (closed, killed by Ray, SIGKILL), and `OwnSimulator.close` stops it at
once. The server is another program (`sim-server`, from this environment), started as a process:
the learner imports nothing of it.
"""

from __future__ import annotations

import importlib.util
import shlex
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Sequence

from agent_client.envs.link import open_channel, say_goodbye
from agent_client.errors import BridgeError
from protocol.messages import Welcome
from protocol.readiness import LISTENING, NotReady, stop_process, wait_for_line
from protocol.transport.security import ClientCredentials

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


EVALUATION_BACKENDS = ("sumo", "highway", "fake")
"""The backends whose scenarios a simulator started here can offer as the user's server does
(a replay needs its recording; a ``--sumocfg`` network shows as a scenario only that server
has, and is caught by the comparison)."""


def evaluation_simulator(
    server: str, scenarios: Sequence[str], timeout_s: float, idle: bool = True
) -> tuple[OwnSimulator | None, str]:
    """A simulator of its own for a run's evaluations (with `idle`, in the kernel's idle
    class), where it offers `scenarios` as the training `server` does (the server and backend
    and their versions, the protocol, the scenarios with their options, the action bounds and
    the sensor range); else None. Either way, a line that says where the evaluations will run
    ("" where the training server itself does not offer `scenarios`: the run's own check says
    so). A training server that does not answer raises, as the run would."""
    inline = "evaluation simulator: none of its own, the evaluations run on the training server"
    if importlib.util.find_spec("sim_server") is None:
        return None, f"{inline} (sim-server is not installed here)"
    if ClientCredentials.from_environment() is not None:
        return None, f"{inline} (the run has CURVE keys, which a simulator of its own lacks)"
    training = welcome_of(server, timeout_s)  # a server that does not answer fails the run
    if not {info.name for info in training.scenarios} >= set(scenarios):
        return None, ""
    if training.backend not in EVALUATION_BACKENDS:
        return None, f"{inline} (no simulator of backend {training.backend!r} can start here)"
    args = f"--backend {training.backend}" + (" --idle-priority" if idle else "")
    try:
        simulator = OwnSimulator(args)
    except SimulatorFailed as exc:
        return None, f"{inline} ({exc})"
    try:
        own = welcome_of(simulator.address, timeout_s)
        difference = serving_differently(training, own, scenarios)
    except BridgeError as exc:
        difference = str(exc)
    except BaseException:
        simulator.close()
        raise
    if difference:
        simulator.close()
        return None, f"{inline} (a simulator started here differs from {server}: {difference})"
    return simulator, (
        f"evaluation simulator: its own (sim-server {args}), the evaluations run there"
        + (" in the background" if idle else "")
        + " (--eval-server ADDRESS chooses one, --inline-evaluations keeps them on the training "
        "server)"
    )


def welcome_of(address: str, timeout_s: float) -> Welcome:
    """The welcome of the server at `address` (a handshake, then goodbye: it stays free)."""
    channel = open_channel(address, timeout_s, None, None)
    try:
        return channel.hello(timeout_s)
    finally:
        say_goodbye(channel)


def serving_differently(training: Welcome, own: Welcome, scenarios: Sequence[str]) -> str:
    """ "" where `own` serves `scenarios` as `training` does, else the first difference."""
    for what, theirs, ours in (
        ("server", training.server, own.server),
        ("backend", training.backend, own.backend),
        ("backend version", training.backend_version, own.backend_version),
        ("protocol", training.protocol, own.protocol),
        ("action bounds", training.action, own.action),
        ("sensor range", training.sensor_range, own.sensor_range),
    ):
        if theirs != ours:
            return f"{what} {ours} here, {theirs} there"
    offered = {info.name: info for info in training.scenarios}
    mine = {info.name: info for info in own.scenarios}
    for name in scenarios:
        if name not in mine:
            return f"scenario {name!r} is not offered here"
        if mine[name] != offered.get(name):
            return f"scenario {name!r} has other options or another step length here"
    return ""
