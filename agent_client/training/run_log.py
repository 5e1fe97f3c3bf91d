"""A run's records: per-episode and per-evaluation CSV files and TensorBoard event files."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import IO, Any

EPISODE_CSV = "episodes.csv"
EVALUATION_CSV = "evaluations.csv"
EPISODE_SCALARS = (
    "total_reward",
    "average_speed",
    "critic_loss",
    "q_mean",
    "q_upper_bound",
    "jerk_share_above_limit",
    "headway_share_below_1s",
    "collisions",
    "noise_scale",
)


class RunLog:
    """Appends rows to CSV (resumable) and scalars to TensorBoard (``charts/``, ``eval/``)."""

    def __init__(self, folder: Path, resume: bool = False) -> None:
        self.folder = folder
        self._files: dict[str, tuple[IO[str], csv.DictWriter[str]]] = {}
        self._resume = resume
        from torch.utils.tensorboard import SummaryWriter

        self.tensorboard = SummaryWriter(str(folder / "tensorboard"))

    def episode(self, row: dict[str, Any]) -> None:
        self._append(EPISODE_CSV, row)
        step = int(row["episode"])
        for key in EPISODE_SCALARS:
            value = row.get(key)
            if isinstance(value, int | float) and math.isfinite(value):
                self.tensorboard.add_scalar(f"charts/{key}", value, step)

    def evaluation(self, row: dict[str, Any]) -> None:
        self._append(EVALUATION_CSV, row)
        step = int(row["episode"])
        for key, value in row.items():
            if (
                isinstance(value, int | float)
                and not isinstance(value, bool)
                and math.isfinite(value)
            ):
                self.tensorboard.add_scalar(f"eval/{key}", value, step)

    def _append(self, name: str, row: dict[str, Any]) -> None:
        if name not in self._files:
            path = self.folder / name
            exists = path.exists() and path.stat().st_size > 0
            stream: IO[str] = path.open("a" if self._resume and exists else "w", newline="")
            writer = csv.DictWriter(stream, fieldnames=list(row))
            if not (self._resume and exists):
                writer.writeheader()
            self._files[name] = (stream, writer)
        stream, writer = self._files[name]
        writer.writerow({k: row.get(k) for k in writer.fieldnames})
        stream.flush()

    def close(self) -> None:
        for stream, _ in self._files.values():
            stream.close()
        self._files.clear()
        self.tensorboard.close()


def read_rows(path: Path) -> list[dict[str, str]]:
    """Rows of a CSV written by `RunLog`."""
    with path.open(newline="") as stream:
        return list(csv.DictReader(stream))
