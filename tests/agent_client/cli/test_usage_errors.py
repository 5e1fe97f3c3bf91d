"""A user's typo is one line naming the bad value and the valid ones, exit status 2, and no
connection is opened: the server address below has nobody listening, and every case must fail
faster than a connection attempt would."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from agent_client.cli import main

NOBODY = "tcp://127.0.0.1:9"  # the discard port: nothing answers there


@pytest.mark.parametrize(
    ("argv", "names"),
    [
        (["train", "--reward", "typo"], ["'typo'", "safe", "ra3"]),
        (["train", "--set", "learner.nosuch=1"], ["'nosuch'", "actor_lr"]),
        (["train", "--set", "nosuch=1"], ["'nosuch'", "episodes"]),
        (["train", "--set", "noequals"], ["noequals", "KEY=VALUE"]),
        (["train", "--set", "episodes=0"], ["episodes", "at least 1"]),
        (["train", "--set", "chunks_in_flight=x"], ["chunks_in_flight", "whole number", "'x'"]),
        (["train", "--set", "features=typo"], ["'typo'", "cf", "lc"]),
        (["train", "--config", "missing.toml"], ["missing.toml"]),
        (["train", "--resume", "no/such/run"], ["no/such/run"]),
        (
            ["train", "--inline-evaluations", "--eval-server", "tcp://127.0.0.1:8"],
            ["--inline-evaluations", "--eval-server"],
        ),
        (["drive", "--reward", "typo"], ["'typo'", "safe"]),
        (["drive", "--policy", "missing.pt"], ["missing.pt", "idm"]),
        (["drive", "--policy", "idm:missing.json"], ["missing.json"]),
        (["evaluate", "--policy", "missing.pt"], ["missing.pt"]),
        (["evaluate", "--policy", "idm", "--baseline", "idm:nope.json"], ["nope.json"]),
        (["evaluate", "--policy", "idm", "--run", "no/such/run"], ["no/such/run"]),
    ],
)
def test_a_typo_is_one_line_with_exit_status_2(
    argv: list[str], names: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    started = time.monotonic()
    status = main([*argv, "--server", NOBODY, "--timeout", "30"])
    assert status == 2
    assert time.monotonic() - started < 10.0  # no connection attempt waited for its deadline
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert err.startswith("agent-client: ")
    for name in names:
        assert name in err


def test_bad_idm_parameters_are_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    params = tmp_path / "idm.json"
    params.write_text('{"params": {"a": 1.0, "warp": 9}}')
    assert main(["drive", "--policy", f"idm:{params}", "--server", NOBODY]) == 2
    err = capsys.readouterr().err
    assert "'warp'" in err and "delta" in err


def test_a_missing_key_file_is_a_usage_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["drive", "--server", NOBODY, "--server-key", str(tmp_path / "server.key")]
    assert main(argv) == 2
    assert "--secret-key" in capsys.readouterr().err
