"""Pictures of single episodes: a time-space diagram and time series of the ego's driving.

`plot_time_space` draws one driver's episode (docs/evaluation.md, "Trajectories of chosen
episodes"): time against position along the road, one panel per lane with the leftmost lane on
top, the ego as a thick black line in the lane it is in (thin and grey in the others, for
reference), every observed neighbour as a line coloured by its speed, the ego's lane changes and
collisions marked. `plot_time_series` puts the drivers of one seed side by side: speed, gap to
the leader, acceleration and jerk over the time since the episode's start. Both read
`agent_client.evaluation.trajectories.EpisodeTrace`s; matplotlib is imported when drawing.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from agent_client.constants import JERK_COMFORT_LIMIT
from agent_client.evaluation.plots import COLOURS, _pyplot
from agent_client.evaluation.trajectories import EpisodeTrace

SPEED_COLOURS = "turbo_r"
"""Colour map of the neighbours' speeds: red slow, blue fast (congestion stands out)."""

EVENT_STYLE: dict[str, dict[str, Any]] = {
    "lane_change_starts": {"color": "tab:purple", "ls": "--", "label": "lane change started"},
    "lane_change_completions": {"color": "tab:purple", "ls": ":", "label": "lane change completed"},
    "lane_change_aborts": {"color": "tab:brown", "ls": "-.", "label": "lane change aborted"},
    "collisions": {"color": "red", "ls": "-", "label": "collision"},
}
"""How each of the ego's events is marked: a vertical line across the panels."""

DPI = 110


def _lane_label(lane: int, lanes: int) -> str:
    """The y label of a lane's row ("lane 0 (right)"); just the unit on a one-lane road."""
    if lanes == 1:
        return "position (m)"
    side = " (right)" if lane == 0 else " (left)" if lane == lanes - 1 else ""
    return f"lane {lane}{side}\nposition (m)"


def _speed_range(trace: EpisodeTrace) -> float:
    """Top of the speed colour scale: 1.25 x the speed limit, rounded up to 5 m/s.

    It depends on the road only, so every diagram of a scenario has the same colours; faster
    vehicles take the top colour (the colour bar's arrow).
    """
    limit = float(np.max(trace.speed_limit)) if len(trace.speed_limit) else 0.0
    return max(5.0, 5.0 * math.ceil(1.25 * limit / 5.0))


def _lane_segments(
    trace: EpisodeTrace, lane: int, relative: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Line segments (time since the start, position) between consecutive observations of a
    neighbour in `lane`, their speeds, and the samples no segment covers (seen once there).

    `relative`: positions from the ego's front at the same observation instead of the road's
    start (leaders above zero, followers below).
    """
    segments, speeds, lone = [np.zeros((0, 2, 2))], [np.zeros(0)], [np.zeros((0, 3))]
    for track in trace.neighbours.values():
        t = track.time - trace.start
        y = track.position - trace.position[track.step] if relative else track.position
        here = track.lane == lane
        starts = np.flatnonzero(here[:-1] & here[1:] & (np.diff(track.step) == 1))
        ends = starts + 1
        segments.append(
            np.stack(
                [np.column_stack([t[starts], y[starts]]), np.column_stack([t[ends], y[ends]])],
                axis=1,
            )
        )
        speeds.append(0.5 * (track.speed[starts] + track.speed[ends]))
        covered = np.zeros(len(t), dtype=bool)
        covered[starts] = covered[ends] = True
        alone = here & ~covered
        lone.append(np.column_stack([t[alone], y[alone], track.speed[alone]]))
    return np.concatenate(segments), np.concatenate(speeds), np.concatenate(lone)


def _draw_ego(axis: Any, trace: EpisodeTrace, lane: int, relative: bool) -> None:
    """The ego: thick black where it is in `lane`, a thin grey reference line elsewhere."""
    t = trace.time - trace.start
    y = np.zeros(len(t)) if relative else trace.position
    axis.plot(t, y, color="0.55", lw=0.8, ls="--", zorder=3)
    axis.plot(
        t,
        np.where(trace.lane == lane, y, np.nan),
        color="black",
        lw=2.5,
        zorder=4,
        solid_capstyle="butt",
    )


def _mark_events(axis: Any, trace: EpisodeTrace, lane: int, relative: bool) -> None:
    """Vertical lines at the ego's events; symbols on its line in the lane where they happen."""
    t = trace.time - trace.start
    y = np.zeros(len(t)) if relative else trace.position
    for name, style in EVENT_STYLE.items():
        times = getattr(trace, name)
        for moment in times:
            axis.axvline(moment - trace.start, color=style["color"], ls=style["ls"], lw=1.0)
        index = np.clip(np.searchsorted(trace.time, times), 0, len(t) - 1).astype(int)
        here = trace.lane[index] == lane
        if name == "lane_change_starts":
            for direction, marker in ((1, "^"), (-1, "v")):
                chosen = index[here & (trace.lane_change_directions == direction)]
                axis.plot(
                    t[chosen],
                    y[chosen],
                    marker,
                    color="tab:purple",
                    ms=9,
                    mec="white",
                    zorder=6,
                    ls="none",
                )
        elif name == "collisions":
            hit = index[here]
            axis.plot(t[hit], y[hit], "X", color="red", ms=13, mec="black", zorder=7, ls="none")


def _legend_handles(lanes: int) -> list[Any]:
    """The key of the marks: on one lane only the ego and collisions (nothing else happens)."""
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], color="black", lw=2.5, label="ego in this lane")]
    styles = list(EVENT_STYLE.values())
    if lanes > 1:
        handles += [
            Line2D([], [], color="0.55", lw=0.8, ls="--", label="ego in another lane"),
            Line2D([], [], color="tab:purple", marker="^", ls="none", ms=8, label="change left"),
            Line2D([], [], color="tab:purple", marker="v", ls="none", ms=8, label="change right"),
        ]
    else:
        handles[0].set_label("ego")
        styles = [EVENT_STYLE["collisions"]]
    handles += [
        Line2D([], [], color=s["color"], ls=s["ls"], lw=1.0, label=s["label"]) for s in styles
    ]
    return handles


def _draw_panel(axis: Any, trace: EpisodeTrace, lane: int, norm: Any, relative: bool) -> Any:
    """One lane's panel: the neighbours coloured by speed, the ego, its events; the colours."""
    from matplotlib.collections import LineCollection

    segments, speeds, lone = _lane_segments(trace, lane, relative)
    lines = LineCollection(
        list(segments), array=speeds, cmap=SPEED_COLOURS, norm=norm, linewidths=1.3, zorder=2
    )
    axis.add_collection(lines)
    axis.scatter(lone[:, 0], lone[:, 1], c=lone[:, 2], cmap=SPEED_COLOURS, norm=norm, s=4, zorder=2)
    _draw_ego(axis, trace, lane, relative)
    _mark_events(axis, trace, lane, relative)
    axis.grid(alpha=0.3)
    return lines


def plot_time_space(trace: EpisodeTrace, path: Path, title: str) -> None:
    """Time-space diagram of one episode of one driver, one row per lane (leftmost on top):
    positions along the road on the left, from the ego's front on the right."""
    plt = _pyplot()
    from matplotlib.colors import Normalize

    lanes = max(trace.lane_count, 1)
    fig, axes = plt.subplots(
        lanes,
        2,
        sharex=True,
        sharey="col",
        squeeze=False,
        width_ratios=(3, 2),
        figsize=(14, 1.8 + 2.6 * lanes),
        layout="constrained",
    )
    norm = Normalize(0.0, _speed_range(trace))
    lines = None
    for row in range(lanes):
        lane = lanes - 1 - row
        for column, relative in enumerate((False, True)):
            lines = _draw_panel(axes[row, column], trace, lane, norm, relative)
        axes[row, 0].set_ylabel(_lane_label(lane, lanes))
        axes[row, 1].set_ylabel("from the ego's front (m)")
    axes[0, 0].set_title("along the road", fontsize=10)
    axes[0, 1].set_title("in the ego's frame: leaders above 0, followers below", fontsize=10)
    end = float(trace.time[-1] - trace.start)
    end = max(end, 1.0)
    for axis in axes[-1]:
        axis.set(xlabel="time since the episode's start (s)", xlim=(-0.01 * end, 1.01 * end))
    for axis in axes[0]:
        axis.autoscale_view(scalex=False)
    fig.colorbar(
        lines,
        ax=list(axes[:, 1]),
        label="neighbour speed (m/s)",
        extend="max",
        extendfrac=0.04,
        shrink=0.9 if lanes > 1 else 1.0,
    )
    fig.suptitle(title)
    fig.legend(handles=_legend_handles(lanes), loc="outside lower center", ncols=8, fontsize=8)
    fig.savefig(path, dpi=DPI)
    plt.close(fig)


def plot_time_series(
    traces: dict[str, EpisodeTrace], labels: dict[str, str], path: Path, title: str
) -> None:
    """Speed, gap to the leader, acceleration and jerk of each driver on one seed (stacked)."""
    plt = _pyplot()
    fig, axes = plt.subplots(4, 1, sharex=True, figsize=(10, 10), layout="constrained")
    speed, gap, acceleration, jerk = axes
    end = 1.0
    for layer, (role, trace) in enumerate(traces.items()):
        t = trace.time - trace.start
        end = max(end, float(t[-1]))
        # The first driver (the policy) on top: the others' lines do not hide it.
        style = {
            "color": COLOURS.get(role, "tab:gray"),
            "lw": 1.1,
            "zorder": 3 + len(traces) - layer,
        }
        speed.plot(t, trace.speed, label=labels.get(role, role), **style)
        gap.plot(t, trace.gap, **style)
        acceleration.plot(t, trace.acceleration, **style)
        jerk.plot(t, trace.jerk, **{**style, "lw": 0.8})
        for axis in axes:
            for moment in trace.lane_change_starts:
                axis.axvline(moment - trace.start, color=style["color"], ls=":", lw=0.9)
            for moment in trace.collisions:
                axis.axvline(moment - trace.start, color="red", lw=1.5)
    first = next(iter(traces.values()))
    speed.plot(
        first.time - first.start,
        first.speed_limit,
        color="0.4",
        ls="--",
        lw=0.9,
        label="speed limit",
    )
    for sign in (-1, 1):
        jerk.axhline(
            sign * JERK_COMFORT_LIMIT,
            color="tab:red",
            ls="--",
            lw=1.0,
            label=f"comfort limit +/-{JERK_COMFORT_LIMIT} m/s^3" if sign > 0 else None,
        )
    reach = _jerk_reach(traces)
    jerk.set_ylim(-reach, reach)
    speed.set(ylabel="speed (m/s)", ylim=(0, None))
    gap.set(ylabel="gap to the leader (m)", ylim=(min(0.0, _smallest_gap(traces)), None))
    acceleration.set(ylabel="acceleration (m/s^2)")
    jerk.set(ylabel="jerk (m/s^3)", xlabel="time since the episode's start (s)")
    jerk.set_xlim(-0.01 * end, 1.01 * end)  # a margin: a spike at the first step stays visible
    for axis in axes:
        axis.grid(alpha=0.3)
    speed.legend(fontsize=8, loc="lower right")
    jerk.legend(fontsize=8, loc="lower right")
    fig.suptitle(title + "\ndotted verticals: lane changes started (driver's colour)")
    fig.savefig(path, dpi=DPI)
    plt.close(fig)


def _jerk_reach(traces: dict[str, EpisodeTrace]) -> float:
    """Half the jerk axis: a little beyond the largest jerk, at least twice the limit."""
    values = [np.abs(t.jerk[np.isfinite(t.jerk)]) for t in traces.values()]
    return max(2.0 * JERK_COMFORT_LIMIT, 1.1 * float(np.concatenate([*values, [0.0]]).max()))


def _smallest_gap(traces: dict[str, EpisodeTrace]) -> float:
    """The smallest gap to a leader drawn (negative on an overlap: a collision); 0 without any."""
    gaps = np.concatenate([t.gap[np.isfinite(t.gap)] for t in traces.values()] + [np.zeros(1)])
    return float(gaps.min())
