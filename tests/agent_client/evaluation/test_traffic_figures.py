"""The traffic-level figures on hand-made speeds and positions with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent_client.evaluation.traffic_figures import (
    arrivals,
    edie_flow,
    first_last,
    mean_speed,
    passes,
    per_hour,
    spread_across,
    spread_over_time,
    stopped_share,
)

NAN = math.nan


def test_uniform_flow_has_no_spread() -> None:
    speeds = np.full((10, 5), 7.0)
    assert spread_across(speeds) == 0.0
    assert spread_over_time(speeds) == 0.0
    assert mean_speed(speeds) == 7.0
    assert stopped_share(speeds) == 0.0


def test_spread_across_is_the_mean_of_each_steps_std() -> None:
    # step 0: 0 and 2 (std 1); step 1: 1 and 5 (std 2); step 2: one vehicle only, skipped
    speeds = np.array([[0.0, 2.0], [1.0, 5.0], [3.0, NAN]])
    assert spread_across(speeds) == pytest.approx(1.5)
    assert mean_speed(speeds) == pytest.approx(11.0 / 5)


def test_spread_over_time_is_the_mean_of_each_vehicles_std() -> None:
    # vehicle 0 swings 0 <-> 2 (std 1), vehicle 1 is steady, vehicle 2 is seen once (skipped)
    speeds = np.array([[0.0, 4.0, NAN], [2.0, 4.0, 9.0], [0.0, 4.0, NAN], [2.0, 4.0, NAN]])
    assert spread_over_time(speeds) == pytest.approx(0.5)


def test_a_wave_spreads_both_ways_and_stops_vehicles() -> None:
    t = np.arange(0.0, 60.0, 0.1)[:, None]
    phase = np.arange(4)[None, :] * np.pi / 2
    speeds = 3.0 + 3.0 * np.sin(2 * np.pi * t / 30.0 + phase)
    assert spread_across(speeds) > 1.5
    assert spread_over_time(speeds) == pytest.approx(3.0 / math.sqrt(2), rel=0.01)
    share = float(np.mean(speeds < 1.0))
    assert stopped_share(speeds) == pytest.approx(share)
    assert 0.1 < share < 0.4


def test_nothing_present_is_nan() -> None:
    empty = np.full((3, 2), NAN)
    for figure in (mean_speed, spread_across, spread_over_time, stopped_share):
        assert math.isnan(figure(empty))


def test_a_table_must_be_two_dimensional() -> None:
    with pytest.raises(ValueError, match="steps, vehicles"):
        mean_speed(np.zeros(3))


def test_first_and_last_positions_skip_the_steps_a_vehicle_is_absent() -> None:
    positions = np.array([[NAN, 0.0, NAN], [5.0, 1.0, NAN], [6.0, NAN, NAN]])
    first, last = first_last(positions)
    np.testing.assert_array_equal(first[:2], [5.0, 0.0])
    np.testing.assert_array_equal(last[:2], [6.0, 1.0])
    assert math.isnan(first[2]) and math.isnan(last[2])


def test_passes_on_a_straight_road() -> None:
    start = np.array([0.0, 990.0, 1000.0, 1200.0, NAN])
    end = np.array([999.0, 1000.0, 1500.0, 1900.0, 2000.0])
    # only the second passes 1000 m (the third starts on the mark, the fourth beyond it)
    assert passes(start, end, 1000.0) == 1


def test_passes_on_a_ring_count_every_lap() -> None:
    # a 100 m ring, point 0: from 95 to 405 passes 100, 200, 300, 400; from 10 to 90 none;
    # from 0 (on the point) to 100 once (it reaches the point again)
    start = np.array([95.0, 10.0, 0.0])
    end = np.array([405.0, 90.0, 100.0])
    assert passes(start, end, 0.0, period=100.0) == 5
    assert passes(start, end, 50.0, period=100.0) == 3 + 1 + 1
    with pytest.raises(ValueError, match="period"):
        passes(start, end, 0.0, period=0.0)


def test_edie_flow_on_a_ring_is_density_times_speed() -> None:
    # 22 vehicles on 230 m at 2 m/s for 300 s: 22 / 230 veh/m x 2 m/s = 688.7 veh/h
    distances = np.full(22, 2.0 * 300.0)
    assert edie_flow(distances, 230.0, 300.0) == pytest.approx(3600 * 22 / 230 * 2)
    assert math.isnan(edie_flow(distances, 230.0, 0.0))


def test_fixed_point_count_agrees_with_edie_flow_on_average() -> None:
    rng = np.random.default_rng(1)
    length, seconds = 230.0, 300.0
    start = rng.uniform(0.0, length, 22)
    end = start + rng.uniform(400.0, 800.0, 22)
    points = np.linspace(0.0, length, 200, endpoint=False)
    mean_count = float(np.mean([passes(start, end, p, length) for p in points]))
    assert per_hour(mean_count, seconds) == pytest.approx(
        edie_flow(end - start, length, seconds), rel=0.01
    )


def test_per_hour() -> None:
    assert per_hour(10, 360.0) == 100.0
    assert math.isnan(per_hour(1, 0.0))


def test_arrivals_count_the_ids_that_disappear() -> None:
    steps = [{"a", "b"}, {"a", "b", "c"}, {"b", "c"}, {"d"}, {"d"}]
    assert arrivals(steps) == 3  # a, then b and c
    assert arrivals([]) == 0
