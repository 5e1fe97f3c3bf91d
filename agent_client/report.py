"""Write an evaluation out: ``metrics.json``, ``report.md`` and the figures (Figs. 9, 10, 13).

`build_metrics` computes every number; the markdown is written from that dictionary only, so
everything the report says is in ``metrics.json`` too.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from agent_client.evaluation import PAPER, Evaluation, summarise, table2
from agent_client.metrics import JERK_COMFORT_LIMIT

SPEED_FIGURE = "speed_distribution.png"
JERK_FIGURE = "jerk_distribution.png"
LABELS = {"policy": "policy", "baseline": "baseline", "cf_policy": "CF-only policy"}


def _ratio(numerator: float | None, denominator: float | None) -> float | None:
    if numerator is None or denominator is None or denominator == 0:
        return None
    return numerator / denominator


def build_metrics(evaluation: Evaluation) -> dict[str, Any]:
    """Every figure of the report as plain JSON-ready values."""
    from agent_client.train import targets_met

    drivers = {
        role: {"spec": run.spec, **summarise(run.records)}
        for role, run in evaluation.drivers().items()
    }
    policy, baseline = drivers["policy"], drivers["baseline"]
    ceiling_over_baseline = [
        c / v
        for c, v in zip(
            baseline["per_episode"]["ceiling_speed"],
            baseline["per_episode"]["average_speed"],
            strict=True,
        )
        if c is not None and v > 0
    ]

    def target_inputs(figures: dict[str, Any]) -> dict[str, float]:
        ratio = figures["speed_ratio_to_ceiling"]
        return {
            "collisions_per_episode": figures["collisions_per_episode"],
            "jerk_share_above_limit": figures["jerk_share_above_limit"],
            "headway_share_below_1s": figures["headway"]["share_below_1s"],
            "average_speed": figures["average_speed"],
            "speed_ratio_to_ceiling": ratio if ratio is not None else math.nan,
        }

    lanes = evaluation.lanes
    metrics: dict[str, Any] = {
        "scenario": evaluation.scenario,
        "seeds": list(evaluation.seeds),
        "episodes": len(evaluation.seeds),
        "options": dict(evaluation.options),
        "versions": dict(evaluation.versions),
        "command": evaluation.command,
        "lanes": lanes,
        "multi_lane": lanes > 1,
        "drivers": drivers,
        "comparison": {
            "speed_ratio_policy_to_baseline": _ratio(
                policy["average_speed"], baseline["average_speed"]
            ),
            "ceiling_over_baseline": float(np.mean(ceiling_over_baseline))
            if ceiling_over_baseline
            else None,
            "targets": targets_met(target_inputs(policy), target_inputs(baseline)),
        },
        "lane_changing": None,
        "paper": PAPER,
        "figures": {"speed_distribution": SPEED_FIGURE, "jerk_distribution": JERK_FIGURE},
    }
    if lanes > 1:
        rows = evaluation.training_rows
        cf = drivers.get("cf_policy")
        metrics["lane_changing"] = {
            "table2": None
            if rows is None
            else {
                "run": evaluation.run_folder,
                "lanes": lanes,
                "rows": table2(rows, lanes, evaluation.table2_bins),
            },
            "integrated_vs_cf": None
            if cf is None
            else {
                "integrated_average_speed": policy["average_speed"],
                "cf_average_speed": cf["average_speed"],
                "gain": policy["average_speed"] / cf["average_speed"] - 1.0
                if cf["average_speed"] > 0
                else None,
            },
        }
    return metrics


# --------------------------------------------------------------------------- markdown


def _f(value: Any, digits: int = 2, suffix: str = "") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    return f"{value:.{digits}f}{suffix}"


def _pct(value: Any, digits: int = 1) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    return f"{100 * value:.{digits}f} %"


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return lines


def _cf_section(metrics: dict[str, Any]) -> list[str]:
    drivers = metrics["drivers"]
    roles = list(drivers)
    paper = metrics["paper"]["cf"]
    header = ["figure", *(f"{LABELS[r]} (`{drivers[r]['spec']}`)" for r in roles), "paper"]

    def row(name: str, cells: list[str], paper_cell: str = "") -> list[str]:
        return [name, *cells, paper_cell]

    each = [drivers[r] for r in roles]
    rows = [
        row(
            "average speed, m/s: mean (sd)",
            [f"{_f(d['average_speed'])} ({_f(d['average_speed_sd'])})" for d in each],
            f"DRL {paper['drl_average_speed']}, IDM {paper['idm_average_speed']}",
        ),
        row("leader-at-entry ceiling, m/s (mean)", [_f(d["ceiling_speed"]) for d in each]),
        row(
            "average speed / ceiling (mean of episodes)",
            [_f(d["speed_ratio_to_ceiling"], 3) for d in each],
            "not reported",
        ),
        row(
            "collisions per episode (episodes with one)",
            [f"{_f(d['collisions_per_episode'])} ({d['episodes_with_collision']})" for d in each],
        ),
        row(
            f"jerk samples above {JERK_COMFORT_LIMIT} m/s^3",
            [_pct(d["jerk_share_above_limit"], 2) for d in each],
            f"DRL {_pct(paper['drl_jerk_share_above_limit'])}",
        ),
        row("max abs jerk, m/s^3", [_f(d["max_abs_jerk"]) for d in each]),
        row("time headway < 1 s (share)", [_pct(d["headway"]["share_below_1s"]) for d in each]),
        row(
            "time headway, s: mean / median",
            [f"{_f(d['headway']['mean'])} / {_f(d['headway']['median'])}" for d in each],
        ),
        row("min time headway, s", [_f(d["min_time_headway"]) for d in each]),
        row("min TTC, s", [_f(d["ttc"]["min"]) for d in each]),
        row("TTC < 4 s (share of leader steps)", [_pct(d["ttc"]["share_below_4s"]) for d in each]),
        row(
            "end reasons",
            [", ".join(f"{k} {v}" for k, v in d["end_reasons"].items()) for d in each],
        ),
    ]  # fmt: skip
    comparison = metrics["comparison"]
    ratio = comparison["speed_ratio_policy_to_baseline"]
    ceiling = comparison["ceiling_over_baseline"]
    gain = f"{100 * (ratio - 1):+.1f} %" if ratio is not None else "n/a"
    lines = ["## Car following: efficiency, comfort, safety (Figs. 9-10)", ""]
    lines += _table(header, rows)
    lines += [
        "",
        f"Policy vs baseline average speed: **{gain}** (the paper: DRL "
        f"{paper['drl_average_speed']} m/s vs IDM {paper['idm_average_speed']} m/s, "
        f"+{100 * paper['drl_gain_over_idm']:.1f} %).",
        "",
    ]
    ceiling_text = f"{100 * (ceiling - 1):+.1f} %" if ceiling is not None else "n/a"
    if metrics["multi_lane"]:
        lines.append(
            "The ceiling is the average speed the ego would have had arriving together with the "
            "vehicle ahead of it at entry. On several lanes the ego can overtake that vehicle, so "
            f"here it is a reference, not a bound (it is {ceiling_text} over the baseline)."
        )
    else:
        lines.append(
            "**The ceiling.** On one lane the ego cannot arrive before the vehicle that was ahead "
            "of it when it entered, and that vehicle's trip does not depend on the ego: arriving "
            f"together with it is the best any driver can do here, {ceiling_text} over the "
            "baseline on these seeds. A gain like the paper's +7.9 % over IDM is therefore out of "
            "reach without collisions (or a baseline far below the traffic's pace): judge a "
            "speed gain against the ceiling, not against the paper's figure."
        )
    targets = comparison["targets"]
    lines += [
        "",
        "Targets of the training's greedy evaluations (docs/learner.md), for the policy: "
        + ", ".join(f"{name} {'yes' if ok else 'no'}" for name, ok in targets.items())
        + ".",
        "",
        f"![Fig. 9: per-episode average speed]({metrics['figures']['speed_distribution']})",
        "",
        "Fig. 9 (ours): per-episode average speed of each driver on the same seeds; dashed "
        "lines are the means, the dotted line the mean leader-at-entry ceiling.",
        "",
        f"![Fig. 10: distribution of jerk]({metrics['figures']['jerk_distribution']})",
        "",
        f"Fig. 10 (ours): jerk at the simulator's step (change of the realised acceleration over "
        f"one step), all steps of all episodes; the dashed lines mark +/-{JERK_COMFORT_LIMIT} "
        "m/s^3, the paper's comfort limit (2.6 % of its DRL samples were beyond it).",
        "",
    ]  # fmt: skip
    return lines


def _lc_section(metrics: dict[str, Any]) -> list[str]:
    drivers = metrics["drivers"]
    paper = metrics["paper"]["lc"]
    lc = metrics["lane_changing"]
    lines = ["## Lane changing (Tables 2-3, Fig. 13)", ""]
    lines += ["### Table 2: lane-change decisions over training", ""]
    table = lc["table2"]
    if table is None:
        lines.append("Not computed: pass `--run runs/NAME` to read the run's `episodes.csv`.")
    else:
        rows = [
            [
                row["episodes"],
                _f(row["instructions_per_episode"], 1),
                _pct(row["success_rate"]),
                _f(row["reward_of_successful_lc"], 3),
                _f(row["frequency"]),
            ]
            for row in table["rows"]
        ]
        last = paper["table2_last_row"]
        rows.append(
            [
                f"paper {last['episodes']}",
                str(last["instructions_per_episode"]),
                _pct(last["success_rate"]),
                _f(last["reward_of_successful_lc"]),
                _f(last["lc_frequency"]),
            ]
        )
        lines += [f"From `{table['run']}/episodes.csv`, {table['lanes']} lanes.", ""]
        lines += _table(
            [
                "training episodes",
                "LC instructions per episode",
                "success rate (started / instructions)",
                "avg. reward of successful LC",
                "actual LC frequency (veh/km/lane)",
            ],
            rows,
        )
        lines += [
            "",
            "Instructions are lane changes started plus refused (any reason: gap too small, no "
            "lane, one already in progress). The reward of a successful lane change is the "
            "training reward of the step whose instruction started it (n/a: no change in the "
            "range, or a log without that column).",
        ]
    lines += ["", "### Lane changes in the evaluation episodes", ""]
    rows = []
    for role, d in drivers.items():
        stats = d["lane_changes"]
        refused = ", ".join(f"{k} {v}" for k, v in stats["refused_by_reason"].items()) or "none"
        if stats.get("aborted"):
            refused += f"; started but aborted by the simulator: {stats['aborted']}"
        rows.append(
            [
                LABELS[role],
                _f(stats["instructions_per_episode"], 1),
                _pct(stats["success_rate"]),
                refused,
                _f(stats["frequency"]),
            ]
        )
    ngsim = paper["lc_frequency_ngsim"]
    rows.append(["paper (converged)", "", "", "", _f(paper["lc_frequency"])])
    rows += [[f"NGSIM {name}", "", "", "", _f(value)] for name, value in ngsim.items()]
    lines += _table(
        ["driver", "instructions per episode", "success rate", "refused by reason", "veh/km/lane"],
        rows,
    )
    lines += [
        "",
        "Frequency = lane changes started / (km driven x lanes). NGSIM's traffic was heavier "
        "(about 1600 and 1300 veh/h/lane) than the paper's 700 veh/h/lane.",
        "",
        "### Table 3: time headways in the target lane when a lane change starts",
        "",
    ]
    rows = [
        [name, _f(value["lead"]), _f(value["lag"]), ""] for name, value in paper["table3"].items()
    ]
    for role, d in drivers.items():
        t3 = d["table3"]
        rows.append(
            [
                f"ours: {LABELS[role]}",
                _f(t3["lead"]),
                _f(t3["lag"]),
                f"{t3['lane_changes']} (lead {t3['lead_samples']}, lag {t3['lag_samples']})",
            ]
        )
    lines += _table(
        ["", "avg. lead time headway (s)", "avg. lag time headway (s)", "lane changes (samples)"],
        rows,
    )
    lines += [
        "",
        "Lead (lag) headway: gap to the leader (follower) in the target lane at the observation "
        "before the lane change started, divided by the ego's speed; a lane without that vehicle "
        "gives no sample.",
        "",
        "### The integrated model against car following only (Fig. 13)",
        "",
    ]
    versus = lc["integrated_vs_cf"]
    if versus is None:
        lines.append("Not computed: pass `--cf-policy FILE` (a car-following-only policy).")
    else:
        lines += _table(
            ["", "integrated (CF + LC), m/s", "CF only, m/s", "gain"],
            [
                [
                    "ours",
                    _f(versus["integrated_average_speed"]),
                    _f(versus["cf_average_speed"]),
                    f"{100 * versus['gain']:+.1f} %" if versus["gain"] is not None else "n/a",
                ],
                [
                    "paper",
                    _f(paper["integrated_average_speed"]),
                    _f(paper["cf_average_speed"]),
                    f"+{100 * paper['integrated_gain_over_cf']:.1f} %",
                ],
            ],
        )
        lines += ["", "Fig. 9 above shows the CF-only policy's speed distribution too."]
    lines.append("")
    return lines


def render_markdown(metrics: dict[str, Any]) -> str:
    """The report as markdown, from `build_metrics`' dictionary."""
    versions = metrics["versions"]
    drivers = metrics["drivers"]
    title = f"# Evaluation on `{metrics['scenario']}`: `{drivers['policy']['spec']}` vs "
    title += f"`{drivers['baseline']['spec']}`"
    seeds = metrics["seeds"]
    seed_text = f"{seeds[0]}..{seeds[-1]}" if len(seeds) > 1 else str(seeds[0])
    options = ", ".join(f"{k}={v}" for k, v in metrics["options"].items()) or "defaults"
    lines = [
        title,
        "",
        "## Setting and how to rerun",
        "",
        f"* scenario `{metrics['scenario']}` ({metrics['lanes']} lane(s)), options: {options}",
        f"* {metrics['episodes']} episodes per driver, the same seeds for all: {seed_text}",
        *(f"* {name}: {value}" for name, value in versions.items()),
        "",
        "```",
        metrics["command"],
        "```",
        "",
    ]
    lines += _cf_section(metrics)
    if metrics["lane_changing"] is not None:
        lines += _lc_section(metrics)
    else:
        lines += [
            "## Lane changing (Tables 2-3, Fig. 13)",
            "",
            "Not applicable: the scenario has one lane (evaluate on `cflc` for these tables).",
            "",
        ]
    lines += [
        f"Every figure above is in `metrics.json`. Paper: {metrics['paper']['source']}.",
        "",
    ]
    return "\n".join(lines)


# --------------------------------------------------------------------------- figures


def plot_speed_distribution(metrics: dict[str, Any], path: Path) -> None:
    """Fig. 9 (and 13): histogram of per-episode average speed for each driver."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    drivers = metrics["drivers"]
    speeds = {role: np.array(d["per_episode"]["average_speed"]) for role, d in drivers.items()}
    everything = np.concatenate(list(speeds.values()))
    low, high = float(everything.min()), float(everything.max())
    bins = np.linspace(low - 0.25, high + 0.25, max(6, min(30, len(everything) // 2 + 2)))
    fig, axis = plt.subplots(figsize=(7, 4.2), constrained_layout=True)
    colours = {"policy": "tab:blue", "baseline": "tab:orange", "cf_policy": "tab:green"}
    for role, values in speeds.items():
        label = f"{LABELS[role]} ({drivers[role]['spec']}): mean {values.mean():.2f} m/s"
        axis.hist(values, bins=list(bins), alpha=0.5, color=colours[role], label=label)
        axis.axvline(values.mean(), color=colours[role], ls="--")
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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    drivers = metrics["drivers"]
    everything = np.concatenate([np.abs(v) for v in jerks.values()] + [np.zeros(1)])
    reach = max(2 * JERK_COMFORT_LIMIT, float(np.percentile(everything, 99.9)))
    bins = np.linspace(-reach, reach, 81)
    fig, axis = plt.subplots(figsize=(7, 4.2), constrained_layout=True)
    colours = {"policy": "tab:blue", "baseline": "tab:orange", "cf_policy": "tab:green"}
    for role, values in jerks.items():
        share = drivers[role]["jerk_share_above_limit"]
        axis.hist(
            np.clip(values, -reach, reach),
            bins=list(bins),
            alpha=0.5,
            color=colours[role],
            label=f"{LABELS[role]}: {100 * share:.2f} % above {JERK_COMFORT_LIMIT}",
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


# --------------------------------------------------------------------------- writing


def _json_ready(value: Any) -> Any:
    """NaN and infinities become null (strict JSON); tuples become lists."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): _json_ready(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_ready(v) for v in value]
    if isinstance(value, np.generic):
        return _json_ready(value.item())
    return value


def write_report(out: Path, evaluation: Evaluation) -> Path:
    """Write metrics.json, report.md and the figures into `out`; returns the report's path."""
    out.mkdir(parents=True, exist_ok=True)
    metrics = _json_ready(build_metrics(evaluation))
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, allow_nan=False) + "\n")
    plot_speed_distribution(metrics, out / SPEED_FIGURE)
    jerks = {
        role: np.concatenate([r.jerks for r in run.records])
        for role, run in evaluation.drivers().items()
    }
    plot_jerk_distribution(jerks, metrics, out / JERK_FIGURE)
    path = out / "report.md"
    path.write_text(render_markdown(metrics))
    return path
