"""``sim-server --workers N``: N simulator servers on consecutive ports, under one supervisor.

libsumo runs one simulation per process, so parallel simulation means parallel processes. The
supervisor starts N ordinary ``sim-server`` processes (same options, one address each), prints
their readiness lines once all of them accept requests, restarts a worker that dies on the
address it had (a learner with ``--retry-for`` then simply reconnects), and stops them all on
SIGTERM or Ctrl-C.
"""

from __future__ import annotations

import logging
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from types import FrameType

from protocol.readiness import LISTENING, NotReady, format_listening, wait_for_line
from protocol.transport.endpoint import Endpoint, parse_endpoint

log = logging.getLogger("sim_server")

READY_TIMEOUT_S = 120.0
CHECK_INTERVAL_S = 0.5
STOP_TIMEOUT_S = 15.0


def worker_addresses(bind: str, count: int) -> list[str]:
    """`count` addresses from one: consecutive tcp ports (port 0: a free port each), or ipc paths
    with a ``-i`` suffix."""
    endpoint = parse_endpoint(bind)
    if endpoint.scheme == "ipc":
        return [f"ipc://{endpoint.path}-{i}" for i in range(count)]
    if endpoint.port and endpoint.port + count - 1 > 65535:
        raise ValueError(f"{count} workers from port {endpoint.port} run past port 65535")
    return [
        str(Endpoint(endpoint.scheme, endpoint.host, endpoint.port + i if endpoint.port else 0))
        for i in range(count)
    ]


def without_options(argv: list[str], names: tuple[str, ...]) -> list[str]:
    """`argv` minus the given options and their values (``--name value`` or ``--name=value``)."""
    kept: list[str] = []
    skip = False
    for arg in argv:
        if skip:
            skip = False
        elif arg in names:
            skip = True
        elif not arg.startswith(tuple(f"{name}=" for name in names)):
            kept.append(arg)
    return kept


@dataclass
class Worker:
    """One supervised sim-server process."""

    index: int
    address: str
    process: subprocess.Popen[str] | None = None
    restarts: int = 0
    ready: bool = False
    """Printed its readiness line and has not exited since (as far as the supervisor saw)."""


class Supervisor:
    """Starts, watches and stops the workers."""

    def __init__(
        self, worker_argv: list[str], addresses: list[str], env: dict[str, str] | None = None
    ) -> None:
        self.worker_argv = worker_argv
        self.env = env
        self.workers = [Worker(i, address) for i, address in enumerate(addresses)]
        self._stop = threading.Event()

    def start(self) -> None:
        """Start every worker; return once each printed its readiness line (or raise)."""
        for worker in self.workers:
            self._spawn(worker)
        for worker in self.workers:
            worker.address = self._wait_ready(worker)

    def _spawn(self, worker: Worker) -> None:
        command = [sys.executable, "-m", "sim_server.cli", *self.worker_argv]
        worker.ready = False
        worker.process = subprocess.Popen(
            [*command, "--bind", worker.address, "--exit-with-parent"],
            stdout=subprocess.PIPE,
            text=True,
            env=self.env,
        )

    def _wait_ready(self, worker: Worker) -> str:
        assert worker.process is not None
        try:
            address = wait_for_line(worker.process, LISTENING, READY_TIMEOUT_S)
            worker.ready = True
            return address
        except NotReady as exc:
            raise RuntimeError(
                f"worker {worker.index} ({worker.address}) did not become ready ({exc}); "
                "see its log above"
            ) from exc

    def supervise(self) -> None:
        """Until `stop`: restart any worker that exits, on the same address."""
        while not self._stop.wait(CHECK_INTERVAL_S):
            for worker in self.workers:
                assert worker.process is not None
                status = worker.process.poll()
                if status is None or self._stop.is_set():
                    continue
                worker.ready = False
                log.warning(
                    "worker %d (%s) exited with status %s; restarting it",
                    worker.index,
                    worker.address,
                    status,
                )
                self._close_pipe(worker)
                worker.restarts += 1
                self._spawn(worker)
                try:
                    self._wait_ready(worker)
                except RuntimeError as exc:
                    log.error("%s", exc)

    def stop(self) -> None:
        self._stop.set()

    @property
    def stopping(self) -> bool:
        """`stop` was called (a signal during `start` is seen here once it returns)."""
        return self._stop.is_set()

    def shutdown(self) -> None:
        """SIGTERM every worker, then SIGKILL the ones still running after a grace period."""
        running = [w.process for w in self.workers if w.process and w.process.poll() is None]
        for process in running:
            process.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + STOP_TIMEOUT_S
        for process in running:
            try:
                process.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(timeout=STOP_TIMEOUT_S)
        for worker in self.workers:
            self._close_pipe(worker)

    @staticmethod
    def _close_pipe(worker: Worker) -> None:
        if worker.process is not None and worker.process.stdout is not None:
            worker.process.stdout.close()


def run_workers(argv: list[str], addresses: list[str]) -> int:
    """The ``--workers`` mode of the CLI: one worker on each of `addresses` (from
    `worker_addresses`); `argv` is the command line it was given."""
    supervisor = Supervisor(without_options(argv, ("--workers", "--bind")), addresses)

    def on_signal(signum: int, frame: FrameType | None) -> None:
        supervisor.stop()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    try:
        supervisor.start()
        for worker in supervisor.workers:
            print(format_listening(parse_endpoint(worker.address)), flush=True)
        log.info("%d workers ready; restarting any that exits", len(addresses))
        supervisor.supervise()
    except RuntimeError as exc:
        print(f"sim-server: {exc}", file=sys.stderr)
        return 1
    finally:
        supervisor.shutdown()
    return 0
