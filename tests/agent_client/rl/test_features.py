from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from agent_client.rl.features import GAP_CAP, FeatureMap
from protocol.messages import OPEN_ROAD, ROAD_RANGE, Ego, Neighbour, Neighbours, Road
from tests.protocol.test_codec import make_observation


def test_car_following_features_hand_computed() -> None:
    features = FeatureMap("cf")
    x = features(make_observation())  # ego 15 m/s, -0.5 m/s^2; leader 12.5 m ahead at 14 m/s
    assert x.dtype == np.float32
    assert features.dim == 6
    assert x == pytest.approx([15 / 22.22, -0.5 / 3, 1.0, 0.125, -0.1, 12.5 / 15 / 5], rel=1e-5)


def test_a_missing_leader_is_a_flag_not_a_huge_gap() -> None:
    absent = Neighbour(False, 200.0, 0.0, 0.0)
    obs = make_observation(neighbours=Neighbours(*(absent,) * 6))
    x = FeatureMap("cf")(obs)
    assert x[2] == 0.0
    assert x[3] == GAP_CAP
    assert x[5] == 1.0  # headway feature at its cap, as for a far leader


def test_lane_changing_features_see_the_lanes() -> None:
    features = FeatureMap("lc")
    middle = make_observation(ego=Ego(15.0, 0.0, 1, 3, 100.0, 22.22))
    right = make_observation(ego=Ego(15.0, 0.0, 0, 3, 100.0, 22.22))
    assert features.dim == 6 + 5 * 3 + 2
    assert list(features(middle)[-2:]) == [1.0, 1.0]
    assert list(features(right)[-2:]) == [1.0, 0.0]


def test_unknown_feature_set() -> None:
    with pytest.raises(ValueError, match="known: cf, lc"):
        FeatureMap("pixels")


def test_the_lane_decision_phase_is_the_last_feature() -> None:
    features = FeatureMap("lc", lane_phase_every=10)
    assert features.dim == FeatureMap("lc").dim + 1
    phases = [features(make_observation(seq=seq))[-1] for seq in (0, 3, 9, 10, 13)]
    assert phases == pytest.approx([0.0, 0.3, 0.9, 0.0, 0.3])


def test_the_road_features_read_the_route() -> None:
    lc, road = FeatureMap("lc"), FeatureMap("road")
    assert road.dim == lc.dim + 7
    merging = Road(lane_end=100.0, lanes_to_change=1, left_lane_end=ROAD_RANGE, right_lane_end=0.0)
    obs = make_observation(ego=Ego(20.0, 0.0, 0, 3, 100.0, 27.78), road=merging)
    x = road(obs)
    assert x[: lc.dim] == pytest.approx(lc(obs))
    # 100 m, +1, 5 s of 10; nobody on the left: both gaps a full 100 m longer than needed
    assert x[lc.dim :] == pytest.approx([0.1, 0.5, 1.0, 0.0, 0.5, 1.0, 1.0])


def test_the_road_features_are_those_of_the_open_road_without_one() -> None:
    """A server older than 1.6, or cf and cflc: the lanes beside it repeat lc's flags."""
    road = FeatureMap("road")
    middle = make_observation(ego=Ego(15.0, 0.0, 1, 3, 100.0, 22.22))
    expected = [1.0, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0]
    assert road(middle)[-7:] == pytest.approx(expected)
    assert road(replace(middle, road=OPEN_ROAD))[-7:] == pytest.approx(expected)


def test_the_gap_margins_say_how_far_the_gap_on_the_routes_side_is_from_a_safe_one() -> None:
    merging = Road(lane_end=100.0, lanes_to_change=1, left_lane_end=ROAD_RANGE, right_lane_end=0.0)
    close = Neighbour(True, 10.0, 3.2, 20.0, "lead")  # 12.5 m short of the secure 22.5 m
    absent = Neighbour(False, 200.0, 0.0, 0.0)
    near = Neighbours(close, absent, absent, absent, absent, absent)
    obs = make_observation(ego=Ego(20.0, 0.0, 0, 3, 100.0, 27.78), neighbours=near, road=merging)
    assert FeatureMap("road")(obs)[-2:] == pytest.approx([-0.125, 1.0])


def test_the_driving_features_read_the_stop_line_and_the_next_light() -> None:
    drive = FeatureMap("drive")
    road = FeatureMap("road")
    assert drive.dim == road.dim + 8
    red = Road(ROAD_RANGE, 0, 0.0, 0.0, stop_line=50.0, signal_distance=50.0, signal_state="red",
               signal_switch=30.0)  # fmt: skip
    obs = make_observation(ego=Ego(10.0, 0.0, 0, 1, 100.0, 13.9), road=red)
    tail = drive(obs)[road.dim :].tolist()
    assert tail[:3] == pytest.approx([1.0, 0.05, 100.0 / 100.0 / 6.0])  # v²/2d = 1 m/s²
    assert tail[3:] == pytest.approx([0.05, 1.0, 0.0, 0.0, 0.25])
    clear = drive(make_observation(ego=Ego(10.0, 0.0, 0, 1, 100.0, 13.9)))[road.dim :]
    assert clear.tolist() == pytest.approx([0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0])
