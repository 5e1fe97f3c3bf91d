"""The highway-env backend in-process: the protocol's semantics on another simulator."""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterable
from dataclasses import replace

import pytest

pytest.importorskip("highway_env")

from agent_client.drivers.idm import IDMDriver
from protocol.errors import ErrorCode
from protocol.messages import ROAD_RANGE, EndReason, Observation, OptionValue, Road, road_ahead
from sim_server.backends.highway import SCENARIOS, CorridorScenario, HighwayBackend
from sim_server.backends.options import TrafficOptions
from sim_server.backends.sumo.corridors import CORRIDORS
from sim_server.errors import BackendError

LENGTH = 2000.0
FREE_ROAD = {"vehicles_count": 0, "vehicles_behind": 0}
MOTORWAY, RAMP = 100 / 3.6, 80 / 3.6
MERGE: dict[str, OptionValue] = {
    "main_lanes": 2, "acceleration_lane": 250.0, "ramp_length": 150.0, "report_ceiling": False,
}  # fmt: skip
"""A merge whose ramp and acceleration lane end 400 m from the ramp's start (900 m: the route)."""
Policy = Callable[[Observation], tuple[float, int]]


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
    assert set(infos) == {"cf", "cflc", "merge", "exit", "lanedrop"}
    for info in infos.values():
        assert info.step_length == pytest.approx(0.1)
        for name in ("decision_interval", "max_episode_time", "warmup", "stop_speed",
                     "stop_gap", "stop_patience", "lane_end_patience", "report_ceiling",
                     "ego_driver", "vehicles_count", "vehicles_behind",
                     "vehicles_density"):  # fmt: skip
            assert name in info.options, name
        for name in ("insertion_timeout", "flow", "sigma", "speed_factor_mean", "ramp_flow",
                     "exit_share", "ego_start"):  # fmt: skip
            assert name not in info.options, name
    own = {
        "merge": {"main_lanes": 0, "acceleration_lane": 0.0, "ramp_length": 0.0,
                  "ramp_vehicles": 2},
        "exit": {"main_lanes": 0, "exit_distance": 0.0, "deceleration_lane": 0.0, "ego_lane": -1},
        "lanedrop": {"drop_distance": 0.0, "dropped_lane": "random", "ego_lane": -1},
    }  # fmt: skip
    for name, defaults in own.items():
        assert {k: infos[name].options[k] for k in defaults} == defaults
        assert infos[name].options["vehicles_density"] == 0.5
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


# ----------------------------------------------------------------------- the road ahead (1.6)


def drive(
    backend: HighwayBackend, first: Observation, policy: Policy, steps: int = 3000
) -> list[Observation]:
    """`first` and every observation after it, `policy` driving, until the episode ends."""
    stream = [first]
    while not (stream[-1].terminated or stream[-1].truncated) and len(stream) <= steps:
        stream.append(backend.step(stream[-1].seq + 1, *policy(stream[-1])))
    return stream


def scripted(change: bool = True) -> Policy:
    """A plain driver for the corridors: towards the speed limit, about 1.5 s behind its leader,
    braking to stop before the end of a lane it must leave; with `change`, it asks at every step
    for the lane change the road ahead needs (refused while one is under way or unsafe)."""

    def policy(obs: Observation) -> tuple[float, int]:
        ego, leader, road = obs.ego, obs.neighbours.leader, obs.road
        assert road is not None
        acceleration = min(1.5, ego.speed_limit - ego.speed)
        if leader.present:
            keep = 0.5 * (leader.gap - 5.0 - 1.5 * ego.speed) + leader.speed - ego.speed
            acceleration = min(acceleration, keep)
        if road.lanes_to_change and road.lane_end < ROAD_RANGE:
            needed = ego.speed**2 / (2.0 * max(road.lane_end - 3.0, 0.1))
            if needed > 1.5:
                acceleration = min(acceleration, -needed)
        towards = (road.lanes_to_change > 0) - (road.lanes_to_change < 0)
        return acceleration, towards if change else 0

    return policy


def test_every_lane_of_cf_and_cflc_leads_on(backend: HighwayBackend) -> None:
    for scenario, seed in (("cf", 1), ("cflc", 1), ("cflc", 2), ("cflc", 3)):
        first = backend.reset(scenario, seed, options(backend, scenario, report_ceiling=False))
        pattern = [(0.0, 1), (0.0, 0), (0.0, -1)] * 10
        for obs in run(backend, first, pattern):
            assert obs.road == road_ahead(replace(obs, road=None))  # the open road
    assert first.road is not None and first.road.lane_end == ROAD_RANGE


def test_the_corridors_draw_the_sumo_corridors_geometry(backend: HighwayBackend) -> None:
    """The same seed (and options) draws the same lengths and lanes on both servers."""
    traffic = TrafficOptions()
    for kind in ("merge", "exit", "lanedrop"):
        ours = SCENARIOS[kind]
        assert isinstance(ours, CorridorScenario)
        theirs = CORRIDORS[kind]
        for seed in range(12):
            info = {s.name: s for s in backend.scenarios()}[kind]
            geometry = ours.geometry(seed, info.options)
            net = theirs.network(theirs.OPTIONS[kind]().parse({}), traffic, seed)
            x = {name: x for name, x, _ in net.nodes}
            lanes = {edge[0]: edge[3] for edge in net.edges}
            if kind == "merge":
                assert geometry.main_lanes == lanes["main_up"]
                assert geometry.acceleration_lane == x["merge_end"] - x["merge_start"]
                assert geometry.ramp_length == x["merge_start"] - x["ramp_start"]
            elif kind == "exit":
                assert geometry.main_lanes == lanes["main"]
                assert geometry.exit_distance == x["diverge"] - x["start"]
                assert geometry.deceleration_lane == x["diverge"] - x["decel_start"]
            else:
                assert geometry.drop_distance == x["drop"] - x["start"]
                first_going_on = net.connections[0][2]  # SUMO counts lanes from the right
                assert geometry.dropped_lane == ("left" if first_going_on == 0 else "right")
    merge = SCENARIOS["merge"]
    assert isinstance(merge, CorridorScenario)
    assert merge.geometry(1, {**options(backend, "merge"), **MERGE}).ramp_length == 150.0


def test_the_ego_enters_from_the_ramp_and_sees_its_lane_end(backend: HighwayBackend) -> None:
    changes = {**MERGE, "vehicles_count": 0, "vehicles_behind": 0, "ramp_vehicles": 0}
    first = backend.reset("merge", 1, options(backend, "merge", **changes))
    assert (first.ego.lane, first.ego.lane_count) == (0, 1)  # the ramp: one lane
    assert first.ego.speed_limit == pytest.approx(RAMP)
    assert 0.0 < first.ego.position < 150.0
    assert first.road == Road(pytest.approx(400.0 - first.ego.position), 0, 0.0, 0.0)
    for side in ("left_leader", "left_follower", "right_leader", "right_follower"):
        assert not getattr(first.neighbours, side).present
    stream = drive(backend, first, scripted(change=False), steps=200)
    merging = [o for o in stream if o.ego.lane_count == 3]
    assert merging, "never reached the acceleration lane"
    for obs in merging:
        assert (obs.ego.lane, obs.ego.speed_limit) == (0, pytest.approx(MOTORWAY))
        assert obs.road == Road(pytest.approx(400.0 - obs.ego.position), 1, ROAD_RANGE, 0.0)
    ends = [o.road.lane_end for o in stream if o.road is not None]
    assert all(later <= before for before, later in itertools.pairwise(ends))


def test_a_merge_reaches_the_end_of_the_road(backend: HighwayBackend) -> None:
    changes = {**MERGE, "vehicles_count": 8, "vehicles_behind": 3, "ramp_vehicles": 1}
    first = backend.reset("merge", 2, options(backend, "merge", **changes))
    stream = drive(backend, first, scripted())
    last = stream[-1]
    assert last.reason == EndReason.END_OF_ROAD and last.ego.position == 900.0
    assert not any(o.events.collision for o in stream)
    (merged,) = [i for i, o in enumerate(stream) if o.events.lane_change_completed]
    before, after = stream[:merged], stream[merged:]
    on_the_lane = [o for o in before if (o.ego.lane, o.ego.lane_count) == (0, 3)]
    ends = [o.road.lane_end for o in on_the_lane if o.road is not None]
    assert len(ends) == len(on_the_lane) > 10
    assert all(later < before for before, later in itertools.pairwise(ends))
    assert all(o.road is not None and o.road.lanes_to_change == 1 for o in on_the_lane)
    assert any(o.action.lane_change_refused == "gap_too_small" for o in before)
    for obs in after:  # on the motorway's right lane: beside the acceleration lane, then not
        assert obs.ego.lane == obs.ego.lane_count - 2
        assert obs.road is not None and obs.road.lane_end == ROAD_RANGE
        assert obs.road.lanes_to_change == 0 and obs.road.left_lane_end == ROAD_RANGE
        beside = obs.road.right_lane_end
        assert beside == (
            0.0 if obs.ego.lane == 0 else pytest.approx(max(0.0, 400.0 - obs.ego.position))
        )
    assert after[-1].road == Road(ROAD_RANGE, 0, ROAD_RANGE, 0.0)  # the lane has ended


def test_keeping_a_lane_that_ends_ends_at_the_lane_end(backend: HighwayBackend) -> None:
    changes = {**MERGE, "vehicles_count": 0, "vehicles_behind": 0, "ramp_vehicles": 0}
    waits = backend.reset("merge", 1, options(backend, "merge", lane_end_patience=2.0, **changes))
    stream = drive(backend, waits, scripted(change=False))
    last = stream[-1]
    assert last.terminated and last.reason == EndReason.LANE_END
    assert last.road is not None and last.road.lane_end <= 15.0 and last.ego.speed < 1.0
    standing = [o for o in stream if o.ego.speed < 1.0 and o.road and o.road.lane_end <= 15.0]
    assert last.time - standing[0].time == pytest.approx(2.0)
    # Driving on past the end is ended there at once: no lane goes on beyond it.
    rolls = backend.reset("merge", 1, options(backend, "merge", **changes))
    past = drive(backend, rolls, lambda obs: (0.0, 0))[-1]
    assert past.reason == EndReason.LANE_END and past.ego.speed == pytest.approx(rolls.ego.speed)
    assert past.road is not None and past.road.lane_end == 0.0
    assert 400.0 <= past.ego.position < 400.0 + past.ego.speed * 0.1 + 1e-9


def test_the_exit_is_reached_by_moving_right(backend: HighwayBackend) -> None:
    changes: dict[str, OptionValue] = {
        "main_lanes": 3, "exit_distance": 600.0, "deceleration_lane": 200.0, "ego_lane": 2,
        "warmup": 0.0, "vehicles_count": 2, "vehicles_behind": 2, "report_ceiling": False,
    }  # fmt: skip
    first = backend.reset("exit", 3, options(backend, "exit", **changes))
    start = first.ego.position
    assert (first.ego.lane, first.ego.lane_count) == (2, 3)
    assert first.road == Road(pytest.approx(600.0), -2, 0.0, pytest.approx(600.0))
    stream = drive(backend, first, scripted())
    last = stream[-1]
    assert last.reason == EndReason.END_OF_ROAD
    assert last.ego.position == pytest.approx(start + 600.0 + 250.0)  # the off-ramp's end
    assert (last.ego.lane_count, last.ego.speed_limit) == (1, pytest.approx(RAMP))
    assert sum(o.events.lane_change_completed for o in stream) == 3
    decelerating = [o for o in stream if o.ego.lane_count == 4 and o.ego.lane == 0]
    assert decelerating and all(o.road and o.road.lane_end == ROAD_RANGE for o in decelerating)
    kept = backend.reset("exit", 3, options(backend, "exit", **changes))
    missed = drive(backend, kept, lambda obs: (0.0, 0))[-1]  # on, past the exit
    assert missed.reason == EndReason.LANE_END and missed.ego.speed == kept.ego.speed
    assert 600.0 < missed.ego.position - start < 600.0 + kept.ego.speed * 0.1 + 1e-9


def test_a_dropped_lane_is_left_for_the_lanes_that_go_on(backend: HighwayBackend) -> None:
    changes: dict[str, OptionValue] = {
        "drop_distance": 300.0, "dropped_lane": "right", "ego_lane": 0, "warmup": 0.0,
        "vehicles_count": 2, "vehicles_behind": 1, "report_ceiling": False,
    }  # fmt: skip
    first = backend.reset("lanedrop", 4, options(backend, "lanedrop", **changes))
    assert (first.ego.lane, first.ego.lane_count) == (0, 3)
    assert first.road == Road(pytest.approx(300.0), 1, ROAD_RANGE, 0.0)
    stream = drive(backend, first, scripted())
    assert stream[-1].reason == EndReason.END_OF_ROAD
    after = [o for o in stream if o.ego.position > first.ego.position + 300.0 + 2.5]
    assert after and all(o.ego.lane_count == 2 for o in after)  # beyond the drop (its middle)


def test_highway_envs_own_drivers_merge(backend: HighwayBackend) -> None:
    """With ``ego_driver`` simulator the ego is one of highway-env's humans: MOBIL takes it off
    the acceleration lane (towards its route's lane, when safe), as it does the humans."""
    changes = {**MERGE, "ego_driver": "simulator"}
    first = backend.reset("merge", 3, options(backend, "merge", **changes))
    human = first.neighbours.leader.id  # ahead on the ramp
    assert human.startswith("h") and first.ego.lane_count == 1
    stream = drive(backend, first, lambda obs: (0.0, 0))
    assert stream[-1].reason == EndReason.END_OF_ROAD
    assert not any(o.events.collision for o in stream)
    assert {o.ego.lane_count for o in stream} >= {1, 3, 2}
    merged_first = [
        o for o in stream if (o.ego.lane, o.ego.lane_count) == (0, 3)
        and o.neighbours.left_leader.id == human
    ]  # fmt: skip
    assert merged_first, "the human ahead on the ramp did not merge before the ego"


def test_the_leader_at_entry_bounds_the_ego_only_along_its_route(backend: HighwayBackend) -> None:
    cut = {"max_episode_time": 1.0, "report_ceiling": True}
    first = backend.reset("merge", 4, options(backend, "merge", **cut))
    last = run(backend, first, [(0.0, 0)] * 20)[-1]
    assert last.reason == EndReason.TIME_LIMIT and last.ceiling is not None
    assert last.ceiling.id == first.neighbours.leader.id  # the human ahead on the ramp
    assert last.ceiling.arrival_time is not None and last.ceiling.arrival_time > last.time
    first = backend.reset("exit", 4, options(backend, "exit", **cut))
    assert first.neighbours.leader.present  # driving on past the exit: it bounds nothing
    assert run(backend, first, [(0.0, 0)] * 20)[-1].ceiling is None


def test_a_corridor_is_the_same_for_the_same_seed(backend: HighwayBackend) -> None:
    def stream(seed: int) -> list[Observation]:
        first = backend.reset("merge", seed, options(backend, "merge", report_ceiling=False))
        return run(backend, first, [(1.0, 1), (0.0, 0), (-0.5, 1)] * 20)

    once = stream(5)
    assert stream(5) == once and stream(6) != once


@pytest.mark.parametrize(
    ("scenario", "changes"),
    [
        ("merge", {"main_lanes": 1}),
        ("merge", {"acceleration_lane": 10.0}),
        ("merge", {"ramp_vehicles": 21}),
        ("exit", {"main_lanes": 5}),
        ("exit", {"exit_distance": 250.0, "deceleration_lane": 200.0}),
        ("exit", {"ego_lane": 4}),
        ("lanedrop", {"dropped_lane": "middle"}),
        ("lanedrop", {"drop_distance": 50.0}),
        ("merge", {"egos": 16}),
    ],
)
def test_invalid_corridor_options_are_refused(
    backend: HighwayBackend, scenario: str, changes: dict[str, OptionValue]
) -> None:
    given = options(backend, scenario, **changes)
    egos = given["egos"]
    assert isinstance(egos, int)
    with pytest.raises(BackendError) as refused:
        backend.reset_many(scenario, 1, given, egos)  # egos 1: the one-ego reset
    assert refused.value.code == ErrorCode.INVALID_OPTION
