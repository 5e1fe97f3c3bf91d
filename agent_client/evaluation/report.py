"""Write an evaluation out: ``metrics.json``, ``report.md`` and the figures (Figs. 9, 10, 13).

`build_metrics` computes every number; the markdown is written from that dictionary only, so
everything the report says is in ``metrics.json`` too.
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

from agent_client.evaluation.evaluate import Evaluation
from agent_client.evaluation.markdown import render_markdown
from agent_client.evaluation.paper import PAPER
from agent_client.evaluation.plots import plot_jerk_distribution, plot_speed_distribution
from agent_client.evaluation.summaries import summarise, table2
from agent_client.evaluation.targets import targets_met

SPEED_FIGURE = "speed_distribution.png"
JERK_FIGURE = "jerk_distribution.png"


def _ratio(numerator: float | None, denominator: float | None) -> float | None:
    if numerator is None or denominator is None or denominator == 0:
        return None
    return numerator / denominator


def build_metrics(evaluation: Evaluation) -> dict[str, Any]:
    """Every figure of the report as plain JSON-ready values."""
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
        "figures": {"speed_distribution": SPEED_FIGURE, "jerk_distribution": JERK_FIGURE},
    }


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
