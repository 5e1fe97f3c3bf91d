"""``sim-server --workers N``: N servers, one readiness line each, dead workers restarted."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

from agent_client.transport import ZmqChannel
from protocol.messages import Welcome
from sim_server.serve.workers import without_options, worker_addresses
from tests.conftest import wait_for_line


def children(pid: int) -> list[int]:
    """Live child processes of `pid` (Linux /proc)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            found.append(int(stat.parent.name))
    return found


def test_worker_addresses_and_argv() -> None:
    assert worker_addresses("tcp://127.0.0.1:6000", 3) == [
        "tcp://127.0.0.1:6000", "tcp://127.0.0.1:6001", "tcp://127.0.0.1:6002",
    ]  # fmt: skip
    assert worker_addresses("tcp://127.0.0.1:0", 2) == ["tcp://127.0.0.1:0"] * 2
    assert worker_addresses("ipc:///tmp/b", 2) == ["ipc:///tmp/b-0", "ipc:///tmp/b-1"]
    argv = ["--workers", "3", "--backend", "fake", "--bind=tcp://x:1", "--workers=2", "-v"]
    assert without_options(argv, ("--workers", "--bind")) == ["--backend", "fake", "-v"]


def test_workers_serve_and_a_killed_one_comes_back() -> None:
    command = [sys.executable, "-m", "sim_server.cli", "--backend", "fake", "--workers", "2",
               "--bind", "tcp://127.0.0.1:0"]  # fmt: skip
    supervisor = subprocess.Popen(command, stdout=subprocess.PIPE, text=True)
    try:
        addresses = [wait_for_line(supervisor, "listening on ", 60.0) for _ in range(2)]
        assert len(set(addresses)) == 2
        for address in addresses:
            with ZmqChannel(address, 10.0) as connection:
                assert isinstance(connection.hello(), Welcome)
        workers = children(supervisor.pid)
        assert len(workers) == 2
        subprocess.run(["kill", "-9", str(workers[0])], check=True, timeout=10)
        # The supervisor restarts it on the same address: a hello there is answered again.
        for address in addresses:
            with ZmqChannel(address, 30.0) as connection:
                assert isinstance(connection.hello(), Welcome)
        assert workers[0] not in children(supervisor.pid)
        assert len(children(supervisor.pid)) == 2
    finally:
        supervisor.send_signal(signal.SIGTERM)
        supervisor.wait(timeout=30)
        assert supervisor.stdout is not None
        supervisor.stdout.close()
    assert supervisor.returncode == 0
    assert children(supervisor.pid) == []


def test_workers_do_not_outlive_a_killed_supervisor() -> None:
    command = [sys.executable, "-m", "sim_server.cli", "--backend", "fake", "--workers", "2",
               "--bind", "tcp://127.0.0.1:0"]  # fmt: skip
    supervisor = subprocess.Popen(command, stdout=subprocess.PIPE, text=True)
    try:
        for _ in range(2):
            wait_for_line(supervisor, "listening on ", 60.0)
        workers = children(supervisor.pid)
        assert len(workers) == 2
    finally:
        supervisor.kill()  # SIGKILL: no chance to stop its workers itself
        supervisor.wait(timeout=30)
    deadline = time.monotonic() + 20
    while any(alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not [pid for pid in workers if alive(pid)]


def alive(pid: int) -> bool:
    """True while `pid` exists and is not a zombie."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"
