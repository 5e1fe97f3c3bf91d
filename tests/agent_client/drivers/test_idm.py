from __future__ import annotations

import math

import pytest

from agent_client.drivers.idm import IDMDriver, IDMParams, idm_acceleration
from protocol.messages import Neighbour, Neighbours
from tests.protocol.test_codec import make_observation


def test_free_road_acceleration() -> None:
    params = IDMParams(a=1.0, v0=20.0, delta=4.0)
    assert idm_acceleration(params, 10.0, 22.0, None, 0.0) == pytest.approx(1.0 * (1 - 0.5**4))
    assert idm_acceleration(params, 20.0, 22.0, None, 0.0) == pytest.approx(0.0)


def test_following_hand_computed() -> None:
    params = IDMParams(a=1.5, b=2.0, T=1.5, s0=2.0, v0=30.0, delta=4.0)
    v, gap, v_lead = 15.0, 30.0, 13.0
    desired = 2.0 + 15.0 * 1.5 + 15.0 * 2.0 / (2 * math.sqrt(1.5 * 2.0))
    expected = 1.5 * (1 - (15 / 30) ** 4 - (desired / gap) ** 2)
    assert idm_acceleration(params, v, 22.0, gap, v_lead) == pytest.approx(expected)


def test_equilibrium_gap_gives_zero_acceleration_without_free_term() -> None:
    params = IDMParams(a=1.0, b=1.5, T=1.2, s0=2.0, v0=1e9)
    v = 10.0
    assert idm_acceleration(params, v, 22.0, 2.0 + v * 1.2, v) == pytest.approx(0.0, abs=1e-9)


def test_default_desired_speed_is_the_speed_limit() -> None:
    assert idm_acceleration(IDMParams(), 22.22, 22.22, None, 0.0) == pytest.approx(0.0)


def test_driver_reads_the_leader_and_keeps_its_lane() -> None:
    driver = IDMDriver(IDMParams(v0=30.0))
    close = make_observation()  # leader 12.5 m ahead at 14 m/s, ego 15 m/s
    absent = Neighbour(False, 200.0, 0.0, 0.0)
    free = make_observation(neighbours=Neighbours(*(absent,) * 6))
    braking, lane = driver.act(close)
    assert lane == 0
    assert braking < 0
    assert driver.act(free)[0] > 0
