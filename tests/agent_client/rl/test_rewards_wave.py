"""The ring's `wave` reward: drive at the traffic's mean speed, smoothly, off the leader."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent_client.errors import UsageError
from agent_client.rl.rewards import WaveReward, make_reward, max_reward, q_upper_bound
from protocol.messages import (
    AppliedAction,
    Ego,
    Events,
    Neighbour,
    Neighbours,
    Observation,
    Traffic,
)

DT = 0.5
LIMIT = 30 / 3.6
ABSENT = Neighbour(False, 200.0, 0.0, 0.0)


def traffic(*speeds: float) -> Traffic:
    n = len(speeds)
    ids = tuple(f"human{i}" for i in range(n))
    return Traffic(
        ids, ("human",) * n, (0,) * n, (0.0,) * n, speeds, (0.0,) * n, ("",) * n,
        (200.0,) * n, (0.0,) * n,
    )  # fmt: skip


def ring_obs(
    speed: float,
    others: tuple[float, ...] | None = (2.0, 2.0, 2.0),
    *,
    acceleration: float = 0.0,
    gap: float = 20.0,
    leader_speed: float | None = None,
    collision: bool = False,
) -> Observation:
    """The ego at `speed` on the ring, `gap` m behind a leader (at `leader_speed`, default the
    ego's), among traffic at `others` (None: no traffic reported)."""
    ahead = Neighbour(True, gap, 0.0, speed if leader_speed is None else leader_speed, "human0")
    neighbours = Neighbours(ABSENT, ABSENT, ahead, ABSENT, ABSENT, ABSENT)
    return Observation(
        seq=1,
        time=DT,
        ego=Ego(speed, acceleration, 0, 1, 100.0, LIMIT),
        neighbours=neighbours,
        events=Events(collision=collision),
        action=AppliedAction(acceleration, 0, acceleration, 0),
        traffic=None if others is None else traffic(*others),
    )


def wave(obs: Observation, **params: float) -> float:
    return WaveReward(**params)(None, obs, DT)


def test_wave_is_registered_and_needs_the_traffic() -> None:
    assert isinstance(make_reward("wave"), WaveReward)
    with pytest.raises(UsageError, match="report_traffic"):
        wave(ring_obs(2.0, None))


def test_wave_pays_the_traffic_mean_speed_at_that_speed() -> None:
    # the ego at the others' 2 m/s: E = 2 / 8.33, M = 1, gates open
    assert wave(ring_obs(2.0)) == pytest.approx(2.0 / LIMIT)
    # faster traffic pays more (E), the ego matching it
    assert wave(ring_obs(4.0, (4.0, 4.0, 4.0))) == pytest.approx(4.0 / LIMIT)
    # 1 m/s off the mean of all (the ego at 3, three at 2: mean 2.25) keeps exp(-0.75^2 / 2)
    expected = 2.25 / LIMIT * math.exp(-(0.75**2) / 2)
    assert wave(ring_obs(3.0, (2.0, 2.0, 2.0))) == pytest.approx(expected)


def test_wave_copying_the_wave_earns_less_than_driving_at_the_mean() -> None:
    # a wave: the others at 0 to 6 m/s; in each case the mean of all six is 2 m/s
    at_mean = wave(ring_obs(2.0, (0.0, 0.5, 4.0, 4.0, 1.5)))
    assert at_mean == pytest.approx(2.0 / LIMIT)
    stopped = wave(ring_obs(0.5, (0.0, 0.5, 4.0, 6.0, 1.0)))  # braking with the wave
    racing = wave(ring_obs(3.5, (0.0, 0.5, 4.0, 4.0, 0.0)))  # accelerating with it
    assert stopped == pytest.approx(racing) == pytest.approx(at_mean * math.exp(-(1.5**2) / 2))
    assert max(stopped, racing) < 0.5 * at_mean


def test_wave_blocking_the_ring_earns_nothing() -> None:
    # the degenerate optimum of a mean-speed match alone: stop, and so make everyone stop
    assert wave(ring_obs(0.0, (0.0, 0.0, 0.0))) == 0.0


def test_wave_own_speed_tilts_a_stopped_ring_towards_driving_off() -> None:
    stopped = ring_obs(0.0, (0.0, 0.0, 0.0))
    moving = ring_obs(0.5, (0.0, 0.0, 0.0))  # the ego drives off; the others still stand
    assert wave(moving) == pytest.approx(0.5 / 4 / LIMIT * math.exp(-(0.375**2) / 2))
    own = make_reward("wave_own")
    assert isinstance(own, WaveReward) and own.own_speed_weight == 0.5
    assert own(None, stopped, DT) == 0.0
    assert own(None, moving, DT) > 2.0 * wave(moving)
    # at the traffic's mean speed the mix changes nothing
    assert own(None, ring_obs(2.0), DT) == pytest.approx(wave(ring_obs(2.0)))


def test_wave_acceleration_gate() -> None:
    calm = wave(ring_obs(2.0))
    assert wave(ring_obs(2.0, acceleration=0.75)) == pytest.approx(calm * (1 - 0.5 * 0.25))
    assert wave(ring_obs(2.0, acceleration=-1.5)) == pytest.approx(calm * 0.5)
    assert wave(ring_obs(2.0, acceleration=-6.0)) == pytest.approx(calm * 0.5)


def test_wave_headway_and_ttc_gates() -> None:
    calm = wave(ring_obs(2.0, gap=20.0))
    assert wave(ring_obs(2.0, gap=2.0)) == pytest.approx(calm)  # h = 1 s: the knee
    assert wave(ring_obs(2.0, gap=1.0)) < 0.2 * calm  # h = 0.5 s
    # closing in at 2 m/s on a standing leader 4 m ahead: TTC 2 s, half the step
    assert wave(ring_obs(2.0, gap=4.0, leader_speed=0.0)) == pytest.approx(0.5 * calm)


def test_wave_collision_and_spread() -> None:
    assert wave(ring_obs(2.0, collision=True)) == -20.0
    assert wave(ring_obs(2.0, gap=-0.1)) == -20.0
    even, spread = (2.0, 2.0, 2.0, 2.0), (0.0, 4.0, 0.0, 4.0)  # both with mean 2.0
    assert wave(ring_obs(2.0, even), spread_weight=1.0) == pytest.approx(2.0 / LIMIT)
    sigma = math.sqrt(16.0 / 5)  # the ego at 2 and four at 0 / 4
    assert wave(ring_obs(2.0, spread), spread_weight=1.0) == pytest.approx(
        2.0 / LIMIT * (1 - sigma / LIMIT)
    )
    assert wave(ring_obs(2.0, spread)) == pytest.approx(2.0 / LIMIT)  # off by default


def test_wave_max_reward_and_bad_weights() -> None:
    assert max_reward("wave") == pytest.approx(1.0)
    assert q_upper_bound("wave", 0.98) == pytest.approx(50.0)
    bad = (
        ({"speed_tolerance": 0.0}, "positive"),
        ({"accel_weight": 1.5}, "accel_weight"),
        ({"spread_weight": -1.0}, "non-negative"),
        ({"own_speed_weight": 2.0}, "own_speed_weight"),
    )
    for params, match in bad:
        with pytest.raises(ValueError, match=match):
            WaveReward(**params)


@settings(max_examples=300, deadline=None)
@given(
    speed=st.floats(-1.0, 20.0),
    others=st.lists(st.floats(0.0, 20.0), min_size=0, max_size=30),
    acceleration=st.floats(-10.0, 10.0),
    gap=st.floats(-10.0, 300.0),
    leader_speed=st.floats(0.0, 20.0),
    collision=st.booleans(),
)
def test_wave_bounded(
    speed: float,
    others: list[float],
    acceleration: float,
    gap: float,
    leader_speed: float,
    collision: bool,
) -> None:
    obs = ring_obs(
        speed, tuple(others), acceleration=acceleration, gap=gap, leader_speed=leader_speed,
        collision=collision,
    )  # fmt: skip
    value = WaveReward(spread_weight=1.0, own_speed_weight=0.3)(None, obs, DT)
    assert math.isfinite(value)
    assert value == -20.0 or 0.0 <= value <= 1.0
    if not (collision or speed < 0.0 or gap < 0.0):
        assert value >= 0.0
