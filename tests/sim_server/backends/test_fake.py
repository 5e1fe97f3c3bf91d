"""The fake backend applies the shared rules: warm-up, limits, refusals, the end of an episode;
with many egos (protocol 1.4) each ego is judged alone and the time limit ends them all."""

from __future__ import annotations

import random
import time
from collections.abc import Callable

import pytest

from protocol.errors import ErrorCode
from protocol.messages import (
    ROAD_RANGE,
    EndReason,
    MultiObservation,
    Observation,
    OptionValue,
    Road,
)
from sim_server.backends.base import SINGLE_EGO_ID
from sim_server.backends.fake import FAKE_OPTIONS, MAX_FAKE_EGOS, SPEED_LIMIT, FakeBackend
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


def test_a_speed_brought_to_standstill_is_never_negative(backend: FakeBackend) -> None:
    # -speed / DT * DT rounds to -1e-17 on some speeds: the protocol's speed >= 0 must hold
    rng = random.Random(0)
    for seed in range(10):
        reset(backend, seed, stop_speed=0.0, stop_patience=0.0)
        for seq in range(1, 100_000):
            obs = backend.step(seq, rng.uniform(-6.0, 1.0), 0)
            assert obs.ego.speed >= 0.0, (seed, seq, obs.ego.speed)
            if obs.terminated or obs.truncated:
                break


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


# --------------------------------------------------------------------------- many egos (1.4)

Policy = Callable[[str, int], float]
"""The acceleration of ego `id` at step `seq`."""


def reset_many(
    backend: FakeBackend, egos: int, seed: int = 1, **changes: OptionValue
) -> MultiObservation:
    options = {**FAKE_OPTIONS, **changes, "egos": egos}
    return backend.reset_many("cf", seed, options, egos)


def running(frame: MultiObservation) -> list[str]:
    return [e.id for e in frame.egos if not (e.terminated or e.truncated)]


def drive(backend: FakeBackend, first: MultiObservation, policy: Policy) -> list[MultiObservation]:
    """Step every running ego until the episode ends; the frames after seq 0."""
    frames, frame = [], first
    for seq in range(1, 100_000):
        frame = backend.step_many(seq, {ego: (policy(ego, seq), 0) for ego in running(frame)})
        frames.append(frame)
        if frame.terminated or frame.truncated:
            return frames
    raise AssertionError("the episode never ended")


def by_id(frame: MultiObservation) -> dict[str, object]:
    return {e.id: e for e in frame.egos}


def test_one_ego_is_the_one_ego_episode(backend: FakeBackend) -> None:
    first = reset_many(backend, 1)
    alone = FakeBackend().reset("cf", 1, dict(FAKE_OPTIONS))
    assert [e.id for e in first.egos] == [SINGLE_EGO_ID]
    assert first.egos[0].ego == alone.ego and first.time == alone.time


def test_egos_drive_in_a_column_behind_the_leader(backend: FakeBackend) -> None:
    first = reset_many(backend, 3)
    assert [e.id for e in first.egos] == ["ego.0", "ego.1", "ego.2"] and first.seq == 0
    assert [e.neighbours.leader.id for e in first.egos] == ["leader", "ego.0", "ego.1"]
    assert [e.neighbours.follower.id for e in first.egos] == ["ego.1", "ego.2", ""]
    positions = [e.ego.position for e in first.egos]
    assert positions == sorted(positions, reverse=True) and positions[-1] == 5.0
    gap = positions[0] - 5.0 - positions[1]
    assert first.egos[1].neighbours.leader.gap == pytest.approx(gap)
    assert first.egos[0].neighbours.follower.gap == pytest.approx(gap)
    assert len({e.ego.speed for e in first.egos}) == 1  # one speed: equal commands keep the gaps
    assert not (first.terminated or first.truncated or any(e.reason for e in first.egos))


def test_an_ego_that_crashes_ends_alone_and_leaves_the_road(backend: FakeBackend) -> None:
    first = reset_many(backend, 3, 5, max_episode_time=60.0)
    frames = drive(backend, first, lambda ego, seq: 3.0 if ego == "ego.0" else 0.0)
    crash = next(f for f in frames if "ego.0" not in running(f))
    ego0 = crash.egos[0]
    assert ego0.terminated and ego0.reason == "collision" and ego0.events.collision_with == "leader"
    assert not (crash.terminated or crash.truncated) and running(crash) == ["ego.1", "ego.2"]
    after = frames[frames.index(crash) + 1]
    assert [e.id for e in after.egos] == ["ego.1", "ego.2"]  # listed once, then no more
    assert after.egos[0].neighbours.leader.id == "leader"  # the crashed ego is gone
    last = frames[-1]
    assert last.truncated and last.reason == "time_limit"
    assert all(e.truncated and e.reason == "time_limit" for e in last.egos)


def test_two_egos_that_collide_end_both(backend: FakeBackend) -> None:
    first = reset_many(backend, 3, 2)
    frames = drive(backend, first, lambda ego, seq: 3.0 if ego == "ego.2" else 0.0)
    crash = next(f for f in frames if len(running(f)) < len(f.egos))
    ended = {e.id: e.events.collision_with for e in crash.egos if e.terminated}
    assert ended == {"ego.1": "ego.2", "ego.2": "ego.1"}
    assert running(crash) == ["ego.0"] and not crash.terminated


def test_the_last_ego_to_end_terminates_the_episode_with_its_reason(backend: FakeBackend) -> None:
    first = reset_many(backend, 2, 5)
    frames = drive(backend, first, lambda ego, seq: 3.0 if ego == "ego.0" else -6.0 * (seq > 600))
    assert [e.reason for f in frames for e in f.egos if e.reason] == ["collision", "stopped"]
    last = frames[-1]
    assert last.terminated and not last.truncated and running(last) == []
    assert [e.id for e in last.egos] == ["ego.1"] and last.reason == "stopped"


def test_many_egos_are_deterministic(backend: FakeBackend) -> None:
    def stream() -> list[MultiObservation]:
        first = reset_many(backend, 4, 9, max_episode_time=3.0)
        return [first, *drive(backend, first, lambda ego, seq: (seq % 3) - 1.0)]

    assert stream() == stream()
    assert reset_many(backend, 4, 10) != reset_many(backend, 4, 9)


def test_many_egos_apply_the_shared_rules(backend: FakeBackend) -> None:
    reset_many(backend, 2)
    frame = backend.step_many(1, {"ego.0": (-50.0, 1), "ego.1": (0.5, 0)})
    first, second = frame.egos
    assert first.action.acceleration == -6.0 and first.action.acceleration_limited_by == "bounds"
    assert first.action.lane_change_refused == "no_lane" and first.events.lane_change_refused
    assert second.action.acceleration == pytest.approx(0.5)
    assert second.action.acceleration_limited_by == ""


def test_too_many_egos_or_too_short_a_road_are_refused(backend: FakeBackend) -> None:
    for egos, changes in ((MAX_FAKE_EGOS + 1, {}), (8, {"length": 100.0})):
        with pytest.raises(BackendError) as refused:
            reset_many(backend, egos, **changes)
        assert refused.value.code is ErrorCode.INVALID_OPTION


def test_after_the_last_ego_a_multi_step_is_out_of_order(backend: FakeBackend) -> None:
    first = reset_many(backend, 2, max_episode_time=0.5)
    drive(backend, first, lambda ego, seq: 0.0)
    with pytest.raises(BackendError) as refused:
        backend.step_many(99, {"ego.0": (0.0, 0)})
    assert refused.value.code is ErrorCode.OUT_OF_ORDER


def test_the_open_road_is_reported_on_every_observation(backend: FakeBackend) -> None:
    first = reset(backend)
    assert first.road == Road(ROAD_RANGE, 0, 0.0, 0.0)
    assert all(obs.road == first.road for obs in run(backend, 0.0))


def test_a_lane_that_ends_stops_the_ego_there_and_ends_the_episode(backend: FakeBackend) -> None:
    first = reset(backend, lane_end=60.0, lane_end_patience=1.5, max_episode_time=100.0)
    assert first.road is not None and first.road.lane_end == pytest.approx(
        60.0 - first.ego.position
    )
    stream = run(backend, -0.2)  # slower than the leader: the lane's end comes first
    last = stream[-1]
    assert last.reason == EndReason.LANE_END and last.terminated
    assert last.ego.position == 60.0 and last.ego.speed == 0.0 and last.road is not None
    assert last.road.lane_end == 0.0
    standing = [o for o in stream if o.ego.speed == 0.0]
    assert standing[-1].time - standing[0].time == pytest.approx(1.5)


def test_a_reset_takes_the_seconds_asked_for(backend: FakeBackend) -> None:
    started = time.monotonic()
    reset(backend, reset_seconds=0.3)
    assert time.monotonic() - started >= 0.3
