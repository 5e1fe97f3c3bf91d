"""``agent-client check`` against real server processes: the SUMO server and the fake backend."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from agent_client.conformance.checks import PASS, run_checks
from agent_client.transport import ZmqChannel
from protocol.messages import Close, Hello, Observation, Reset, Step, Welcome
from protocol.version import PROTOCOL_VERSION
from tests.agent_client.conformance.test_checks import CHECKS
from tests.conftest import RunningServer, sim_server


def assert_free(address: str) -> None:
    """Another client can start an episode right away: the kit said goodbye."""
    with ZmqChannel(address, timeout_s=30.0) as connection:
        connection.request(Hello(PROTOCOL_VERSION))
        assert isinstance(connection.request(Reset("cf", 1), timeout_s=120.0), Observation)
        connection.request(Close())


@pytest.mark.sumo
def test_the_sumo_server_conforms(sumo_server: RunningServer) -> None:
    for scenario in ("cf", "cflc", "ring"):
        report = run_checks(sumo_server.address, scenario, timeout_s=30.0)
        assert {r.name: r.status for r in report.results} == dict.fromkeys(CHECKS, PASS), (
            report.format_table()
        )
    assert_free(sumo_server.address)
    assert sumo_server.process.poll() is None


@pytest.mark.sumo
def test_check_command_against_the_sumo_server(sumo_server: RunningServer) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "agent_client.cli.main", "check", "--server", sumo_server.address,
         "--json", "--timeout", "30"],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout + result.stderr
    report = json.loads(result.stdout)
    assert report["ok"] is True
    assert report["scenario"] == "cf"  # the first one offered
    assert [c["status"] for c in report["checks"]] == [PASS] * len(CHECKS)


def test_the_fake_backend_conforms() -> None:
    with sim_server("--backend", "fake") as server:
        result = subprocess.run(
            [sys.executable, "-m", "agent_client.cli.main", "check", "--server", server.address],
            capture_output=True, text=True, timeout=120, check=False,
        )  # fmt: skip
        assert result.returncode == 0, result.stdout + result.stderr
        assert f"CONFORMS - {len(CHECKS)} passed, 0 warnings, 0 failed, 0 skipped" in result.stdout
        assert_free(server.address)


def test_check_command_reports_an_unreachable_server() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "agent_client.cli.main", "check", "--server", "tcp://127.0.0.1:1",
         "--timeout", "0.5"],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert result.returncode == 2
    assert "no reply from tcp://127.0.0.1:1 within 0.5 s" in result.stderr
    assert result.stdout == ""


@pytest.mark.parametrize("version", [(1, 0), (1, 1)])
def test_a_client_of_an_older_minor_version_drives_an_episode(version: tuple[int, int]) -> None:
    """Protocol 1.2 added no key and kept every reply a 1.0/1.1 client reads."""
    with sim_server("--backend", "fake") as server, ZmqChannel(server.address, 30.0) as old:
        welcome = old.request(Hello(version, "a 1.x client"))
        assert isinstance(welcome, Welcome) and welcome.protocol == PROTOCOL_VERSION
        assert all(s.step_length for s in welcome.scenarios)
        assert isinstance(old.request(Reset("cf", 1), timeout_s=120.0), Observation)
        for seq in range(1, 4):
            obs = old.request(Step(seq, 0.0))
            assert isinstance(obs, Observation) and obs.seq == seq
        old.request(Close())
