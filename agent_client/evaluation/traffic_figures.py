"""Traffic-level figures from every vehicle's speed and position over time.

What a mixed-autonomy evaluation reports of the whole traffic, not of one ego: the mean speed,
the spread of the speeds across vehicles (0 in uniform flow; a stop-and-go wave makes it large)
and over time per vehicle (a wave makes each vehicle's speed swing), the share of time stopped,
and the throughput: vehicles past a fixed point per hour, and Edie's (1963) generalised flow,
the distance all vehicles drove in a stretch of road and a span of time over that area.

Inputs are arrays of shape (steps, vehicles), one column per vehicle, NaN where a vehicle is not
on the road at that step; positions are unwrapped (they grow lap after lap on a ring). Pure
numpy, no simulator: `benchmarks/mixed_autonomy.py` feeds them from the bridge's ``traffic``.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Collection, Sequence

import numpy as np

__all__ = [
    "STOPPED_SPEED",
    "arrivals",
    "edie_flow",
    "first_last",
    "mean_speed",
    "passes",
    "per_hour",
    "spread_across",
    "spread_over_time",
    "stopped_share",
]

STOPPED_SPEED = 1.0
"""A vehicle slower than this (m/s) counts as stopped (the bridge's default ``stop_speed``)."""


def _table(values: np.ndarray | Sequence[Sequence[float]]) -> np.ndarray:
    array = np.asarray(values, dtype=np.float64)
    if array.ndim != 2:
        raise ValueError(f"expected a (steps, vehicles) array, got shape {array.shape}")
    return array


def mean_speed(speeds: np.ndarray) -> float:
    """The mean over every vehicle-step present (nan if none)."""
    table = _table(speeds)
    present = ~np.isnan(table)
    return float(table[present].mean()) if present.any() else math.nan


def spread_across(speeds: np.ndarray) -> float:
    """The standard deviation of the speeds across the vehicles present at each step, averaged
    over the steps with at least two vehicles (nan if none)."""
    table = _table(speeds)
    counts = (~np.isnan(table)).sum(axis=1)
    rows = table[counts >= 2]
    if len(rows) == 0:
        return math.nan
    return float(np.nanstd(rows, axis=1).mean())


def spread_over_time(speeds: np.ndarray) -> float:
    """Each vehicle's standard deviation of its speed over the steps it is present, averaged
    over the vehicles present at two steps or more (nan if none)."""
    table = _table(speeds)
    counts = (~np.isnan(table)).sum(axis=0)
    columns = table[:, counts >= 2]
    if columns.shape[1] == 0:
        return math.nan
    return float(np.nanstd(columns, axis=0).mean())


def stopped_share(speeds: np.ndarray, threshold: float = STOPPED_SPEED) -> float:
    """The share of vehicle-steps slower than `threshold` (nan if none)."""
    table = _table(speeds)
    present = ~np.isnan(table)
    return float((table[present] < threshold).mean()) if present.any() else math.nan


def first_last(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each vehicle's first and last position present (NaN for a vehicle never present)."""
    table = _table(positions)
    present = ~np.isnan(table)
    seen = present.any(axis=0)
    first_row = np.argmax(present, axis=0)
    last_row = len(table) - 1 - np.argmax(present[::-1], axis=0)
    columns = np.arange(table.shape[1])
    first = np.where(seen, table[first_row, columns], np.nan)
    last = np.where(seen, table[last_row, columns], np.nan)
    return first, last


def passes(start: np.ndarray, end: np.ndarray, point: float, period: float | None = None) -> int:
    """How often fronts that moved forward from `start` to `end` (unwrapped, m) passed `point`.

    On a straight road (`period` None) a vehicle passes once if it started before the point and
    ended at or beyond it. On a ring of length `period` every lap counts: the point is every
    ``point + k * period``. Vehicles with a NaN position are left out."""
    a, b = np.asarray(start, dtype=np.float64), np.asarray(end, dtype=np.float64)
    known = ~(np.isnan(a) | np.isnan(b))
    a, b = a[known], b[known]
    if period is None:
        return int(((a < point) & (b >= point)).sum())
    if period <= 0:
        raise ValueError(f"period must be > 0, got {period}")
    laps = np.floor((b - point) / period) - np.floor((a - point) / period)
    return int(np.maximum(laps, 0).sum())


def per_hour(count: float, seconds: float) -> float:
    """`count` events in `seconds` as a rate per hour (nan without time)."""
    return 3600.0 * count / seconds if seconds > 0 else math.nan


def edie_flow(distances: np.ndarray, length: float, seconds: float) -> float:
    """Edie's generalised flow (veh/h): the total distance the vehicles drove in a stretch of
    `length` m during `seconds`, over that area (on a ring: density x mean speed)."""
    if length <= 0 or seconds <= 0:
        return math.nan
    driven = np.asarray(distances, dtype=np.float64)
    return 3600.0 * float(np.nansum(driven)) / (length * seconds)


def arrivals(ids_per_step: Sequence[Collection[str]]) -> int:
    """How many vehicles left: ids present at one step and absent at the next."""
    steps = [set(ids) for ids in ids_per_step]
    return sum(len(before - after) for before, after in itertools.pairwise(steps))
