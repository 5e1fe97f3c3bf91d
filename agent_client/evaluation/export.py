"""Recorded trajectories as a table: one row per observation of a recording (docs/recording.md).

The columns follow the protocol's messages field by field (`COLUMNS`), so the table says what
the wire said: the episode and its reset, the observation's seq and time, the ego, each of the
six neighbours, the action as requested and applied, the events, and how the episode ended.
Written as CSV (`write_csv`), which ``pandas.read_csv`` reads with the right types: numbers as
the shortest text that reads back to the same float, booleans as ``True``/``False``.
"""

from __future__ import annotations

import csv
from collections.abc import Iterator
from dataclasses import fields
from pathlib import Path
from typing import Any

from protocol.messages import AppliedAction, Ego, Events, Neighbour, Neighbours, Observation
from protocol.recording import RecordedEpisode, Recording

EPISODE_COLUMNS = ("episode", "stream", "scenario", "seed", "seq", "time")
"""Which episode (its index in the recording, its stream file, its reset) and when."""
NEIGHBOUR_SLOTS = tuple(f.name for f in fields(Neighbours))
END_COLUMNS = ("terminated", "truncated", "reason")


def _prefixed(prefix: str, cls: type) -> tuple[str, ...]:
    return tuple(f"{prefix}_{f.name}" for f in fields(cls))


COLUMNS: tuple[str, ...] = (
    EPISODE_COLUMNS
    + _prefixed("ego", Ego)
    + tuple(column for slot in NEIGHBOUR_SLOTS for column in _prefixed(slot, Neighbour))
    + _prefixed("action", AppliedAction)
    + _prefixed("event", Events)
    + END_COLUMNS
)
"""Every column of the table, in order."""


def rows(recording: Recording) -> Iterator[list[Any]]:
    """One row per observation of every episode (an episode whose reset failed has none)."""
    for index, episode in enumerate(recording.episodes):
        for obs in episode.observations:
            yield _row(index, episode, obs)


def _row(index: int, episode: RecordedEpisode, obs: Observation) -> list[Any]:
    reset = episode.reset
    row: list[Any] = [index, episode.stream, reset.scenario, reset.seed, obs.seq, obs.time]
    row += _values(obs.ego)
    for slot in NEIGHBOUR_SLOTS:
        row += _values(getattr(obs.neighbours, slot))
    row += _values(obs.action) + _values(obs.events)
    row += [obs.terminated, obs.truncated, obs.reason]
    return row


def _values(message: Any) -> list[Any]:
    return [getattr(message, f.name) for f in fields(message)]


def write_csv(recording: Recording, out: Path) -> int:
    """Write the table to `out` (header first); returns the number of rows."""
    count = 0
    with out.open("w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(COLUMNS)
        for row in rows(recording):
            writer.writerow(["" if value is None else value for value in row])
            count += 1
    return count
