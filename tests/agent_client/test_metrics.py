from __future__ import annotations

import numpy as np
import pytest

from agent_client.metrics import (
    EpisodeRecorder,
    jerk_series,
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
    recorder = EpisodeRecorder(episode=1, seed=9)
    absent = Neighbour(False, 200.0, 0.0, 0.0)
    for i, (acc, gap) in enumerate([(0.0, 20.0), (0.7, 8.0), (0.7, 9.0), (0.0, 30.0)]):
        leader = Neighbour(True, gap, 0.0, 10.0)
        recorder.add(
            make_observation(
                seq=i,
                time=30.0 + 0.1 * i,
                ego=Ego(10.0, acc, 0, 1, 5.0 + i, 22.22),
                neighbours=Neighbours(absent, absent, leader, absent, absent, absent),
                ceiling=LeaderTrip("l", 29.0, 30.5, 2000.0 / 1.5) if i == 3 else None,
            ),
            reward=1.0,
        )
    summary = recorder.summary()
    assert summary.steps == 3
    assert summary.average_speed == pytest.approx(3.0 / 0.3)
    assert summary.jerk_share_above_limit == pytest.approx(2 / 3)  # +7, 0, -7 m/s^3
    assert summary.max_abs_jerk == pytest.approx(7.0)
    assert summary.headway_share_below_1s == pytest.approx(2 / 4)  # 0.8 s and 0.9 s
    assert summary.min_ttc is None  # never faster than the leader
    assert summary.total_reward == 3.0
    # Arriving with the leader at 30.5 s from entry at 30.0 s and 5 m: (2000 - 5) / 0.5
    assert summary.ceiling_speed == pytest.approx(1995.0 / 0.5)
