"""Simulators the learner starts for itself: one beside each sampling worker, a process of its
own or a Ray actor (``agent-client train --sampling processes|ray --simulators N``), gone with
the run however it ends."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import BridgeError
from agent_client.training import simulators
from agent_client.training.run_log import read_rows
from agent_client.training.sampling.worker import SamplingWorker, Settings
from agent_client.training.simulators import (
    OwnSimulator,
    SimulatorFailed,
    evaluation_simulator,
    welcome_of,
)
from tests.conftest import RunningServer
from tests.integration.test_ray_sampling import spec as ray_spec
from tests.integration.test_train import wait_for_episodes
from tests.integration.test_workers import alive

pytestmark = [pytest.mark.sumo, pytest.mark.slow]


def simulators_under(folder: Path) -> list[int]:
    """Live sim-server processes whose address lies under `folder` (their --bind names it)."""
    found = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            words = cmdline.read_bytes().split(b"\0")
        except OSError:
            continue
        if b"sim_server.cli" in words and any(str(folder).encode() in w for w in words):
            pid = int(cmdline.parent.name)
            if alive(pid):
                found.append(pid)
    return found


def sampling_processes_under(folder: Path) -> list[int]:
    """Live sampling worker processes (``multiprocessing`` children) of a run whose TMPDIR is
    `folder`."""
    found = []
    for environ in Path("/proc").glob("[0-9]*/environ"):
        try:
            words = environ.read_bytes().split(b"\0")
            cmdline = (environ.parent / "cmdline").read_bytes()
        except OSError:
            continue
        if b"spawn_main" in cmdline and f"TMPDIR={folder}".encode() in words:
            pid = int(environ.parent.name)
            if alive(pid):
                found.append(pid)
    return found


def wait_until_gone(folder: Path, timeout_s: float) -> None:
    """The run's simulators and sampling processes exit within `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while simulators_under(folder) or sampling_processes_under(folder):
        assert time.monotonic() < deadline, (
            f"simulators {simulators_under(folder)} or sampling processes "
            f"{sampling_processes_under(folder)} outlived the run"
        )
        time.sleep(0.2)


@pytest.fixture
def short_tmp() -> Iterator[Path]:
    """A temporary folder with a short path: Ray's sockets under it must fit AF_UNIX's 107."""
    folder = Path(tempfile.mkdtemp(prefix="avb-", dir="/tmp"))
    yield folder
    shutil.rmtree(folder, ignore_errors=True)


SAMPLING = [pytest.param("ray", marks=pytest.mark.ray), "processes"]
"""The sampling workers that start simulators of their own."""


def train(tmp_path: Path, sampling: str, *extra: str) -> subprocess.Popen[str]:
    """``agent-client train --sampling SAMPLING --simulators 2`` with its temporary files (the
    simulators' sockets) under `tmp_path`."""
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    command = [
        sys.executable, "-m", "agent_client", "train", "--sampling", sampling, "--simulators", "2",
        "--out", str(tmp_path / "run"), "--quiet", "--decision-interval", "1.0",
        "--set", "eval_every=0", "--set", "warmup_policy=idm", "--set", "checkpoint_every=1",
        *extra,
    ]  # fmt: skip
    return subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
    )


def test_an_own_simulator_serves_and_stops(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    with OwnSimulator("--backend fake") as simulator:
        assert simulator.address.startswith(f"ipc://{tmp_path}")
        env = RemoteEnv(simulator.address, "cf")
        env.reset(seed=1)
        env.close()
        assert simulators_under(tmp_path) == [simulator.process.pid]
    assert simulators_under(tmp_path) == []
    assert list(tmp_path.iterdir()) == []  # its socket's folder removed
    with pytest.raises(SimulatorFailed, match="did not start"):
        OwnSimulator("--backend nope")


def test_a_worker_whose_simulator_dies_starts_another(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    spec = replace(ray_spec(""), simulator_args="--backend fake", timeout_s=2.0)
    worker = SamplingWorker(spec, index=0, stride=1, first_seed=0)
    try:
        assert len(worker.sample(20, Settings(learning=False)).transitions) >= 20
        assert worker.simulator is not None
        first = worker.simulator.process.pid
        os.kill(first, signal.SIGKILL)
        chunk = worker.sample(20, Settings(learning=False))  # waits out one step's deadline
        assert chunk.reconnects == 1 and len(chunk.transitions) >= 20
        assert simulators_under(tmp_path) == [worker.simulator.process.pid] != [first]
    finally:
        worker.close()
    assert simulators_under(tmp_path) == []


@pytest.mark.parametrize("sampling", SAMPLING)
def test_the_workers_start_the_simulators_and_they_stop_with_the_run(
    short_tmp: Path, sampling: str
) -> None:
    tmp_path = short_tmp
    process = train(tmp_path, sampling, "--episodes", "6")
    seen: set[int] = set()
    try:
        while process.poll() is None:  # the run's simulators: 2 beside the workers, 1 here
            seen.update(simulators_under(tmp_path))
            time.sleep(0.2)
        _, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert process.returncode == 0, stderr
    assert len(seen) == 3
    assert len(read_rows(tmp_path / "run" / "episodes.csv")) == 6
    wait_until_gone(tmp_path, 30.0)


@pytest.mark.parametrize("sampling", SAMPLING)
@pytest.mark.parametrize("ending", [signal.SIGINT, signal.SIGKILL])
def test_the_simulators_do_not_outlive_a_stopped_or_killed_learner(
    short_tmp: Path, ending: signal.Signals, sampling: str
) -> None:
    tmp_path = short_tmp
    process = train(tmp_path, sampling, "--episodes", "1000")
    try:
        wait_for_episodes(tmp_path / "run" / "episodes.csv", 2, timeout_s=240)
        assert len(simulators_under(tmp_path)) == 3
        assert len(sampling_processes_under(tmp_path)) == (2 if sampling == "processes" else 0)
        process.send_signal(ending)
        process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    if ending == signal.SIGINT:  # stopped: checkpointed, as any run
        assert process.returncode == 0
        assert (tmp_path / "run" / "checkpoint.pt").exists()
    wait_until_gone(tmp_path, 60.0)


def test_a_run_without_an_evaluation_server_evaluates_on_one_of_its_own(
    fake_server: RunningServer, tmp_path: Path
) -> None:
    """`agent-client train` with nothing but a --server: the evaluations run in the background
    on a simulator the command starts (the recommended setup), which stops with the run."""
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    command = [
        sys.executable, "-m", "agent_client", "train", "--server", fake_server.address,
        "--scenario", "cf", "--out", str(tmp_path / "run"), "--episodes", "4",
        "--set", "eval_every=2", "--set", "eval_episodes=1", "--set", "eval_gate=0",
        "--set", "learner.learning_starts=50", "--set", "learner.compile=false",
    ]  # fmt: skip
    result = subprocess.run(
        command, capture_output=True, text=True, env=env, timeout=300, check=False
    )
    assert result.returncode == 0, result.stderr
    output = result.stdout + result.stderr
    assert "evaluation simulator: its own" in output
    assert "in the background on 1 evaluation server(s)" in output  # the run's own plan
    assert len(read_rows(tmp_path / "run" / "evaluations.csv")) >= 1
    assert simulators_under(tmp_path) == []


def test_an_evaluation_simulator_is_started_only_where_it_serves_as_the_training_one(
    fake_server: RunningServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    simulator, line = evaluation_simulator(fake_server.address, ["cf"], 10.0)
    assert simulator is not None and "run there in the background" in line
    try:
        assert simulators_under(tmp_path) == [simulator.process.pid]
        assert welcome_of(simulator.address, 10.0).backend == "fake"
    finally:
        simulator.close()
    # one that serves differently (what differs: tests/agent_client/training/test_simulators.py)
    monkeypatch.setattr(simulators, "serving_differently", lambda *_: "sensor range 1 here")
    simulator, line = evaluation_simulator(fake_server.address, ["cf"], 10.0)
    assert simulator is None
    assert "run on the training server" in line and "sensor range 1 here" in line
    assert simulators_under(tmp_path) == []  # the one that did not fit is gone
    # a scenario the training server lacks: nothing started, the run's own check names it
    assert evaluation_simulator(fake_server.address, ["nosuch"], 10.0) == (None, "")
    assert simulators_under(tmp_path) == []
    with pytest.raises(BridgeError):  # no answer: the run fails, as it would without
        evaluation_simulator("tcp://127.0.0.1:9", ["cf"], 0.5)
