"""Shared fixtures: real `sim-server` subprocesses on free loopback ports."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest

from protocol import readiness

READY_TIMEOUT_S = 60.0


def pytest_configure(config: pytest.Config) -> None:
    """Ctrl-C reaches the tests, and the processes they start, even where pytest was started
    with SIGINT ignored (a background job of a non-interactive shell, `cmd &`): the tests of
    Ctrl-C send it themselves, and a child inherits an ignored SIGINT but not a handler."""
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


@dataclass
class RunningServer:
    """A sim-server subprocess and the address it printed."""

    process: subprocess.Popen[str]
    address: str


def wait_for_line(process: subprocess.Popen[str], prefix: str, timeout_s: float) -> str:
    """Read stdout until a line starting with `prefix` (the readiness signal), or kill and fail."""
    try:
        return readiness.wait_for_line(process, prefix, timeout_s)
    except readiness.NotReady as exc:
        process.kill()
        process.wait(timeout=10)
        raise RuntimeError(f"sim-server did not print {prefix!r}: {exc}") from exc


@contextmanager
def sim_server(
    *args: str,
    cache_dir: Path | None = None,
    bind: str = "tcp://127.0.0.1:0",
    ready_timeout_s: float = READY_TIMEOUT_S,
) -> Iterator[RunningServer]:
    """Start `sim-server --bind BIND ARGS`, wait for readiness, always clean up."""
    env = dict(os.environ)
    if cache_dir is not None:
        env["XDG_CACHE_HOME"] = str(cache_dir)
    command = [sys.executable, "-m", "sim_server.cli", "--bind", bind, *args]
    # stderr goes to a file: an unread pipe fills up and blocks a chatty server.
    with tempfile.TemporaryFile(mode="w+") as log:
        process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=log, text=True, env=env)
        try:
            address = wait_for_line(process, "listening on ", ready_timeout_s)
            yield RunningServer(process, address)
        finally:
            readiness.stop_process(process)


@pytest.fixture(scope="session")
def scenario_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One scenario cache for the whole run (netconvert runs once per scenario)."""
    return tmp_path_factory.mktemp("xdg-cache")


@pytest.fixture(scope="module")
def sumo_server(scenario_cache: Path) -> Iterator[RunningServer]:
    """A real SUMO server for a test module."""
    with sim_server("--backend", "sumo", cache_dir=scenario_cache) as server:
        yield server


@pytest.fixture
def fake_server() -> Iterator[RunningServer]:
    """A server process with the kinematic fake backend (fast)."""
    with sim_server("--backend", "fake") as server:
        yield server


@pytest.fixture(scope="module")
def local_ray() -> Iterator[None]:
    """A local Ray for a test module: 3 logical CPUs, bound to 127.0.0.1, no dashboard."""
    ray = pytest.importorskip("ray")
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")  # loopback, not the host IP
    ray.init(num_cpus=3, include_dashboard=False, log_to_driver=False)
    try:
        yield
    finally:
        ray.shutdown()
