"""Evaluation metrics against hand-computed cases, and the report writer on synthetic records."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from agent_client.constants import PAPER_SPEED_LIMIT
from agent_client.drivers.episode import Episode
from agent_client.evaluation.evaluate import (
    DriverRun,
    EpisodeRecord,
    Evaluation,
    LaneChangeGap,
    lane_change_gaps,
)
from agent_client.evaluation.metrics import EpisodeSummary, aggregate
from agent_client.evaluation.report import JERK_FIGURE, SPEED_FIGURE, write_report
from agent_client.evaluation.summaries import (
    headway_stats,
    lane_change_frequency,
    lane_change_stats,
    summarise,
    table2,
    table3,
    ttc_stats,
)
from protocol.messages import AppliedAction, Ego, Events, Neighbour, Neighbours
from tests.protocol.test_codec import make_observation

ABSENT = Neighbour(False, 200.0, 0.0, 0.0)


def test_headway_stats_hand_computed() -> None:
    stats = headway_stats(np.array([0.5, 1.5, 2.0, 0.8]))
    assert stats["share_below_1s"] == pytest.approx(0.5)
    assert stats["mean"] == pytest.approx(1.2)
    assert stats["median"] == pytest.approx(1.15)
    assert stats["samples"] == 4
    assert headway_stats(np.array([]))["mean"] is None


def test_ttc_share_is_over_steps_with_a_leader() -> None:
    stats = ttc_stats(np.array([3.0, 5.0, 10.0, 3.9]), leader_steps=8)
    assert stats["min"] == pytest.approx(3.0)
    assert stats["share_below_4s"] == pytest.approx(2 / 8)
    assert ttc_stats(np.array([]), 0) == {"min": None, "share_below_4s": 0.0}


def test_lane_change_frequency_per_km_per_lane() -> None:
    # 3 lane changes over 2 km of a 3-lane road: 3 / (2 x 3) = 0.5 veh/km/lane.
    assert lane_change_frequency(3, 2000.0, 3) == pytest.approx(0.5)
    assert lane_change_frequency(1, 500.0, 1) == pytest.approx(2.0)
    assert lane_change_frequency(1, 0.0, 3) is None


def test_lane_changes_the_simulator_gave_up_are_not_counted_as_made() -> None:
    stats = lane_change_stats(4, 6, 2000.0, 3, 2, aborted=1)
    assert stats["instructions_per_episode"] == 5.0 and stats["success_rate"] == 0.4
    assert stats["frequency"] == pytest.approx(3 / 6)  # 3 made over 2 km of 3 lanes
    assert stats["aborted"] == 1


def lc_observations() -> list:
    """Three observations: a left change from 10 m/s, then a right change with no lag vehicle."""
    neighbours = Neighbours(
        left_leader=Neighbour(True, 30.0, 3.2, 12.0, "LL"),
        left_follower=Neighbour(True, 20.0, 3.2, 9.0, "LF"),
        leader=Neighbour(True, 15.0, 0.0, 10.0, "L"),
        follower=ABSENT,
        right_leader=Neighbour(True, 40.0, -3.2, 11.0, "RL"),
        right_follower=ABSENT,
    )
    return [
        make_observation(seq=0, time=30.0, ego=Ego(10.0, 0.0, 1, 3, 100.0, PAPER_SPEED_LIMIT),
                         neighbours=neighbours, events=Events(), action=AppliedAction(0, 0, 0, 0)),
        make_observation(seq=1, time=30.1, ego=Ego(8.0, 0.0, 1, 3, 101.0, PAPER_SPEED_LIMIT),
                         neighbours=neighbours, events=Events(lane_change_started=True),
                         action=AppliedAction(0, 1, 0, 1)),
        make_observation(seq=2, time=30.2, ego=Ego(8.0, 0.0, 2, 3, 102.0, PAPER_SPEED_LIMIT),
                         neighbours=neighbours, events=Events(lane_change_started=True),
                         action=AppliedAction(0, -1, 0, -1)),
    ]  # fmt: skip


def test_lane_change_headways_at_the_decision() -> None:
    gaps = lane_change_gaps(lc_observations())
    # Left at 10 m/s (the observation before the start): lead 30/10, lag 20/10.
    # Right at 8 m/s: lead 40/8, no lag vehicle.
    assert gaps == [LaneChangeGap(1, 3.0, 2.0), LaneChangeGap(-1, 5.0, None)]
    row = table3(gaps)
    assert row["lead"] == pytest.approx(4.0)
    assert row["lag"] == pytest.approx(2.0)
    assert (row["lane_changes"], row["lead_samples"], row["lag_samples"]) == (2, 2, 1)
    assert table3([])["lead"] is None


def test_table2_ranges_from_episode_rows() -> None:
    rows = [
        {"episode": str(e), "lane_changes_started": str(s), "lane_changes_refused": str(r),
         "distance": str(d)}
        for e, s, r, d in [(1, 2, 8, 1000), (2, 0, 10, 1000), (3, 1, 1, 2000), (4, 1, 0, 1000)]
    ]  # fmt: skip
    table = table2(rows, lanes=3, bins=2)
    assert [r["episodes"] for r in table] == ["1-2", "3-4"]
    assert table[0]["instructions_per_episode"] == pytest.approx(10.0)  # (2+8+0+10)/2
    assert table[0]["success_rate"] == pytest.approx(0.1)  # 2/20
    assert table[0]["frequency"] == pytest.approx(2 / (2.0 * 3))
    assert table[1]["success_rate"] == pytest.approx(2 / 3)
    assert table[1]["frequency"] == pytest.approx(2 / (3.0 * 3))
    assert table[0]["reward_of_successful_lc"] is None  # a log without the column
    for row, reward in zip(rows, ["0.5", "0", "0.25", "-1.0"], strict=True):
        row["successful_lc_reward"] = reward
    table = table2(rows, lanes=3, bins=2)
    assert table[0]["reward_of_successful_lc"] == pytest.approx(0.5 / 2)
    assert table[1]["reward_of_successful_lc"] == pytest.approx((0.25 - 1.0) / 2)
    with pytest.raises(ValueError, match="lane_changes_started"):
        table2([{"episode": "1"}], lanes=3)


def test_episode_record_from_episode() -> None:
    recorder = Episode(episode=0, seed=5, step_length=0.1)
    for observation, reward in zip(lc_observations(), [0.0, 0.75, -0.25], strict=True):
        recorder.add(observation, reward)
    record = EpisodeRecord.from_episode(recorder)
    assert record.leader_steps == 3
    assert record.lane_count == 3
    assert record.headways == pytest.approx([1.5, 15.0 / 8.0, 15.0 / 8.0])
    assert len(record.ttcs) == 0  # the ego never closes in
    assert len(record.jerks) == 2
    assert record.summary.lane_changes_started == 2
    assert record.summary.successful_lc_reward == pytest.approx(0.75 - 0.25)


def test_summarise_reports_the_aggregate_figures_under_their_names() -> None:
    recorder = Episode(episode=0, seed=5, step_length=0.1)
    for observation, reward in zip(lc_observations(), [0.0, 0.75, -0.25], strict=True):
        recorder.add(observation, reward)
    records = [EpisodeRecord.from_episode(recorder)] * 2
    figures = summarise(records)
    totals = aggregate([r.summary for r in records])
    assert {k: figures[k] for k in totals} == pytest.approx(totals, nan_ok=True)
    # The flat share and the one of the pooled samples are one figure.
    assert figures["headway_share_below_1s"] == figures["headway"]["share_below_1s"]


# --------------------------------------------------------------------------- the report


def synthetic_record(seed: int, speed: float, jerk: float, lanes: int) -> EpisodeRecord:
    summary = EpisodeSummary(
        episode=seed, seed=seed, steps=1000, reason="end_of_road", duration=100.0,
        distance=100.0 * speed, average_speed=speed, collisions=0,
        jerk_share_above_limit=0.01, max_abs_jerk=abs(jerk), headway_share_below_1s=0.02,
        min_time_headway=0.8, min_ttc=3.5, ceiling_speed=speed * 1.02,
        speed_ratio_to_ceiling=1 / 1.02, total_reward=10.0, lane_changes_started=2,
        lane_changes_refused=6,
    )  # fmt: skip
    return EpisodeRecord(
        summary=summary,
        jerks=np.array([0.1, -0.2, jerk, 0.0]),
        headways=np.array([0.8, 1.5, 2.0]),
        ttcs=np.array([3.5, 8.0]),
        leader_steps=900,
        lane_count=lanes,
        lane_change_gaps=[LaneChangeGap(1, 4.0, 5.0), LaneChangeGap(-1, 2.0, None)],
        refusals={"gap_too_small": 6},
    )


def synthetic_evaluation(lanes: int) -> Evaluation:
    def run(spec: str, base: float) -> DriverRun:
        return DriverRun(spec, [synthetic_record(s, base + s, 6.0, lanes) for s in range(4)])

    rows = [
        {"episode": str(e), "lane_changes_started": "1", "lane_changes_refused": "9",
         "distance": "2000"}
        for e in range(1, 21)
    ]  # fmt: skip
    return Evaluation(
        scenario="cflc" if lanes > 1 else "cf",
        seeds=[0, 1, 2, 3],
        options={"max_episode_time": 100.0},
        versions={"backend version": "1.28.0", "agent_client version": "0.1.0"},
        command="agent-client evaluate --policy p.pt",
        policy=run("runs/x/policy.pt", 13.0),
        baseline=run("idm", 12.0),
        cf_policy=run("runs/cf/policy.pt", 12.5) if lanes > 1 else None,
        training_rows=rows if lanes > 1 else None,
        run_folder="runs/x" if lanes > 1 else None,
        table2_bins=4,
    )


def strict_json(path: Path) -> dict:
    def refuse(name: str) -> None:
        raise ValueError(f"non-standard JSON constant {name}")

    return json.loads(path.read_text(), parse_constant=refuse)


def test_report_on_a_multi_lane_evaluation_fills_every_section(tmp_path: Path) -> None:
    path = write_report(tmp_path, synthetic_evaluation(lanes=3))
    text = path.read_text()
    for heading in ("## Setting and how to rerun", "## Car following", "### Table 2",
                    "### Lane changes in the evaluation episodes", "### Table 3",
                    "### The integrated model against car following only"):  # fmt: skip
        assert heading in text
    assert "Not computed" not in text and "Not applicable" not in text
    assert "agent-client evaluate --policy p.pt" in text
    assert "1.28.0" in text and "12.44" in text and "4.70" in text and "0.63" in text
    metrics = strict_json(tmp_path / "metrics.json")
    assert set(metrics["drivers"]) == {"policy", "baseline", "cf_policy"}
    policy = metrics["drivers"]["policy"]
    assert policy["average_speed"] == pytest.approx(14.5)
    assert policy["headway"]["share_below_1s"] == pytest.approx(1 / 3)
    assert policy["ttc"]["share_below_4s"] == pytest.approx(4 / 3600)
    assert policy["table3"]["lead"] == pytest.approx(3.0)
    assert policy["table3"]["lag"] == pytest.approx(5.0)
    assert policy["lane_changes"]["success_rate"] == pytest.approx(0.25)
    lc = metrics["lane_changing"]
    assert len(lc["table2"]["rows"]) == 4
    assert lc["table2"]["rows"][0]["frequency"] == pytest.approx(5 / (10.0 * 3))
    assert lc["integrated_vs_cf"]["gain"] == pytest.approx(14.5 / 14.0 - 1)
    assert metrics["comparison"]["speed_ratio_policy_to_baseline"] == pytest.approx(14.5 / 13.5)
    assert metrics["paper"]["cf"]["drl_average_speed"] == 12.44
    assert {"scenario", "seeds", "versions", "command", "figures"} <= set(metrics)
    for figure in (SPEED_FIGURE, JERK_FIGURE):
        assert (tmp_path / figure).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_report_on_one_lane_says_lane_changing_does_not_apply(tmp_path: Path) -> None:
    path = write_report(tmp_path, synthetic_evaluation(lanes=1))
    text = path.read_text()
    assert "Not applicable: the scenario has one lane" in text
    assert "On one lane the ego cannot arrive before" in text
    metrics = strict_json(tmp_path / "metrics.json")
    assert metrics["lane_changing"] is None
    assert metrics["comparison"]["ceiling_over_baseline"] == pytest.approx(1.02)


def test_report_without_any_ceiling_says_so(tmp_path: Path) -> None:
    """A ring reports no leader-at-entry trip: the report says so instead of "n/a over"."""
    evaluation = synthetic_evaluation(lanes=1)
    for run in (evaluation.policy, evaluation.baseline):
        for record in run.records:
            record.summary.ceiling_speed = record.summary.speed_ratio_to_ceiling = None
    text = write_report(tmp_path, evaluation).read_text()
    assert "reported no leader-at-entry trip" in text and "n/a over the baseline" not in text
    assert strict_json(tmp_path / "metrics.json")["comparison"]["ceiling_over_baseline"] is None


def test_summarise_refuses_no_episodes() -> None:
    with pytest.raises(ValueError, match="no episodes"):
        summarise([])
