from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from agent_client.constants import PAPER_SPEED_LIMIT
from agent_client.drivers.episode import Episode
from agent_client.evaluation.metrics import (
    EpisodeSummary,
    aggregate,
    episode_summary,
    jerk_series,
    safety_rule_shares,
    time_headways,
    times_to_collision,
)
from protocol.messages import Ego, LeaderTrip, Neighbour, Neighbours
from tests.protocol.test_codec import make_observation


def test_jerk_from_an_acceleration_series() -> None:
    jerk, samples = jerk_series(np.array([0.0, 0.5, 0.5, -0.3]), np.array([0.0, 0.1, 0.2, 0.3]))
    assert jerk == pytest.approx([5.0, 0.0, -8.0])
    assert samples == 3


def test_jerk_with_long_decisions_happens_in_one_simulation_step() -> None:
    # Decisions every 1 s on a 0.1 s simulator: a change of 1 m/s^2 is a 10 m/s^3 jerk in one
    # step, and the interval holds 10 samples.
    times = np.array([0.0, 1.0, 2.0])
    jerk, samples = jerk_series(np.array([0.0, 1.0, 1.2]), times, step_length=0.1)
    assert jerk == pytest.approx([10.0, 2.0])
    assert samples == 20


def test_headway_skips_missing_leaders_and_standstill() -> None:
    gaps = np.array([20.0, np.nan, 10.0, 5.0])
    speeds = np.array([10.0, 10.0, 0.0, 5.0])
    assert time_headways(gaps, speeds) == pytest.approx([2.0, 1.0])


def test_ttc_only_when_closing_in() -> None:
    ttc = times_to_collision(np.array([20.0, 20.0]), np.array([15.0, 10.0]), np.array([10.0, 12.0]))
    assert ttc == pytest.approx([4.0])


def test_episode_summary_hand_computed() -> None:
    recorder = Episode(episode=1, seed=9)
    absent = Neighbour(False, 200.0, 0.0, 0.0)
    for i, (acc, gap) in enumerate([(0.0, 20.0), (0.7, 8.0), (0.7, 9.0), (0.0, 30.0)]):
        leader = Neighbour(True, gap, 0.0, 10.0)
        recorder.add(
            make_observation(
                seq=i,
                time=30.0 + 0.1 * i,
                ego=Ego(10.0, acc, 0, 1, 5.0 + i, PAPER_SPEED_LIMIT),
                neighbours=Neighbours(absent, absent, leader, absent, absent, absent),
                ceiling=LeaderTrip("l", 29.0, 30.5, 2000.0 / 1.5) if i == 3 else None,
            ),
            reward=1.0,
        )
    summary = episode_summary(recorder)
    assert summary.steps == 3
    assert summary.average_speed == pytest.approx(3.0 / 0.3)
    assert summary.jerk_share_above_limit == pytest.approx(2 / 3)  # +7, 0, -7 m/s^3
    assert summary.max_abs_jerk == pytest.approx(7.0)
    assert summary.headway_share_below_1s == pytest.approx(2 / 4)  # 0.8 s and 0.9 s
    assert summary.min_ttc is None  # never faster than the leader
    assert summary.total_reward == 3.0
    # Arriving with the leader at 30.5 s from entry at 30.0 s and 5 m: (2000 - 5) / 0.5
    assert summary.ceiling_speed == pytest.approx(1995.0 / 0.5)


def summary(steps: int, speed: float, jerk: float, headway: float, headways: int) -> EpisodeSummary:
    return EpisodeSummary(
        episode=0, seed=0, steps=steps, reason="end_of_road", duration=steps / 10,
        distance=speed * steps / 10, average_speed=speed, collisions=0,
        jerk_share_above_limit=jerk, max_abs_jerk=6.0, headway_share_below_1s=headway,
        min_time_headway=0.5, min_ttc=None, ceiling_speed=None, speed_ratio_to_ceiling=None,
        total_reward=1.0, lane_changes_started=0, lane_changes_refused=0, headway_samples=headways,
    )  # fmt: skip


def test_aggregate_pools_the_shares_of_all_samples() -> None:
    # 300 steps with 2 % jerk above the limit and 100 steps with 10 %; 1 of 50 and 30 of 100
    # headways below 1 s: pooled, 31 of 150.
    totals = aggregate([summary(300, 12.0, 0.02, 1 / 50, 50), summary(100, 14.0, 0.10, 0.3, 100)])
    assert totals["episodes"] == 2
    assert totals["average_speed"] == pytest.approx(13.0)
    assert totals["average_speed_sd"] == pytest.approx(1.0)
    assert totals["jerk_share_above_limit"] == pytest.approx((6 + 10) / 400)
    assert totals["headway_share_below_1s"] == 31 / 150
    assert np.isnan(totals["speed_ratio_to_ceiling"]) and np.isnan(totals["min_ttc"])
    with pytest.raises(ValueError, match="no episodes"):
        aggregate([])


def test_the_layers_decisions_by_rule_are_shares_of_all_steps() -> None:
    # 300 steps with 6 lane-end and 3 collision decisions, 100 steps with 1 lane-end decision
    first = replace(
        summary(300, 12.0, 0.0, 0.0, 0), safety_steps=9, safety_rules="collision:3 lane_end:6"
    )
    second = replace(summary(100, 14.0, 0.0, 0.0, 0), safety_steps=1, safety_rules="lane_end:1")
    shares = safety_rule_shares([first, second])
    assert shares == {"collision": 3 / 400, "lane_end": 7 / 400}
    assert sum(shares.values()) == pytest.approx(aggregate([first, second])["safety_share"])
    assert safety_rule_shares([summary(100, 14.0, 0.0, 0.0, 0)]) == {}


@pytest.mark.parametrize("bad", [0.0, -0.1, float("nan"), float("inf")])
def test_a_step_length_that_is_no_duration_spreads_jerk_over_the_decision(bad: float) -> None:
    """`step_length: 0` made `drive` crash with OverflowError (issue 14)."""
    times = np.array([0.0, 0.1, 0.2])
    accelerations = np.array([0.0, 1.0, 1.2])
    jerk, samples = jerk_series(accelerations, times, step_length=bad)
    expected, expected_samples = jerk_series(accelerations, times, step_length=None)
    assert np.allclose(jerk, expected) and samples == expected_samples
