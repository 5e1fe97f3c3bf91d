"""``drive --record``, ``evaluate --record`` and ``export-recording`` as a user runs them (in
process, against a conforming in-process server), and their typos: one line naming the bad
value, exit status 2, no connection opened."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from agent_client.cli import main
from agent_client.evaluation.export import COLUMNS
from protocol.recording import MANIFEST, load
from tests.agent_client.conformance.toys import ToyServer

NOBODY = "tcp://127.0.0.1:9"  # the discard port: nothing answers there
SHORT = ["--option", "length=120"]


def test_drive_records_its_episodes_and_export_writes_one_row_per_observation(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "rec"
    with ToyServer() as toy:
        argv = ["drive", "--server", toy.address, "--episodes", "2", "--seed", "8", *SHORT]
        assert main([*argv, "--json", "--record", str(folder)]) == 0
    driven = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    manifest = json.loads((folder / MANIFEST).read_text())
    assert manifest["command"] == "drive" and manifest["seeds"] == [8, 9]
    assert manifest["drivers"] == {"policy": "idm"} and manifest["options"] == {"length": 120}
    assert [e["steps"] for e in manifest["episodes"]] == [d["steps"] for d in driven]
    assert main(["export-recording", str(folder), "--out", str(tmp_path / "t.csv")]) == 0
    assert "observations of 2 episodes" in capsys.readouterr().out
    lines = (tmp_path / "t.csv").read_text().splitlines()
    assert lines[0].split(",") == list(COLUMNS)
    assert len(lines) == 1 + sum(d["steps"] + 1 for d in driven)


def test_evaluate_records_both_drivers_on_the_same_seeds(tmp_path: Path) -> None:
    folder = tmp_path / "rec"
    with ToyServer() as toy:
        argv = ["evaluate", "--server", toy.address, "--policy", "idm", "--episodes", "1"]
        argv += ["--seed", "4", "--out", str(tmp_path / "eval"), *SHORT, "--record", str(folder)]
        assert main(argv) == 0
    recording = load(folder)
    assert [e.reset.seed for e in recording.episodes] == [4, 4]
    assert recording.manifest["drivers"] == {"policy": "idm", "baseline": "idm"}


@pytest.mark.parametrize(
    ("argv", "names"),
    [
        (["drive", "--record", "{file}"], ["--record", "{file}", "not a folder"]),
        (["drive", "--record", "{full}"], ["--record", "{full}", "not empty"]),
        (["drive", "--record", "{file}/sub"], ["--record", "{file}/sub", "cannot write"]),
        (["evaluate", "--policy", "idm", "--record", "{full}"], ["--record", "{full}"]),
        (["export-recording", "{tmp}/nope"], ["{tmp}/nope", "no such folder"]),
        (["export-recording", "{tmp}"], ["{tmp}", "holds no recording"]),
        (["export-recording", "{full}", "--out", "t.parquet"], ["--out t.parquet", "CSV"]),
        (["export-recording", "{full}", "--out", "{tmp}/no/t.csv"], ["{tmp}/no/t.csv"]),
    ],
)
def test_a_recording_typo_is_one_line_with_exit_status_2(
    tmp_path: Path, argv: list[str], names: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    paths = {"file": tmp_path / "file", "full": tmp_path / "full", "tmp": tmp_path}
    paths["file"].write_text("")
    paths["full"].mkdir()
    (paths["full"] / "notes.txt").write_text("")

    def filled(text: str) -> str:
        return text.format(**paths)

    started = time.monotonic()
    connection = [] if argv[0] == "export-recording" else ["--server", NOBODY, "--timeout", "30"]
    assert main([*map(filled, argv), *connection]) == 2
    assert time.monotonic() - started < 10.0  # no connection attempt waited for its deadline
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert err.startswith("agent-client: ")
    for name in map(filled, names):
        assert name in err
    assert not (tmp_path / "file" / "sub").exists()
