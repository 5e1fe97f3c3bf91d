"""The fake backend applies the shared rules: warm-up, limits, refusals, the end of an episode."""

from __future__ import annotations

import pytest

from protocol.errors import ErrorCode
from protocol.messages import Observation, OptionValue
from sim_server.backends.fake import FAKE_OPTIONS, SPEED_LIMIT, FakeBackend
from sim_server.errors import BackendError


@pytest.fixture
def backend() -> FakeBackend:
    return FakeBackend()


def reset(backend: FakeBackend, seed: int = 1, **changes: OptionValue) -> Observation:
    unknown = set(changes) - set(FAKE_OPTIONS)
    assert not unknown, unknown
    return backend.reset("cf", seed, {**FAKE_OPTIONS, **changes})


def run(backend: FakeBackend, acceleration: float, lane_change: int = 0) -> list[Observation]:
    stream = []
    for seq in range(1, 100_000):
        obs = backend.step(seq, acceleration, lane_change)
        stream.append(obs)
        if obs.terminated or obs.truncated:
            return stream
    raise AssertionError("the episode never ended")


def test_the_episode_starts_after_the_warmup(backend: FakeBackend) -> None:
    assert reset(backend).time == 30.0  # the default, as SUMO's
    assert reset(backend, warmup=5.0).time == 5.0
    with pytest.raises(BackendError) as refused:
        reset(backend, warmup=-1.0)
    assert refused.value.code is ErrorCode.INVALID_OPTION


def test_the_time_limit_counts_from_the_entry(backend: FakeBackend) -> None:
    for warmup in (0.0, 12.0):
        first = reset(backend, warmup=warmup, max_episode_time=2.0, report_ceiling=False)
        stream = run(backend, 0.0)
        assert len(stream) == 20
        last = stream[-1]
        assert last.truncated and not last.terminated and last.reason == "time_limit"
        assert last.time == pytest.approx(first.time + 2.0)


def test_the_ceiling_is_the_leaders_trip_from_the_entry(backend: FakeBackend) -> None:
    reset(backend, 3, warmup=10.0, length=300.0)
    last = run(backend, 0.0)[-1]
    trip = last.ceiling
    assert trip is not None and trip.id == "leader"
    assert trip.depart_time == 10.0
    assert trip.arrival_time is not None and trip.arrival_time > trip.depart_time
    assert trip.average_speed == pytest.approx(290.0 / (trip.arrival_time - 10.0))


def test_limits_are_those_of_the_shared_rule(backend: FakeBackend) -> None:
    reset(backend, 2)
    braking = backend.step(1, -50.0, 0)
    assert braking.action.acceleration == -6.0
    assert braking.action.acceleration_limited_by == "bounds"
    stream = run(backend, 3.0)
    assert max(o.ego.speed for o in stream) <= SPEED_LIMIT + 1e-9
    reset(backend, 2, stop_speed=0.0, stop_patience=0.0)
    halted = run(backend, -6.0)
    assert halted[-1].ego.speed == 0.0
    assert any(o.action.acceleration_limited_by == "standstill" for o in halted)


def test_one_lane_refuses_every_lane_change(backend: FakeBackend) -> None:
    reset(backend)
    for seq, direction in enumerate((1, -1, 0), start=1):
        obs = backend.step(seq, 0.0, direction)
        assert obs.action.lane_change == 0
        assert obs.action.lane_change_refused == ("no_lane" if direction else "")
        assert obs.events.lane_change_refused == bool(direction)


def test_a_stop_far_behind_a_faster_leader_is_unreasonable(backend: FakeBackend) -> None:
    reset(backend, 4)
    stream = run(backend, -6.0)
    last = stream[-1]
    assert last.reason == "stopped" and last.terminated
    assert last.ego.speed < 1.0
    stopped = [o for o in stream if o.ego.speed < 1.0]
    assert last.time - stopped[0].time == pytest.approx(2.0)


def test_full_throttle_ends_in_a_collision(backend: FakeBackend) -> None:
    reset(backend, 5)
    last = run(backend, 3.0)[-1]
    assert last.reason == "collision" and last.events.collision
    assert last.events.collision_with == "leader" and last.neighbours.leader.gap < 0


def test_after_the_end_a_step_is_out_of_order(backend: FakeBackend) -> None:
    reset(backend, 6, max_episode_time=0.5)
    run(backend, 0.0)
    with pytest.raises(BackendError) as refused:
        backend.step(99, 0.0, 0)
    assert refused.value.code is ErrorCode.OUT_OF_ORDER
