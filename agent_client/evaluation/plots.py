"""The report's figures: per-episode average speed (the paper's Figs. 9, 13) and jerk (Fig. 10).

Both read `agent_client.evaluation.report.build_metrics`' dictionary; matplotlib is imported
when a figure is drawn, with the file-only Agg backend.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from agent_client.constants import JERK_COMFORT_LIMIT
from agent_client.evaluation.evaluate import ROLE_LABELS

COLOURS = {"policy": "tab:blue", "baseline": "tab:orange", "cf_policy": "tab:green"}
"""Each driver role's colour, the same in both figures."""


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_speed_distribution(metrics: dict[str, Any], path: Path) -> None:
    """Fig. 9 (and 13): histogram of per-episode average speed for each driver."""
    plt = _pyplot()
    drivers = metrics["drivers"]
    speeds = {role: np.array(d["per_episode"]["average_speed"]) for role, d in drivers.items()}
    everything = np.concatenate(list(speeds.values()))
    low, high = float(everything.min()), float(everything.max())
    bins = np.linspace(low - 0.25, high + 0.25, max(6, min(30, len(everything) // 2 + 2)))
    fig, axis = plt.subplots(figsize=(7, 4.2), constrained_layout=True)
    for role, values in speeds.items():
        label = f"{ROLE_LABELS[role]} ({drivers[role]['spec']}): mean {values.mean():.2f} m/s"
        axis.hist(values, bins=list(bins), alpha=0.5, color=COLOURS[role], label=label)
        axis.axvline(values.mean(), color=COLOURS[role], ls="--")
    ceiling = drivers["baseline"]["ceiling_speed"]
    if ceiling is not None:
        axis.axvline(
            ceiling, color="k", ls=":", label=f"mean leader-at-entry ceiling {ceiling:.2f}"
        )
    axis.set(
        title=f"Average speed per episode on {metrics['scenario']} (cf. the paper's Fig. 9)",
        xlabel="average speed (m/s)",
        ylabel="episodes",
    )
    axis.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_jerk_distribution(
    jerks: dict[str, np.ndarray], metrics: dict[str, Any], path: Path
) -> None:
    """Fig. 10: distribution of jerk samples with the 5.6 m/s^3 comfort limit."""
    plt = _pyplot()
    drivers = metrics["drivers"]
    everything = np.concatenate([np.abs(v) for v in jerks.values()] + [np.zeros(1)])
    reach = max(2 * JERK_COMFORT_LIMIT, float(np.percentile(everything, 99.9)))
    bins = np.linspace(-reach, reach, 81)
    fig, axis = plt.subplots(figsize=(7, 4.2), constrained_layout=True)
    for role, values in jerks.items():
        share = drivers[role]["jerk_share_above_limit"]
        axis.hist(
            np.clip(values, -reach, reach),
            bins=list(bins),
            alpha=0.5,
            color=COLOURS[role],
            label=f"{ROLE_LABELS[role]}: {100 * share:.2f} % above {JERK_COMFORT_LIMIT}",
        )
    for sign in (-1, 1):
        label = f"comfort limit +/-{JERK_COMFORT_LIMIT} m/s^3" if sign > 0 else None
        axis.axvline(sign * JERK_COMFORT_LIMIT, color="tab:green", ls="--", label=label)
    axis.set(
        title="Jerk per simulation step (cf. the paper's Fig. 10)",
        xlabel="jerk (m/s^3), clipped to the plot range",
        ylabel="steps",
        yscale="log",
    )
    axis.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)
