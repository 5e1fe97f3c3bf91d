"""The two console scripts as users run them: real processes, real SUMO, loopback."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from tests.conftest import RunningServer, sim_server

pytestmark = pytest.mark.sumo


def test_agent_client_drive_prints_one_json_object_per_episode(sumo_server: RunningServer) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "agent_client.cli.main", "drive", "--server", sumo_server.address,
         "--scenario", "cf", "--policy", "idm", "--episodes", "2", "--seed", "5", "--json"],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    episodes = [json.loads(line) for line in result.stdout.splitlines()]
    assert [e["seed"] for e in episodes] == [5, 6]
    for episode in episodes:
        assert episode["collisions"] == 0
        assert episode["reason"] == "end_of_road"
        assert 5.0 < episode["average_speed"] <= 80 / 3.6
        assert 0.0 <= episode["jerk_share_above_limit"] <= 1.0
        assert episode["ceiling_speed"] is not None
        assert episode["average_speed"] <= episode["ceiling_speed"] * 1.01


def test_agent_client_drive_human_summary(sumo_server: RunningServer) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "agent_client.cli.main", "drive", "--server", sumo_server.address,
         "--episodes", "1", "--option", "max_episode_time=5"],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "time_limit" in result.stdout
    assert "avg speed" in result.stdout and "collisions/episode" in result.stdout


def test_drive_on_the_ring_says_it_has_no_ceiling(sumo_server: RunningServer) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "agent_client.cli.main", "drive", "--server", sumo_server.address,
         "--scenario", "ring", "--episodes", "1", "--option", "max_episode_time=5"],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    totals = result.stdout.strip().splitlines()[-1]
    assert "idm on ring" in totals and "no ceiling" in totals and "nan" not in totals


def test_agent_client_reports_an_unreachable_server_clearly() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "agent_client.cli.main", "drive", "--server", "tcp://127.0.0.1:1",
         "--timeout", "0.5"],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert result.returncode == 2
    assert "no reply from tcp://127.0.0.1:1" in result.stderr


def test_sim_server_refuses_a_public_bind_without_insecure() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "sim_server.cli", "--bind", "tcp://0.0.0.0:0", "--backend", "fake"],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert result.returncode != 0
    assert "--insecure" in result.stderr


def test_sim_server_serves_ipc_and_removes_its_socket_file(tmp_path: object) -> None:
    from pathlib import Path

    path = Path(str(tmp_path)) / "bridge.sock"
    command = [
        sys.executable,
        "-m",
        "sim_server.cli",
        "--bind",
        f"ipc://{path}",
        "--backend",
        "fake",
    ]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        from tests.conftest import wait_for_line

        address = wait_for_line(process, "listening on ", 30)
        assert address == f"ipc://{path}"
        assert path.exists()
        from agent_client.envs.remote_env import RemoteEnv

        env = RemoteEnv(address, "cf", reward=lambda p, o, d: 0.0)
        env.reset(seed=1)
        env.close()
    finally:
        process.terminate()
        process.wait(timeout=10)
        process.stdout.close()  # type: ignore[union-attr]
        process.stderr.close()  # type: ignore[union-attr]
    assert process.returncode == 0
    assert not path.exists()


def test_sim_server_port_zero_gives_distinct_free_ports() -> None:
    with sim_server("--backend", "fake") as one, sim_server("--backend", "fake") as two:
        assert one.address != two.address
        assert one.address.startswith("tcp://127.0.0.1:")
