"""The picture of a merge (or an exit, or a lane drop): each driver's first route change on the
same seed, as a time-space diagram around it.

One panel per driver: time from the start of the change (x) against the distance along the road
from the end of the lane it left (y, so 0 is where that lane ends, the same for every driver on
the seed). The ego is the thick black line; the vehicles it saw in the lane it moved to are thin
lines coloured by their speed; a purple triangle marks where the change started and a dotted
line where it completed. Drivers that made no route change on the seed say so.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from agent_client.evaluation.routes import RouteChange
from agent_client.evaluation.trajectories import EpisodeTrace

WINDOW_S = (-8.0, 12.0)
"""Seconds around the start of the change that a panel shows."""


def plot_route_changes(
    drivers: dict[str, tuple[str, EpisodeTrace, RouteChange | None]], path: Path, title: str
) -> None:
    """One panel per driver (label, its trace on the seed, its first route change or None)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(
        1, len(drivers), figsize=(5.2 * len(drivers), 4.6), sharey=True, squeeze=False
    )
    norm = plt.Normalize(0.0, 30.0)
    for axis, (label, trace, change) in zip(axes[0], drivers.values(), strict=True):
        axis.set_title(label, fontsize=10)
        axis.set_xlabel("time from the start of the change (s)")
        axis.axhline(0.0, color="red", lw=1.2, ls="--")
        axis.grid(alpha=0.3)
        axis.set_xlim(*WINDOW_S)
        if change is None:
            axis.text(0.5, 0.5, "no route change on this seed", ha="center", va="center",
                      transform=axis.transAxes)  # fmt: skip
            continue
        _draw(axis, trace, change, norm)
    axes[0][0].set_ylabel("along the road from the lane's end (m)")
    mappable = plt.cm.ScalarMappable(norm=norm, cmap="viridis")
    figure.colorbar(mappable, ax=axes[0].tolist(), label="speed of the others (m/s)", shrink=0.85)
    figure.suptitle(title, fontsize=11)
    figure.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(figure)


def _draw(axis: Any, trace: EpisodeTrace, change: RouteChange, norm: Any) -> None:
    """The ego and the vehicles of the lane it moved to, around `change`."""
    start = trace.start + change.time
    end_of_lane = change.position + change.lane_end
    low, high = start + WINDOW_S[0], start + WINDOW_S[1]
    shown = (trace.time >= low) & (trace.time <= high)
    starts = trace.lane_change_starts
    index = int(np.argmin(np.abs(starts - start))) if len(starts) else -1
    direction = int(trace.lane_change_directions[index]) if index >= 0 else 0
    before = trace.lane[np.searchsorted(trace.time, start, side="right") - 1]
    target = before + direction
    for track in trace.neighbours.values():
        mine = (track.lane == target) & (track.time >= low) & (track.time <= high)
        if mine.sum() < 2:
            continue
        axis.scatter(track.time[mine] - start, track.position[mine] - end_of_lane, s=2,
                     c=track.speed[mine], cmap="viridis", norm=norm)  # fmt: skip
    axis.plot(trace.time[shown] - start, trace.position[shown] - end_of_lane, color="black", lw=2.2)
    axis.plot([0.0], [change.position - end_of_lane], marker="^", color="purple", ms=9)
    done = trace.lane_change_completions
    after = done[(done >= start) & (done <= high)]
    if len(after):
        axis.axvline(after[0] - start, color="purple", ls=":", lw=1.2)
    gaps = ", ".join(
        f"{name} {value:.1f} s"
        for name, value in (("lead", change.lead_headway), ("lag", change.lag_headway))
        if value is not None
    )
    braking = change.follower_braking
    note = f"{change.lane_end:.0f} m before the end\ngaps: {gaps or 'no one there'}"
    if braking is not None:
        note += f"\nnew follower braked {braking:.1f} m/s²"
    axis.text(0.02, 0.98, note, transform=axis.transAxes, va="top", fontsize=8)
