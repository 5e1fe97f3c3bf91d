"""CURVE authentication over real processes: keygen, an authenticated server, refused clients."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from agent_client.errors import AuthenticationFailed
from agent_client.transport import ZmqChannel
from protocol.messages import Observation, Reset, Step, Welcome
from protocol.transport.security import ClientCredentials
from tests.conftest import sim_server


def keygen(directory: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "sim_server.cli", "keygen", "--out", str(directory)],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip


@pytest.fixture(scope="module")
def keys(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("keys")
    made = keygen(directory)
    assert made.returncode == 0, made.stderr
    return directory


def credentials(directory: Path) -> ClientCredentials:
    return ClientCredentials.from_files(directory / "server.key", directory / "client.key_secret")


def test_keygen_writes_two_key_pairs_and_never_overwrites(keys: Path) -> None:
    names = sorted(p.name for p in keys.iterdir())
    assert names == ["client.key", "client.key_secret", "server.key", "server.key_secret"]
    assert (keys / "server.key_secret").stat().st_mode & 0o077 == 0
    again = keygen(keys)
    assert again.returncode == 1 and "not overwriting" in again.stderr


def test_an_authorised_client_runs_an_episode(keys: Path) -> None:
    with (
        sim_server("--backend", "fake", "--secret-key", str(keys / "server.key_secret")) as server,
        ZmqChannel(server.address, 5.0, credentials(keys)) as connection,
    ):
        assert isinstance(connection.hello(), Welcome)
        connection.request(Reset("cf", 1))
        assert isinstance(connection.request(Step(1, 0.5)), Observation)


def test_clients_without_the_right_keys_are_refused_before_the_protocol(
    keys: Path, tmp_path: Path
) -> None:
    assert keygen(tmp_path / "other").returncode == 0
    stranger = credentials(tmp_path / "other")  # a key pair the server never authorised
    with sim_server("--backend", "fake", "--secret-key", str(keys / "server.key_secret")) as server:
        for who in (stranger, None):
            started = time.monotonic()
            with ZmqChannel(server.address, 10.0, who) as connection:
                with pytest.raises(AuthenticationFailed):
                    connection.hello()
                with pytest.raises(AuthenticationFailed):
                    connection.request(Step(1, 0.5))
            assert time.monotonic() - started < 5.0  # refused at once, not timed out
        with ZmqChannel(server.address, 5.0, credentials(keys)) as connection:
            assert isinstance(connection.hello(), Welcome)  # the server went on serving


def test_a_public_bind_needs_keys_or_insecure(keys: Path) -> None:
    refused = subprocess.run(
        [sys.executable, "-m", "sim_server.cli", "--backend", "fake", "--bind", "tcp://0.0.0.0:0"],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert refused.returncode == 2 and "--secret-key" in refused.stderr
    with sim_server(
        "--backend", "fake", "--secret-key", str(keys / "server.key_secret"),
        bind="tcp://0.0.0.0:0",
    ) as server:  # fmt: skip
        port = server.address.rsplit(":", 1)[1]
        with ZmqChannel(f"tcp://127.0.0.1:{port}", 5.0, credentials(keys)) as connection:
            assert isinstance(connection.hello(), Welcome)


def test_bad_key_files_are_usage_errors(keys: Path, tmp_path: Path) -> None:
    garbage = tmp_path / "garbage.key_secret"
    garbage.write_text("not a certificate\n")
    for key in (keys / "server.key", garbage, tmp_path / "missing"):
        result = subprocess.run(
            [sys.executable, "-m", "sim_server.cli", "--backend", "fake", "--secret-key", str(key)],
            capture_output=True, text=True, timeout=60, check=False,
        )  # fmt: skip
        assert result.returncode == 2 and "--secret-key" in result.stderr, result.stderr


def test_agent_client_takes_key_files(keys: Path) -> None:
    with sim_server("--backend", "fake", "--secret-key", str(keys / "server.key_secret")) as server:
        driven = subprocess.run(
            [sys.executable, "-m", "agent_client.cli.main", "drive", "--server", server.address,
             "--episodes", "1", "--json", "--option", "length=300.0",
             "--server-key", str(keys / "server.key"),
             "--secret-key", str(keys / "client.key_secret")],
            capture_output=True, text=True, timeout=120, check=False,
        )  # fmt: skip
        assert driven.returncode == 0, driven.stderr
        assert json.loads(driven.stdout.splitlines()[0])["steps"] > 0
        refused = subprocess.run(
            [sys.executable, "-m", "agent_client.cli.main", "drive", "--server", server.address,
             "--episodes", "1", "--timeout", "30"],
            capture_output=True, text=True, timeout=120, check=False,
        )  # fmt: skip
        assert refused.returncode == 2 and "refused the CURVE handshake" in refused.stderr
