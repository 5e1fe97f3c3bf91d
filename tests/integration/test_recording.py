"""Record `agent-client drive` against real SUMO, replay it with `sim-server --backend replay`:
the same command gets the same frames bit for bit, and a departing request gets its error while
the server goes on serving (docs/recording.md)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from agent_client.transport import connect
from protocol.messages import Error, Observation, Reset, Step
from protocol.recording import REPLY, load, read_records, stream_name
from tests.conftest import RunningServer, sim_server

pytestmark = pytest.mark.sumo

OPTIONS = ["--option", "max_episode_time=20"]
"""Short episodes: 200 decisions each after the warm-up."""


def drive(address: str, record: Path) -> list[dict[str, object]]:
    """`agent-client drive` with IDM, seeds 5 and 6, recorded; its JSON lines."""
    result = subprocess.run(
        [sys.executable, "-m", "agent_client.cli.main", "drive", "--server", address,
         "--scenario", "cf", "--policy", "idm", "--episodes", "2", "--seed", "5", *OPTIONS,
         "--json", "--record", str(record)],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    return [json.loads(line) for line in result.stdout.splitlines()]


def reply_frames(folder: Path) -> list[bytes]:
    records = read_records(folder / stream_name(0))
    return [record.frame for record in records if record.direction == REPLY]


@pytest.fixture(scope="module")
def recorded(sumo_server: RunningServer, tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("recording") / "sumo"
    drive(sumo_server.address, folder)
    return folder


def test_a_replayed_drive_gets_the_recorded_frames_bit_for_bit(
    recorded: Path, tmp_path: Path
) -> None:
    original = load(recorded)
    assert original.welcome.backend == "sumo"
    assert [e.reset.seed for e in original.episodes] == [5, 6]
    assert all(len(e.steps) > 100 for e in original.episodes)
    with sim_server("--backend", "replay", "--recording", str(recorded)) as replay:
        summaries = drive(replay.address, tmp_path / "again")
        assert replay.process.poll() is None
    again = load(tmp_path / "again")
    assert again.welcome == original.welcome
    assert [e.observations for e in again.episodes] == [e.observations for e in original.episodes]
    assert reply_frames(tmp_path / "again") == reply_frames(recorded)
    assert [s["seed"] for s in summaries] == [5, 6]


def test_a_departing_request_gets_its_error_and_the_server_goes_on(recorded: Path) -> None:
    episode = load(recorded).episodes[0]
    reset, first = episode.reset, episode.steps[0]
    with (
        sim_server("--backend", "replay", "--recording", str(recorded)) as replay,
        connect(replay.address) as channel,
    ):
        channel.hello()
        other_seed = channel.exchange(Reset("cf", 99, reset.options))
        assert isinstance(other_seed, Error) and other_seed.code == "invalid_number"
        assert "seed 99 departs from the recording" in other_seed.message
        other_option = channel.exchange(Reset("cf", 5, {**reset.options, "warmup": 10.0}))
        assert isinstance(other_option, Error) and other_option.code == "invalid_option"
        assert "warmup" in other_option.message
        assert channel.request(reset) == episode.reply
        step = first.step
        nudged = channel.exchange(Step(1, step.acceleration + 1e-6, step.lane_change))
        assert isinstance(nudged, Error) and nudged.code == "invalid_number"
        assert f"recorded {step.acceleration!r}" in nudged.message
        assert channel.request(reset) == episode.reply  # still serving
        reply = channel.request(step)
        assert isinstance(reply, Observation) and reply == first.reply
        assert replay.process.poll() is None
