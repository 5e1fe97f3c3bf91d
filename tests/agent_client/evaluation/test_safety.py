"""The surrogate safety measures' figures, table and picture, from hand-built records."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from agent_client.evaluation.markdown import render_markdown
from agent_client.evaluation.plots import plot_safety
from agent_client.evaluation.report import build_metrics, write_report
from agent_client.evaluation.safety import safety_figures
from protocol.messages import Conflict, Safety
from tests.agent_client.evaluation.test_evaluate import synthetic_evaluation, synthetic_record

RAMMED = Conflict("veh.3", 40.0, 46.0, 0.4, 12.0, None, 2.5, 1.0, 4.0)
CLOSE = Conflict("veh.7", 80.0, 83.0, 2.2, 2.0, None, 0.8, 0.0, 0.5)


def with_safety(record: object, *conflicts: Conflict) -> object:
    exposed = sum(c.ttc_below for c in conflicts)  # these conflicts do not overlap in time
    return replace(record, safety=Safety(conflicts, 3.0, 3.0, 2.0, exposed))  # type: ignore[type-var]


def test_figures_pool_conflicts_and_normalise_by_distance() -> None:
    records = [
        with_safety(synthetic_record(0, 20.0, 1.0, 1), RAMMED, CLOSE),  # 2 km
        with_safety(synthetic_record(1, 20.0, 1.0, 1)),  # 2 km, no conflict
    ]
    figures = safety_figures(records)  # type: ignore[arg-type]
    assert figures is not None
    assert figures["episodes"] == 2 and figures["conflicts"] == 2
    assert figures["distance_km"] == pytest.approx(4.0)
    assert figures["conflicts_per_km"] == pytest.approx(0.5)
    assert figures["episodes_with_conflict"] == 1
    assert figures["critical_conflicts"] == 1  # 0.4 s < 1.5 s, 2.2 s is not
    assert figures["min_ttc"] == 0.4 and figures["max_drac"] == 12.0
    assert figures["min_pet"] is None
    assert figures["ttc_exposed_s_per_km"] == pytest.approx((2.5 + 0.8) / 4.0)
    assert figures["ttc_exposed_share"] == pytest.approx(3.3 / 200.0)
    assert figures["ttc_integral_per_km"] == pytest.approx(4.5 / 4.0)
    assert figures["conflict_min_ttcs"] == [0.4, 2.2]
    assert figures["per_episode_min_ttc"] == [0.4, None]


def test_no_figures_when_the_server_reported_none() -> None:
    assert safety_figures([synthetic_record(0, 20.0, 1.0, 1)]) is None


def test_the_report_has_the_table_and_the_picture(tmp_path: Path) -> None:
    evaluation = synthetic_evaluation(lanes=1)
    evaluation.policy.records = [with_safety(r, RAMMED) for r in evaluation.policy.records]  # type: ignore[misc]
    evaluation.baseline.records = [with_safety(r) for r in evaluation.baseline.records]  # type: ignore[misc]
    report = write_report(tmp_path, evaluation).read_text()
    section = report.split("## Surrogate safety measures")[1].split("\n## ")[0]
    assert (
        "| conflicts per km | " in section and "![surrogate safety measures](safety.png)" in section
    )
    assert "| conflicts with min TTC < 1.5 s | 4 | 0 |" in section
    picture = tmp_path / "safety.png"
    assert picture.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and picture.stat().st_size > 20_000


def test_without_conflicts_nothing_is_drawn_and_the_report_says_so(tmp_path: Path) -> None:
    evaluation = synthetic_evaluation(lanes=1)
    for run in (evaluation.policy, evaluation.baseline):
        run.records = [with_safety(r) for r in run.records]  # type: ignore[misc]
    metrics = build_metrics(evaluation)
    assert metrics["figures"]["safety"] is None
    assert not plot_safety(metrics, tmp_path / "safety.png")
    assert not (tmp_path / "safety.png").exists()
    assert "No driver had a conflict on these seeds" in render_markdown(metrics)


def test_a_server_without_the_device_is_named_not_zero() -> None:
    text = render_markdown(build_metrics(synthetic_evaluation(lanes=1)))
    section = text.split("## Surrogate safety measures")[1].split("\n## ")[0]
    assert "Not reported" in section and "0.00" not in section
