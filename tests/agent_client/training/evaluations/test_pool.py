"""`EvaluationPool`: blocking evaluations by one worker process per server, against conforming
in-process servers (fake backend) reached over real loopback sockets by real worker processes."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from agent_client.drivers.idm import IDMDriver, IDMParams
from agent_client.drivers.policy import ActionScale, PolicyDriver, load_policy_driver, save_policy
from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import (
    BridgeError,
    FeatureMismatch,
    InsertionFailed,
    ServerError,
    ServerLost,
    ServerTimeout,
    ServerUnavailable,
)
from agent_client.evaluation.targets import FailureScreen
from agent_client.rl.features import FeatureMap
from agent_client.rl.lanes import LaneChoice
from agent_client.rl.td3 import Agent, TD3Config
from agent_client.training.evaluations import pool as eval_pool
from agent_client.training.evaluations.inline import EvaluationJob, Evaluator
from agent_client.training.evaluations.pool import EvaluationPool
from agent_client.training.evaluations.worker import (
    EvaluationWorkerFailed,
    Pipe,
    driver_from_message,
    driver_message,
    error_message,
    raise_error,
    serve,
)
from protocol.messages import Observation, OptionValue
from tests.agent_client.conformance.toys import ToyServer
from tests.conftest import sim_server

SEEDS = [7, 3, 11, 5, 9]
RESET_OPTIONS: dict[str, OptionValue] = {"decision_interval": 0.1}


@pytest.fixture
def servers() -> Iterator[list[ToyServer]]:
    with ToyServer() as first, ToyServer() as second:
        yield [first, second]


@pytest.fixture
def pool(servers: list[ToyServer]) -> Iterator[EvaluationPool]:
    opened = EvaluationPool([s.address for s in servers], "cf", "safe", {}, RESET_OPTIONS, 5.0)
    try:
        yield opened
    finally:
        opened.close()


def lockstep(job: EvaluationJob) -> list[dict[str, object]]:
    """The same job run by the learner's own `Evaluator` on two servers of its own (the
    reference; the pool's workers hold theirs)."""
    with ToyServer() as first, ToyServer() as second:
        envs = [RemoteEnv(s.address, "cf", reward="safe", timeout_s=5.0, decision_interval=0.1)
                for s in (first, second)]  # fmt: skip
        try:
            return [summary.to_dict() for summary in Evaluator(envs).run(job)]
        finally:
            for env in envs:
                env.close()


def test_the_workers_drive_the_same_episodes_as_the_learner_would(pool: EvaluationPool) -> None:
    idm = IDMDriver(IDMParams(T=1.2))
    summaries = pool.run(EvaluationJob("idm", idm, SEEDS))
    assert [s.seed for s in summaries] == SEEDS
    assert [s.episode for s in summaries] == list(range(len(SEEDS)))
    assert [s.to_dict() for s in summaries] == lockstep(EvaluationJob("idm", idm, SEEDS))
    # Another driver's parameters reach the workers: other episodes.
    other = pool.run(EvaluationJob("idm", IDMDriver(IDMParams(T=2.5)), SEEDS))
    assert [s.average_speed for s in other] != [s.average_speed for s in summaries]


def test_a_job_in_the_background_ends_as_the_same_job_run_at_once(
    servers: list[ToyServer],
) -> None:
    idm = IDMDriver(IDMParams(T=1.2))
    addresses = [s.address for s in servers]
    background = EvaluationPool(addresses, "cf", "safe", {}, RESET_OPTIONS, 5.0, idle_priority=True)
    try:
        if hasattr(os, "SCHED_IDLE"):  # the kernel gives its workers only CPU time left over
            assert {os.sched_getscheduler(w.process.pid) for w in background.workers} == {
                os.SCHED_IDLE
            }
        job = EvaluationJob("idm", idm, SEEDS)
        background.start(job)
        assert background.busy and background.job is job
        with pytest.raises(RuntimeError, match="already running"):
            background.start(EvaluationJob("idm", idm, SEEDS))
        polls = 0
        while not background.poll():  # never waits: the learner trains in between
            polls += 1
            time.sleep(0.001)  # the idle-priority workers get the CPU this loop leaves
        assert polls > 0, "the job was done before the learner could have trained at all"
        summaries = background.finish()
        assert not background.busy
        # Given up half-way, the pool takes the next job as if nothing had run.
        background.start(EvaluationJob("idm", idm, SEEDS))
        background.poll()
        background.cancel()
        again = background.run(EvaluationJob("idm", idm, SEEDS))
    finally:
        background.close()
    expected = lockstep(EvaluationJob("idm", idm, SEEDS))
    assert [s.to_dict() for s in summaries] == expected
    assert [s.to_dict() for s in again] == expected


@pytest.mark.parametrize("lane_change", [False, True])
def test_a_policy_drives_the_workers_as_it_drives_the_learner(
    pool: EvaluationPool, tmp_path: Path, lane_change: bool
) -> None:
    every = 10 if lane_change else 1
    features = FeatureMap("lc" if lane_change else "cf", lane_phase_every=every)
    lanes = LaneChoice(3 if lane_change else 1, every, gap_rule=lane_change)
    agent = Agent(features.dim, lanes.n_choices, TD3Config(compile=False), seed=5)
    save_policy(tmp_path / "p.pt", agent.policy_state_dict(), features, ActionScale(-6, 3), lanes)
    driver = load_policy_driver(tmp_path / "p.pt")
    message = driver_message(driver)
    again = driver_from_message(message)
    assert isinstance(again, PolicyDriver)
    assert (again.features.name, again.features.dim, again.lanes, again.scale) == (
        features.name, features.dim, lanes, ActionScale(-6, 3)
    )  # fmt: skip
    summaries = pool.run(EvaluationJob("policy", driver, SEEDS[:3]))
    assert [s.to_dict() for s in summaries] == lockstep(EvaluationJob("policy", driver, SEEDS[:3]))


def test_a_driver_a_worker_cannot_rebuild_is_refused_before_anything_runs(
    pool: EvaluationPool,
) -> None:
    class Idle:
        def act(self, obs: Observation) -> tuple[float, int]:
            return 0.0, 0

    with pytest.raises(ValueError, match=r"IDM \(\+ MOBIL\) or a policy"):
        pool.run(EvaluationJob("idle", Idle(), SEEDS))
    assert len(pool.run(EvaluationJob("idm", IDMDriver(), SEEDS[:1]))) == 1


def test_a_worker_never_imports_torch() -> None:
    """What it drives with is plain numpy: a worker starts in a fraction of a second."""
    code = "import sys, agent_client.training.evaluations.worker; print('torch' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=60, check=True)  # fmt: skip
    assert result.stdout.strip() == "False"


def test_a_screened_evaluation_stops_at_the_first_seeds_that_have_failed_for_certain(
    pool: EvaluationPool,
) -> None:
    everything = pool.run(EvaluationJob("idm", IDMDriver(), SEEDS))
    speed = sum(s.average_speed for s in everything) / len(SEEDS)
    bounds = [s.average_speed for s in everything]
    hopeless = FailureScreen(len(SEEDS), 1.05 * speed, speed_bounds=bounds)
    # In seed order: the fewest first seeds that fail whatever the others give.
    first = next(k for k in range(1, len(SEEDS)) if hopeless.failed(everything[:k], range(k, 5)))
    for _ in range(3):  # whichever worker finishes first, the same verdict and episodes
        job = EvaluationJob("idm", IDMDriver(), SEEDS, screen=hopeless)
        stopped = pool.run(job)
        assert job.stopped == "as_fast_as_idm"
        assert [s.to_dict() for s in stopped] == [s.to_dict() for s in everything[:first]]
    # The workers are ready for the next job at once: nothing of the stopped one is left over.
    assert [s.to_dict() for s in pool.run(EvaluationJob("idm", IDMDriver(), SEEDS))] == [
        s.to_dict() for s in everything
    ]


def test_a_server_that_is_not_there_is_reported_as_unavailable_and_no_worker_is_left() -> None:
    with socket.socket() as probe:  # a free port nobody listens on
        probe.bind(("127.0.0.1", 0))
        address = f"tcp://127.0.0.1:{probe.getsockname()[1]}"
    started: list[int] = []
    original = eval_pool._WorkerProcess.__init__

    def remember(self: eval_pool._WorkerProcess, address: str, write_timeout_s: float) -> None:
        original(self, address, write_timeout_s)
        started.append(self.process.pid)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(eval_pool._WorkerProcess, "__init__", remember)
        with pytest.raises(ServerUnavailable, match=address.removeprefix("tcp://")):
            EvaluationPool([address], "cf", "safe", {}, RESET_OPTIONS, 0.5)
    assert len(started) == 1
    with pytest.raises(ProcessLookupError):
        os.kill(started[0], 0)  # reaped


def test_a_worker_that_died_is_reported_as_lost_and_started_again_on_reconnect(
    pool: EvaluationPool,
) -> None:
    before = pool.run(EvaluationJob("idm", IDMDriver(), SEEDS[:2]))
    victim = pool.workers[1].process
    victim.kill()
    victim.wait(timeout=10)
    with pytest.raises(ServerLost, match="exited"):
        pool.run(EvaluationJob("idm", IDMDriver(), SEEDS))
    pool.reconnect(5.0)
    assert pool.workers[1].process.pid != victim.pid
    after = pool.run(EvaluationJob("idm", IDMDriver(), SEEDS[:2]))
    assert [s.to_dict() for s in after] == [s.to_dict() for s in before]


def test_a_silent_worker_times_out_and_is_replaced_on_reconnect(pool: EvaluationPool) -> None:
    pool.silence_s = 1.0
    frozen = pool.workers[0].process
    os.kill(frozen.pid, signal.SIGSTOP)
    try:
        with pytest.raises(ServerTimeout, match="said nothing"):
            pool.run(EvaluationJob("idm", IDMDriver(), SEEDS))
        pool.reconnect(5.0)
    finally:
        with contextlib.suppress(ProcessLookupError):  # killed and reaped: nothing to resume
            os.kill(frozen.pid, signal.SIGCONT)
    assert pool.workers[0].process.pid != frozen.pid
    assert frozen.wait(timeout=10) is not None
    assert len(pool.run(EvaluationJob("idm", IDMDriver(), SEEDS))) == len(SEEDS)


def test_a_worker_that_hangs_mid_episode_is_given_up_and_started_again(
    pool: EvaluationPool, monkeypatch: pytest.MonkeyPatch
) -> None:
    reference = pool.run(EvaluationJob("idm", IDMDriver(), SEEDS))
    monkeypatch.setattr(eval_pool, "STOP_GRACE_S", 0.5)
    pool.silence_s = 1.0
    hung = pool.workers[0]
    request = eval_pool._WorkerProcess.request

    def freeze_on_its_first_episode(self: eval_pool._WorkerProcess, message: dict) -> None:
        request(self, message)
        if self is hung and message["op"] == "episode":
            os.kill(self.process.pid, signal.SIGSTOP)  # it got the episode, and hangs in it

    monkeypatch.setattr(eval_pool._WorkerProcess, "request", freeze_on_its_first_episode)
    try:
        with pytest.raises(ServerTimeout, match="said nothing"):
            pool.run(EvaluationJob("idm", IDMDriver(), SEEDS))
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(hung.process.pid, signal.SIGCONT)
    monkeypatch.undo()
    assert hung.process.wait(timeout=10) is not None  # killed
    pool.silence_s = 30.0
    pool.reconnect(20.0)  # its server may still hold the dead worker's session a while
    assert pool.workers[0] is not hung
    again = pool.run(EvaluationJob("idm", IDMDriver(), SEEDS))
    assert [s.to_dict() for s in again] == [s.to_dict() for s in reference]


def test_errors_come_back_as_the_clients_own_exceptions() -> None:
    for error in (
        ServerError("busy", "another client holds this simulator"),
        InsertionFailed("cf", [3, 4], "insertion_failed: no room"),
        ServerLost("gone"),
        FeatureMismatch("6 features, not 7"),
        KeyError("seed"),
    ):
        message = error_message(error)
        with pytest.raises(BridgeError) as raised:
            raise_error(message, "evaluation worker for tcp://127.0.0.1:1")
        expected = type(error) if isinstance(error, BridgeError) else EvaluationWorkerFailed
        assert type(raised.value) is expected
        assert "evaluation worker for tcp://127.0.0.1:1" in str(raised.value)
        if isinstance(error, ServerError):
            assert isinstance(raised.value, ServerError) and raised.value.code == "busy"
        if isinstance(error, InsertionFailed):
            assert isinstance(raised.value, InsertionFailed) and raised.value.seeds == [3, 4]


def test_after_its_server_restarts_the_pool_reconnects_and_drives_the_same_episodes() -> None:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        address = f"direct://127.0.0.1:{probe.getsockname()[1]}"
    with sim_server("--backend", "fake", bind=address) as first:
        pool = EvaluationPool([address], "cf", "safe", {}, RESET_OPTIONS, 5.0)
        try:
            before = pool.run(EvaluationJob("idm", IDMDriver(), SEEDS[:2]))
            first.process.kill()  # the simulator dies between two evaluations
            first.process.wait(timeout=10)
            with pytest.raises(ServerUnavailable):
                pool.run(EvaluationJob("idm", IDMDriver(), SEEDS[:2]))
            with sim_server("--backend", "fake", bind=address):  # and comes back
                pool.reconnect(30.0)
                after = pool.run(EvaluationJob("idm", IDMDriver(), SEEDS[:2]))
        finally:
            pool.close()
    assert [s.to_dict() for s in after] == [s.to_dict() for s in before]


def test_a_worker_whose_first_connection_failed_connects_on_reconnect() -> None:
    """The worker's own loop, in a thread, over real pipes: ``connect`` to a server that is not
    up yet fails; once it is, ``reconnect`` connects (the learner restarts no process)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        address = f"direct://127.0.0.1:{probe.getsockname()[1]}"
    to_worker, from_learner = os.pipe()
    to_learner, from_worker = os.pipe()
    learner = Pipe(to_learner, from_learner)
    worker = threading.Thread(target=serve, args=(Pipe(to_worker, from_worker),), daemon=True)
    worker.start()
    try:
        connect = {"op": "connect", "id": 1, "address": address, "scenario": "cf",
                   "reward": "safe", "reward_params": {}, "options": {}, "timeout_s": 0.5,
                   "reset_timeout_s": 5.0}  # fmt: skip
        learner.send(connect)
        answer = learner.receive(30.0)
        assert answer is not None and (answer["op"], answer["id"]) == ("error", 1)
        assert answer["kind"] in ("timeout", "unavailable")
        with sim_server("--backend", "fake", bind=address):
            learner.send({"op": "reconnect", "id": 2, "timeout_s": 30.0})
            answer = learner.receive(60.0)
            assert answer is not None and (answer["op"], answer["id"]) == ("ready", 2), answer
            learner.send({"op": "driver", "id": 3, "kind": "idm", "params": {}})
            learner.send({"op": "episode", "id": 4, "index": 0, "seed": 7})
            answers = [learner.receive(60.0) for _ in range(2)]
    finally:
        os.close(from_learner)  # the worker sees the pipe close and returns
        worker.join(timeout=30)
        for fd in (to_learner, to_worker, from_worker):
            os.close(fd)
    assert [(a["op"], a["id"]) for a in answers if a] == [("ready", 3), ("summary", 4)]
    assert not worker.is_alive()


def test_stopping_never_raises_and_replaces_a_worker_that_answered_nonsense(
    pool: EvaluationPool, monkeypatch: pytest.MonkeyPatch
) -> None:
    broken = pool.workers[1]
    broken.request({"op": "episode", "index": 0, "seed": SEEDS[0]})
    broken.running = 0

    wait_answer = eval_pool._WorkerProcess.wait_answer

    def nonsense(self: eval_pool._WorkerProcess, timeout_s: float) -> dict:
        if self is broken:
            raise RuntimeError("a frame it could not read")
        return wait_answer(self, timeout_s)

    monkeypatch.setattr(eval_pool._WorkerProcess, "wait_answer", nonsense)
    pool._stop_running()  # no exception: the job's own outcome stands
    monkeypatch.undo()
    assert pool.workers[1] is not broken and broken.closed
    assert len(pool.run(EvaluationJob("idm", IDMDriver(), SEEDS))) == len(SEEDS)
