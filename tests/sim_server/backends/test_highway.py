"""The highway-env backend in-process: the protocol's semantics on another simulator."""

from __future__ import annotations

from collections.abc import Iterable

import pytest

pytest.importorskip("highway_env")

from agent_client.drivers.idm import IDMDriver
from protocol.errors import ErrorCode
from protocol.messages import Observation, OptionValue
from sim_server.backends.highway import HighwayBackend
from sim_server.errors import BackendError

LENGTH = 2000.0
FREE_ROAD = {"vehicles_count": 0, "vehicles_behind": 0}


@pytest.fixture
def backend() -> HighwayBackend:
    return HighwayBackend()


def options(
    backend: HighwayBackend, scenario: str, **changes: OptionValue
) -> dict[str, OptionValue]:
    info = {s.name: s for s in backend.scenarios()}[scenario]
    unknown = set(changes) - set(info.options)
    assert not unknown, unknown
    return {**info.options, **changes}


def run(
    backend: HighwayBackend, first: Observation, actions: Iterable[tuple[float, int]]
) -> list[Observation]:
    stream = [first]
    for seq, (acceleration, lane_change) in enumerate(actions, start=1):
        obs = backend.step(seq, acceleration, lane_change)
        stream.append(obs)
        if obs.terminated or obs.truncated:
            break
    return stream


def test_scenarios_offer_only_the_options_the_backend_honours(backend: HighwayBackend) -> None:
    infos = {s.name: s for s in backend.scenarios()}
    assert set(infos) == {"cf", "cflc"}
    for info in infos.values():
        assert info.step_length == pytest.approx(0.1)
        for name in ("decision_interval", "max_episode_time", "warmup", "stop_speed",
                     "stop_gap", "stop_patience", "report_ceiling", "ego_driver",
                     "vehicles_count", "vehicles_behind", "vehicles_density"):  # fmt: skip
            assert name in info.options, name
        for name in ("insertion_timeout", "flow", "sigma", "speed_factor_mean"):
            assert name not in info.options, name
    assert backend.name == "highway"
    assert backend.version.startswith("1.12")


def test_reset_hands_the_ego_over_after_the_warm_up(backend: HighwayBackend) -> None:
    obs = backend.reset("cf", 1, options(backend, "cf"))
    assert obs.seq == 0 and not (obs.terminated or obs.truncated or obs.reason)
    assert obs.time == pytest.approx(5.0)
    assert (obs.ego.lane, obs.ego.lane_count) == (0, 1)
    assert obs.ego.speed_limit == pytest.approx(80 / 3.6)
    assert 0 < obs.ego.position < LENGTH
    assert obs.neighbours.leader.present and obs.neighbours.leader.gap > 0
    assert obs.neighbours.leader.id.startswith("h")
    for slot in ("left_leader", "left_follower", "right_leader", "right_follower"):
        absent = getattr(obs.neighbours, slot)
        assert (absent.present, absent.gap, absent.lateral, absent.speed, absent.id) == (
            False, backend.sensor_range, 0.0, 0.0, "",
        )  # fmt: skip
    cold = backend.reset("cf", 1, options(backend, "cf", warmup=0.0))
    assert cold.time == 0.0


def test_commanded_acceleration_is_realised_exactly(backend: HighwayBackend) -> None:
    obs = backend.reset("cf", 2, options(backend, "cf"))
    checked = 0
    for seq, request in enumerate([0.5, -0.5, 1.0, -1.5, 0.2, -0.3] * 3, start=1):
        before = obs.ego.speed
        obs = backend.step(seq, request, 0)
        assert not obs.events.collision
        if obs.action.acceleration_limited_by:
            continue
        assert obs.action.acceleration == request
        assert obs.ego.acceleration == request
        assert obs.ego.speed == pytest.approx(before + 0.1 * request, abs=1e-9)
        checked += 1
    assert checked >= 10


def test_a_long_decision_repeats_the_action_over_its_steps(backend: HighwayBackend) -> None:
    first = backend.reset("cf", 2, options(backend, "cf", decision_interval=1.0))
    obs = backend.step(1, -0.5, 0)
    assert obs.time == pytest.approx(first.time + 1.0)
    assert obs.ego.speed == pytest.approx(first.ego.speed - 0.5, abs=1e-9)
    assert obs.action.acceleration == pytest.approx(-0.5)


def test_bounds_and_the_speed_limit_are_applied_and_reported(backend: HighwayBackend) -> None:
    backend.reset("cf", 3, options(backend, "cf"))
    braking = backend.step(1, -50.0, 0)
    assert braking.action.requested_acceleration == -50.0
    assert braking.action.acceleration == -6.0
    assert braking.action.acceleration_limited_by == "bounds"
    first = backend.reset("cf", 3, options(backend, "cf", **FREE_ROAD))
    stream = run(backend, first, [(3.0, 0)] * 200)
    assert max(o.ego.speed for o in stream) <= first.ego.speed_limit + 1e-9
    assert stream[-1].ego.speed == pytest.approx(first.ego.speed_limit)
    assert any(o.action.acceleration_limited_by == "speed_limit" for o in stream)
    fresh = backend.reset("cf", 3, options(backend, "cf", **FREE_ROAD, stop_speed=0.0))
    halted = run(backend, fresh, [(-6.0, 0)] * 60)
    assert min(o.ego.speed for o in halted) == 0.0
    assert any(o.action.acceleration_limited_by == "standstill" for o in halted)


def test_lane_changes_follow_the_protocols_lane_numbering(backend: HighwayBackend) -> None:
    first = backend.reset("cflc", 4, options(backend, "cflc", **FREE_ROAD))
    direction = 1 if first.ego.lane < 2 else -1
    start = backend.step(1, 0.0, direction)
    assert start.events.lane_change_started and start.action.lane_change == direction
    assert start.ego.changing_lane == direction
    busy = backend.step(2, 0.0, direction)
    assert busy.events.lane_change_refused and busy.action.lane_change_refused == "in_progress"
    assert busy.ego.changing_lane == direction
    seq, obs, moved = 2, busy, []
    while not obs.events.lane_change_completed:
        seq += 1
        obs = backend.step(seq, 0.0, 0)
        moved.append(obs)
        assert seq < 60, "the lane change did not complete within 6 s"
    assert obs.ego.lane == first.ego.lane + direction and obs.ego.changing_lane == 0
    assert all(o.ego.changing_lane == direction for o in moved[:-1])
    assert 1.0 <= obs.time - start.time + 0.1 <= 3.0  # SUMO's lane change takes 2 s
    # On to the edge of the road, where the next change is refused with no_lane.
    for _ in range(100):
        seq += 1
        obs = backend.step(seq, 0.0, direction)
        if obs.action.lane_change_refused == "no_lane":
            break
        assert obs.action.lane_change_refused in ("", "in_progress")
    else:
        pytest.fail("never reached the edge of the road")
    assert obs.ego.lane == (2 if direction == 1 else 0)
    assert obs.action.lane_change == 0 and obs.events.lane_change_refused


def test_neighbour_lanes_and_lateral_offsets_point_left_positive(backend: HighwayBackend) -> None:
    seen = {"left": 0, "right": 0}
    for seed in range(1, 6):
        obs = backend.reset("cflc", seed, options(backend, "cflc"))
        stream = run(backend, obs, [(0.0, 0)] * 30)
        for o in stream:
            n = o.neighbours
            for side, sign in (("left", 1.0), ("right", -1.0)):
                for slot in (f"{side}_leader", f"{side}_follower"):
                    neighbour = getattr(n, slot)
                    if neighbour.present:
                        # a side lane's centre is 4 m away; highway-env counts a vehicle on
                        # it within 3 m of that centre (e.g. while it changes lanes)
                        assert 0.5 < sign * neighbour.lateral < 7.5, (slot, neighbour)
                        seen[side] += 1
            if o.ego.lane == 0:
                assert not n.right_leader.present and not n.right_follower.present
            if o.ego.lane == 2:
                assert not n.left_leader.present and not n.left_follower.present
            for slot in ("leader", "follower"):  # up to 3 m off: a human changing lanes
                neighbour = getattr(n, slot)
                assert not neighbour.present or abs(neighbour.lateral) <= 3.0
                assert not neighbour.present or 0 <= neighbour.gap <= backend.sensor_range
    assert seen["left"] > 0 and seen["right"] > 0


def test_an_unsafe_lane_change_is_refused_by_mobils_safety_rule(backend: HighwayBackend) -> None:
    outcomes = {"started": 0, "gap_too_small": 0}
    for seed in range(1, 6):
        obs = backend.reset("cflc", seed, options(backend, "cflc", report_ceiling=False))
        direction = 1 if obs.ego.lane < 2 else -1
        side = "left" if direction == 1 else "right"
        after = backend.step(1, 0.0, direction)
        leader = getattr(obs.neighbours, f"{side}_leader")
        follower = getattr(obs.neighbours, f"{side}_follower")
        nearest = (
            min(n.gap for n in (leader, follower) if n.present)
            if (leader.present or follower.present)
            else backend.sensor_range
        )
        if after.action.lane_change_refused:
            # MOBIL's rule: someone in the target lane would brake harder than 2 m/s^2.
            assert after.action.lane_change_refused == "gap_too_small"
            assert after.events.lane_change_refused and not after.events.lane_change_started
            assert after.action.lane_change == 0 and after.ego.lane == obs.ego.lane
            assert nearest < 40.0
            outcomes["gap_too_small"] += 1
        else:
            assert after.events.lane_change_started and nearest > 5.0
            outcomes["started"] += 1
    assert outcomes["gap_too_small"] > 0 and outcomes["started"] > 0, outcomes


def test_full_throttle_ends_in_a_reported_collision_with_the_ceiling(
    backend: HighwayBackend,
) -> None:
    small = {"vehicles_count": 6, "vehicles_behind": 1}  # a short run-on for the ceiling
    first = backend.reset("cf", 5, options(backend, "cf", **small))
    leader = first.neighbours.leader.id
    last = run(backend, first, [(3.0, 0)] * 3000)[-1]
    assert last.terminated and not last.truncated and last.reason == "collision"
    assert last.events.collision and last.events.collision_with == leader
    assert last.neighbours.leader.gap < 0.5  # a real overlap (or about to be one)
    trip = last.ceiling
    assert trip is not None and trip.id == leader
    assert trip.arrival_time is not None and trip.average_speed is not None
    assert trip.arrival_time > last.time
    assert trip.average_speed * (trip.arrival_time - trip.depart_time) == pytest.approx(LENGTH)
    with pytest.raises(BackendError) as refused:
        backend.step(10_000, 0.0, 0)
    assert refused.value.code == ErrorCode.OUT_OF_ORDER


def test_an_idm_episode_reaches_the_end_of_the_road_behind_its_ceiling(
    backend: HighwayBackend,
) -> None:
    driver = IDMDriver()
    small = {"vehicles_count": 8, "vehicles_behind": 1}
    obs = backend.reset("cf", 6, options(backend, "cf", decision_interval=0.5, **small))
    stream = [obs]
    for seq in range(1, 1000):
        obs = backend.step(seq, *driver.act(obs))
        stream.append(obs)
        if obs.terminated or obs.truncated:
            break
    assert obs.reason == "end_of_road" and obs.terminated and obs.events.end_of_road
    assert obs.ego.position == LENGTH
    assert not any(o.events.collision for o in stream)
    trip = obs.ceiling
    assert trip is not None and trip.id == stream[0].neighbours.leader.id
    assert trip.arrival_time is not None and trip.arrival_time <= obs.time  # one lane
    ceiling = (LENGTH - stream[0].ego.position) / (trip.arrival_time - stream[0].time)
    average = (obs.ego.position - stream[0].ego.position) / (obs.time - stream[0].time)
    assert average <= ceiling + 1e-9


def test_the_time_limit_truncates(backend: HighwayBackend) -> None:
    changes: dict[str, OptionValue] = {"max_episode_time": 2.0, "report_ceiling": False}
    first = backend.reset("cflc", 7, options(backend, "cflc", **changes))
    stream = run(backend, first, [(0.0, 0)] * 100)
    last = stream[-1]
    assert len(stream) == 21
    assert last.truncated and not last.terminated and last.reason == "time_limit"
    assert all(not o.reason for o in stream[:-1])
    assert last.ceiling is None  # not asked for


def test_without_a_leader_there_is_no_ceiling(backend: HighwayBackend) -> None:
    first = backend.reset("cf", 8, options(backend, "cf", **FREE_ROAD))
    assert not first.neighbours.leader.present
    last = run(backend, first, [(3.0, 0)] * 2000)[-1]
    assert last.reason == "end_of_road" and last.ceiling is None
    assert last.ego.position == LENGTH


def test_the_same_seed_gives_the_same_stream(backend: HighwayBackend) -> None:
    def stream(seed: int) -> list[Observation]:
        first = backend.reset("cflc", seed, options(backend, "cflc", report_ceiling=False))
        pattern = [(0.5, 0), (0.0, 1), (-0.5, 0), (1.0, 0), (-1.0, -1)] * 8
        return run(backend, first, pattern)

    once, twice = stream(11), stream(11)
    assert once == twice
    assert stream(12) != once


def test_the_simulator_can_drive_the_ego(backend: HighwayBackend) -> None:
    agent = backend.reset("cflc", 9, options(backend, "cflc"))
    first = backend.reset("cflc", 9, options(backend, "cflc", ego_driver="simulator"))
    assert first == agent  # the same scene: highway-env drove the ego in both warm-ups
    stream = run(backend, first, [(3.0, 1)] * 50)
    for obs in stream[1:]:
        assert obs.action.acceleration_limited_by == "simulator"
        assert obs.action.lane_change_refused == "simulator_drives"
        assert obs.action.acceleration == pytest.approx(obs.ego.acceleration)
    assert not any(o.events.collision for o in stream)
    assert any(o.ego.acceleration != 3.0 for o in stream[1:])
    alias = backend.reset("cflc", 9, options(backend, "cflc", ego_driver="sumo"))
    assert alias == first


@pytest.mark.parametrize(
    "changes",
    [
        {"ego_driver": "robot"},
        {"decision_interval": 0.15},
        {"vehicles_behind": 21},
        {"vehicles_count": 1000, "vehicles_behind": 0},
        {"vehicles_density": 0.0},
        {"vehicles_count": 200, "vehicles_behind": 200, "vehicles_density": 0.05},
        {"max_episode_time": -1.0},
    ],
)
def test_invalid_options_are_refused(backend: HighwayBackend, changes: dict) -> None:
    with pytest.raises(BackendError) as refused:
        backend.reset("cf", 1, options(backend, "cf", **changes))
    assert refused.value.code == ErrorCode.INVALID_OPTION
