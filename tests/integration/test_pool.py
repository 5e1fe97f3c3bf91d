"""``sim-server --pool N``: one address, N real SUMO simulators, a session each."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from agent_client.conformance.checks import PASS, run_checks
from agent_client.envs import register
from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import ServerError
from agent_client.transport import ZmqChannel
from protocol.messages import Welcome
from tests.agent_client.conformance.test_checks import CHECKS
from tests.conftest import RunningServer, sim_server, wait_for_line
from tests.integration.test_workers import alive, children

pytestmark = [pytest.mark.sumo]


@pytest.fixture(scope="module")
def pool(scenario_cache: Path) -> Iterator[RunningServer]:
    with sim_server(
        "--backend", "sumo", "--pool", "2", cache_dir=scenario_cache, ready_timeout_s=180
    ) as server:
        yield server


def drive(env: RemoteEnv, steps: int) -> int:
    """`steps` steps of a constant action (new episodes as they end); the steps it drove."""
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(
            np.zeros(env.action_space.shape or (1,), np.float32)
        )
        if terminated or truncated:
            env.reset()
    return steps


def test_two_clients_drive_at_once_and_a_third_is_told_the_pool_is_full(
    pool: RunningServer,
) -> None:
    first, second = RemoteEnv(pool.address, "cf"), RemoteEnv(pool.address, "cf")
    try:
        one, _ = first.reset(seed=11)
        two, _ = second.reset(seed=11)
        np.testing.assert_array_equal(one, two)  # the same seed on two simulators
        for _ in range(30):  # interleaved: neither waits for the other's episode
            drive(first, 1), drive(second, 1)
        with pytest.raises(ServerError) as refused:
            RemoteEnv(pool.address, "cf")
        assert refused.value.code == "busy" and "all 2 simulators" in str(refused.value)
        first.close()  # close frees its simulator at once
        third = RemoteEnv(pool.address, "cf")
        try:
            third.reset(seed=3)
            assert drive(third, 5) == 5 and drive(second, 5) == 5
        finally:
            third.close()
    finally:
        first.close()
        second.close()


def test_a_client_that_vanishes_frees_its_simulator_at_once(pool: RunningServer) -> None:
    with ZmqChannel(pool.address, 10.0) as keeper:
        assert isinstance(keeper.hello(), Welcome)
        vanished = ZmqChannel(pool.address, 10.0)
        assert isinstance(vanished.hello(), Welcome)
        vanished.close()  # no close message: the connection just goes
        deadline = time.monotonic() + 20
        refusals: list[str] = []
        while True:  # ZeroMQ reports the closed connection within a moment
            try:
                with ZmqChannel(pool.address, 10.0) as newcomer:
                    assert isinstance(newcomer.hello(), Welcome)
                break
            except ServerError as exc:
                refusals.append(exc.code)
            assert time.monotonic() < deadline, refusals
        assert set(refusals) <= {"busy"}


def test_a_client_whose_simulator_was_taken_over_is_told_busy() -> None:
    # Two idle sessions past the session timeout: a third client takes one of them over.
    with sim_server("--backend", "fake", "--pool", "2", "--session-timeout", "1") as server:
        first, second = RemoteEnv(server.address, "cf"), RemoteEnv(server.address, "cf")
        try:
            for env in (first, second):
                env.reset(seed=1)
            time.sleep(1.5)  # silent, still connected, past the timeout
            third = RemoteEnv(server.address, "cf")
            third.reset(seed=2)
            outcomes = []
            for env in (first, second):
                try:
                    drive(env, 1)
                    outcomes.append("drove")
                except ServerError as exc:
                    outcomes.append(exc.code)
            assert sorted(outcomes) == ["busy", "drove"]
            assert drive(third, 3) == 3
            third.close()
        finally:
            first.close()
            second.close()


def test_check_env_passes_on_an_env_from_gymnasium_make(pool: RunningServer) -> None:
    # The checker makes a second env from the spec for its determinism check: the pool's second
    # simulator serves it while the first env holds the first.
    env = gymnasium.make(register(), server=pool.address, scenario="cf")
    try:
        check_env(env.unwrapped, skip_render_check=True)
    finally:
        env.close()


def test_the_pool_conforms_session_by_session(pool: RunningServer) -> None:
    report = run_checks(pool.address, "cf", timeout_s=30.0)
    statuses = {result.name: result.status for result in report.results}
    assert statuses == dict.fromkeys(CHECKS, PASS), report.format_table()
    ownership = next(r for r in report.results if r.name == "ownership")
    assert "welcomed beside the first" in ownership.detail


def test_a_simulator_that_dies_ends_its_episode_only(scenario_cache: Path) -> None:
    with sim_server(
        "--backend", "sumo", "--pool", "2", cache_dir=scenario_cache, ready_timeout_s=180
    ) as server:
        envs = [RemoteEnv(server.address, "cf"), RemoteEnv(server.address, "cf")]
        try:
            for env in envs:
                env.reset(seed=5)
                drive(env, 3)
            simulators = children(server.process.pid)
            assert len(simulators) == 2
            os.kill(simulators[0], signal.SIGKILL)
            failed, errors = [], []
            for env in envs:
                try:
                    drive(env, 20)
                except ServerError as exc:
                    failed.append(env)
                    errors.append((exc.code, "exited" in str(exc)))
            assert errors == [("simulator_error", True)]  # the other session went on
            failed[0].reset(seed=6)  # placed on a simulator again (restarted, or free)
            assert drive(failed[0], 10) == 10 and drive(envs[0], 5) == 5
            deadline = time.monotonic() + 60
            while len(children(server.process.pid)) != 2:  # the dead one was replaced
                assert time.monotonic() < deadline
                time.sleep(0.2)
        finally:
            for env in envs:
                env.close()


def test_the_simulators_do_not_outlive_a_killed_pool(scenario_cache: Path) -> None:
    command = [sys.executable, "-m", "sim_server.cli", "--backend", "fake", "--pool", "2",
               "--bind", "tcp://127.0.0.1:0"]  # fmt: skip
    front = subprocess.Popen(command, stdout=subprocess.PIPE, text=True)
    try:
        wait_for_line(front, "listening on ", 60.0)
        simulators = children(front.pid)
        assert len(simulators) == 2
    finally:
        front.kill()  # SIGKILL: no chance to stop its simulators itself
        front.wait(timeout=30)
        assert front.stdout is not None
        front.stdout.close()
    deadline = time.monotonic() + 20
    while any(alive(pid) for pid in simulators):
        assert time.monotonic() < deadline, "a simulator outlived its pool"
        time.sleep(0.2)
