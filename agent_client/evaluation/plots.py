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

COLOURS = {
    "policy": "tab:blue",
    "baseline": "tab:orange",
    "reference": "tab:purple",
    "cf_policy": "tab:green",
}
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


def plot_safety(metrics: dict[str, Any], path: Path) -> bool:
    """SUMO's surrogate safety measures: the distribution of the conflicts' minimum TTC per
    driver, and conflicts and time exposed per km. False (nothing drawn) without a conflict."""
    drivers = {r: d["safety"] for r, d in metrics["drivers"].items() if d.get("safety")}
    if not any(figures["conflicts"] for figures in drivers.values()):
        return False
    plt = _pyplot()
    fig, (cdf, rates) = plt.subplots(
        1, 2, figsize=(10, 4.2), constrained_layout=True, width_ratios=(3, 2)
    )
    thresholds = next(iter(drivers.values()))["thresholds"]
    for role, figures in drivers.items():
        values = np.array(figures["conflict_min_ttcs"])
        label = f"{ROLE_LABELS[role]}: {figures['conflicts']} conflicts"
        if len(values):  # the empirical distribution, from 0 at 0 s to 1 at the plot's edge
            share = np.arange(len(values) + 2) / len(values)
            x = np.concatenate(([0.0], values, [thresholds["ttc_s"] * 1.05]))
            cdf.step(x, np.minimum(share, 1.0), where="post", color=COLOURS[role], label=label)
        else:
            cdf.plot([], [], color=COLOURS[role], label=label)
    cdf.axvline(thresholds["critical_ttc_s"], color="tab:red", ls="--", label="critical, 1.5 s")
    cdf.axvline(thresholds["ttc_s"], color="k", ls=":", label=f"conflict, {thresholds['ttc_s']} s")
    cdf.set(
        title="Minimum TTC of each conflict (SUMO's SSM device)",
        xlabel="minimum time to collision (s)",
        ylabel="share of the driver's conflicts",
        xlim=(0, thresholds["ttc_s"] * 1.05),
        ylim=(0, 1.02),
    )
    cdf.legend(fontsize=8, loc="upper left")
    names = ("conflicts_per_km", "ttc_exposed_s_per_km")
    labels = ("conflicts per km", "s below TTC 3 s per km")
    width = 0.8 / len(drivers)
    for i, (role, figures) in enumerate(drivers.items()):
        heights = [figures[name] or 0.0 for name in names]
        x = np.arange(len(names)) + (i - (len(drivers) - 1) / 2) * width
        bars = rates.bar(x, heights, width, color=COLOURS[role], label=ROLE_LABELS[role])
        rates.bar_label(bars, fmt="%.2f", fontsize=7)
    rates.set_xticks(np.arange(len(names)), labels, fontsize=8)
    rates.set(title="Per km driven", ylim=(0, None))
    rates.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True
