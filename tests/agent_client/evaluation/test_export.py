"""The export of recorded trajectories: every column documented, and the CSV read by pandas back
to the recorded values exactly."""

from __future__ import annotations

from pathlib import Path

import pytest

from agent_client.evaluation.export import COLUMNS, NEIGHBOUR_SLOTS, rows, write_csv
from protocol.messages import Bye, Close, Hello, Reset, Step
from protocol.recording import load
from protocol.version import PROTOCOL_VERSION
from tests.protocol.test_recording import WELCOME, observation, recording

DOCS = Path(__file__).resolve().parents[3] / "docs" / "recording.md"


def documented_name(column: str) -> str:
    """How docs/recording.md names a column: neighbour columns as ``SLOT_field``."""
    for slot in NEIGHBOUR_SLOTS:
        if column.startswith(slot + "_"):
            return "SLOT_" + column.removeprefix(slot + "_")
    return column


@pytest.mark.parametrize("column", COLUMNS)
def test_every_column_is_documented(column: str) -> None:
    assert f"`{documented_name(column)}`" in DOCS.read_text()


def test_every_slot_is_documented() -> None:
    text = DOCS.read_text()
    assert all(f"`{slot}`" in text for slot in NEIGHBOUR_SLOTS)


CONVERSATION = [
    (Hello(PROTOCOL_VERSION), WELCOME),
    (Reset("cf", 11), observation(0)),
    (Step(1, 0.5), observation(1, time=1 / 3)),  # a float that needs all 17 digits
    (Step(2, 0.5), observation(2, terminated=True, reason="collision")),
    (Close(), Bye()),
]


def test_one_row_per_observation_with_its_episode(tmp_path: Path) -> None:
    table = list(rows(load(recording(tmp_path / "rec", CONVERSATION))))
    assert [row[:5] for row in table] == [
        [0, "session-000.avbr", "cf", 11, seq] for seq in range(3)
    ]
    assert all(len(row) == len(COLUMNS) for row in table)


def test_pandas_reads_the_recorded_values_back_exactly(tmp_path: Path) -> None:
    pandas = pytest.importorskip("pandas")
    folder = recording(tmp_path / "rec", CONVERSATION)
    assert write_csv(load(folder), tmp_path / "t.csv") == 3
    table = pandas.read_csv(tmp_path / "t.csv")
    assert list(table.columns) == list(COLUMNS)
    assert table["time"].tolist() == [30.0, 1 / 3, 30.2]
    assert table["terminated"].dtype == bool
    assert table["terminated"].tolist() == [False, False, True]
    assert table["leader_gap"].tolist() == [12.5] * 3
    assert table["leader_id"].tolist() == ["veh.1"] * 3
    assert table["action_acceleration_limited_by"].tolist() == ["bounds"] * 3
    assert table["reason"].isna().tolist() == [True, True, False]
