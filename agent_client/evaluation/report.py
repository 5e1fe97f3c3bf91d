"""Write an evaluation out: ``metrics.json``, ``report.md`` and the figures (Figs. 9, 10, 13).

`build_metrics` computes every number; the markdown is written from that dictionary only, so
everything the report says is in ``metrics.json`` too. Besides the paper's figures the report
draws chosen episodes (`trajectory_plan`): by default the first seed and the policy's most
critical episode, each driver's time-space diagram and the drivers' time series on that seed.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from agent_client.errors import UsageError
from agent_client.evaluation.evaluate import ROLE_LABELS, EpisodeRecord, Evaluation
from agent_client.evaluation.markdown import render_markdown
from agent_client.evaluation.paper import PAPER
from agent_client.evaluation.plots import (
    plot_jerk_distribution,
    plot_safety,
    plot_speed_distribution,
)
from agent_client.evaluation.route_plots import plot_route_changes
from agent_client.evaluation.summaries import summarise, table2
from agent_client.evaluation.targets import targets_met
from agent_client.evaluation.trajectory_plots import plot_time_series, plot_time_space

SPEED_FIGURE = "speed_distribution.png"
JERK_FIGURE = "jerk_distribution.png"
SAFETY_FIGURE = "safety.png"
ROUTE_FIGURE = "route_change.png"


def _ratio(numerator: float | None, denominator: float | None) -> float | None:
    if numerator is None or denominator is None or denominator == 0:
        return None
    return numerator / denominator


def build_metrics(
    evaluation: Evaluation, trajectory_seeds: Sequence[int] | None = None
) -> dict[str, Any]:
    """Every figure of the report as plain JSON-ready values (`trajectory_seeds`: the episodes
    to draw, default `trajectory_plan`'s choice)."""
    drivers = {
        role: {"spec": run.spec, **summarise(run.records)}
        for role, run in evaluation.drivers().items()
    }
    lanes = evaluation.lanes
    return {
        "scenario": evaluation.scenario,
        "seeds": list(evaluation.seeds),
        "episodes": len(evaluation.seeds),
        "options": dict(evaluation.options),
        "versions": dict(evaluation.versions),
        "command": evaluation.command,
        "lanes": lanes,
        "multi_lane": lanes > 1,
        "drivers": drivers,
        "comparison": _comparison(drivers["policy"], drivers["baseline"]),
        "lane_changing": _lane_changing(evaluation, drivers) if lanes > 1 else None,
        "paper": PAPER,
        "figures": {
            "speed_distribution": SPEED_FIGURE,
            "jerk_distribution": JERK_FIGURE,
            "safety": SAFETY_FIGURE if _any_conflict(drivers) else None,
            "trajectories": trajectory_plan(evaluation, trajectory_seeds),
            "route_change": _route_plan(evaluation),
        },
    }


def _route_plan(evaluation: Evaluation) -> dict[str, Any] | None:
    """The seed whose route changes the report draws: the first on which the policy made one
    (else the baseline), with its file; None where no driver made one."""
    drivers = evaluation.drivers()
    for role in ("policy", "baseline"):
        for index, record in enumerate(drivers[role].records):
            if record.route_changes and record.trace is not None:
                return {"seed": evaluation.seeds[index], "file": ROUTE_FIGURE}
    return None


def _any_conflict(drivers: dict[str, Any]) -> bool:
    """Whether any driver had a conflict (the safety figure is drawn only then)."""
    return any(d["safety"] and d["safety"]["conflicts"] for d in drivers.values())


def _comparison(policy: dict[str, Any], baseline: dict[str, Any]) -> dict[str, Any]:
    """The policy against the baseline: speed ratio, room to the ceiling, the targets met."""
    per_episode = baseline["per_episode"]
    ceiling_over_baseline = [
        c / v
        for c, v in zip(per_episode["ceiling_speed"], per_episode["average_speed"], strict=True)
        if c is not None and v > 0
    ]
    return {
        "speed_ratio_policy_to_baseline": _ratio(
            policy["average_speed"], baseline["average_speed"]
        ),
        "ceiling_over_baseline": float(np.mean(ceiling_over_baseline))
        if ceiling_over_baseline
        else None,
        "targets": targets_met(policy, baseline),
    }


def _lane_changing(evaluation: Evaluation, drivers: dict[str, Any]) -> dict[str, Any]:
    """Table 2 from the training log and the integrated policy against the CF-only one."""
    rows = evaluation.training_rows
    policy, cf = drivers["policy"], drivers.get("cf_policy")
    return {
        "table2": None
        if rows is None
        else {
            "run": evaluation.run_folder,
            "lanes": evaluation.lanes,
            "rows": table2(rows, evaluation.lanes, evaluation.table2_bins),
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


def write_report(
    out: Path, evaluation: Evaluation, trajectory_seeds: Sequence[int] | None = None
) -> Path:
    """Write metrics.json, report.md and the figures into `out`; returns the report's path.

    `trajectory_seeds` chooses the episodes drawn one by one (`trajectory_plan`).
    """
    out.mkdir(parents=True, exist_ok=True)
    metrics = _json_ready(build_metrics(evaluation, trajectory_seeds))
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, allow_nan=False) + "\n")
    plot_speed_distribution(metrics, out / SPEED_FIGURE)
    jerks = {
        role: np.concatenate([r.jerks for r in run.records])
        for role, run in evaluation.drivers().items()
    }
    plot_jerk_distribution(jerks, metrics, out / JERK_FIGURE)
    plot_safety(metrics, out / SAFETY_FIGURE)
    _draw_trajectories(out, evaluation, metrics)
    _draw_route_change(out, evaluation, metrics)
    path = out / "report.md"
    path.write_text(render_markdown(metrics))
    return path


# --------------------------------------------------------------------------- chosen episodes


def check_trajectory_seeds(chosen: Sequence[int], seeds: Sequence[int]) -> None:
    """Refuse seeds that were not evaluated (`UsageError` naming them and the valid range)."""
    missing = [seed for seed in chosen if seed not in seeds]
    if missing:
        valid = f"{seeds[0]}..{seeds[-1]}" if len(seeds) > 1 else str(seeds[0]) if seeds else "none"
        raise UsageError(
            f"--trajectory-seeds {' '.join(map(str, missing))}: not among the evaluated seeds "
            f"({valid})"
        )


def most_critical(records: Sequence[EpisodeRecord]) -> tuple[int, str] | None:
    """Index and reason of the most critical episode: the first with a collision, else the
    smallest minimum TTC, else the smallest minimum time headway; None when none has either."""
    inf = math.inf

    def key(record: EpisodeRecord) -> tuple[int, float, float]:
        s = record.summary
        return (
            0 if s.collisions else 1,
            s.min_ttc if s.min_ttc is not None else inf,
            s.min_time_headway if s.min_time_headway is not None else inf,
        )

    if not records:
        return None
    index = min(range(len(records)), key=lambda i: key(records[i]))
    collided, ttc, headway = key(records[index])
    if not collided:
        return index, "the policy's most critical episode (a collision)"
    if ttc < inf:
        return index, f"the policy's most critical episode (smallest minimum TTC, {ttc:.2f} s)"
    if headway < inf:
        return index, (
            f"the policy's most critical episode (smallest minimum time headway, {headway:.2f} s)"
        )
    return None


def trajectory_plan(
    evaluation: Evaluation, chosen: Sequence[int] | None = None
) -> list[dict[str, Any]]:
    """The episodes drawn and their files: `chosen` seeds, or by default the first seed and the
    policy's `most_critical` episode (if another). Drivers without a trace are left out, and so
    is a seed none of them has one for."""
    seeds = list(evaluation.seeds)
    reasons: dict[int, list[str]] = {}
    if chosen is not None:
        check_trajectory_seeds(chosen, seeds)
        for seed in chosen:
            reasons.setdefault(seed, ["chosen (--trajectory-seeds)"])
    elif seeds:
        reasons[seeds[0]] = ["the first seed"]
        critical = most_critical(evaluation.policy.records)
        if critical is not None:
            reasons.setdefault(seeds[critical[0]], []).append(critical[1])
    plan = []
    for seed, why in reasons.items():
        index = seeds.index(seed)
        roles = [
            role
            for role, run in evaluation.drivers().items()
            if index < len(run.records) and run.records[index].trace is not None
        ]
        if roles:
            plan.append(
                {
                    "seed": seed,
                    "why": "; ".join(why),
                    "time_series": f"time_series_{seed}.png",
                    "time_space": {role: f"time_space_{seed}_{role}.png" for role in roles},
                }
            )
    return plan


def _draw_trajectories(out: Path, evaluation: Evaluation, metrics: dict[str, Any]) -> None:
    """The planned time-space diagrams and time series, into `out`."""
    drivers = evaluation.drivers()
    for entry in metrics["figures"]["trajectories"]:
        seed = entry["seed"]
        index = list(evaluation.seeds).index(seed)
        traces = {}
        for role, name in entry["time_space"].items():
            trace = drivers[role].records[index].trace
            assert trace is not None  # the plan holds drivers with a trace only
            traces[role] = trace
            title = (
                f"{ROLE_LABELS[role]} ({drivers[role].spec}) on {evaluation.scenario}, "
                f"seed {seed}: time-space diagram"
            )
            plot_time_space(trace, out / name, title)
        labels = {role: f"{ROLE_LABELS[role]} ({drivers[role].spec})" for role in traces}
        title = f"{evaluation.scenario}, seed {seed}: every driver on the same seed"
        plot_time_series(traces, labels, out / entry["time_series"], title)


def _draw_route_change(out: Path, evaluation: Evaluation, metrics: dict[str, Any]) -> None:
    """Every driver's first route change on the planned seed, side by side."""
    plan = metrics["figures"]["route_change"]
    if plan is None:
        return
    index = list(evaluation.seeds).index(plan["seed"])
    panels = {}
    for role, run in evaluation.drivers().items():
        record = run.records[index] if index < len(run.records) else None
        if record is None or record.trace is None:
            continue
        first = record.route_changes[0] if record.route_changes else None
        panels[role] = (f"{ROLE_LABELS[role]} ({run.spec})", record.trace, first)
    title = f"{evaluation.scenario}, seed {plan['seed']}: the first lane change towards the route"
    plot_route_changes(panels, out / plan["file"], title)


_IMAGE = re.compile(r"(!\[[^\]]*\]\()([^)/][^)]*\))")
_HEADING = re.compile(r"^(#+) ", re.MULTILINE)


def combine_reports(out: Path, parts: Sequence[Path], title: str) -> Path:
    """One report.md in `out` from the reports of several evaluations (each in its folder),
    in order, with their figures linked where they are."""
    out.mkdir(parents=True, exist_ok=True)
    sections = [f"# {title}\n"]
    for part in parts:
        text = (part / "report.md").read_text()
        relative = os.path.relpath(part, out).replace("\\", "/")
        text = _IMAGE.sub(rf"\g<1>{relative}/\g<2>", text)
        sections.append(_HEADING.sub(r"#\1 ", text))  # one level down, under the title
    path = out / "report.md"
    path.write_text("\n".join(sections))
    return path
