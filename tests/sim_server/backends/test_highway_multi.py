"""Many egos on the highway-env backend (protocol 1.4: `reset_many` / `step_many`), in-process."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import pytest

pytest.importorskip("highway_env")

from agent_client.drivers.idm import IDMDriver
from protocol.codec import decode_reply, encode
from protocol.errors import ErrorCode
from protocol.messages import (
    ROAD_RANGE,
    EgoObservation,
    EndReason,
    MultiObservation,
    Observation,
    OptionValue,
    Road,
    road_ahead,
)
from sim_server.backends.base import SINGLE_EGO_ID
from sim_server.backends.highway import MAX_HIGHWAY_EGOS, HighwayBackend
from sim_server.errors import BackendError

LENGTH = 2000.0
IDS = ["ego.0", "ego.1", "ego.2"]
COLUMN = {"vehicles_count": 2, "vehicles_behind": 2}
"""Two humans behind, then the three egos one after another (no human between them)."""

Policy = Callable[[EgoObservation, int], tuple[float, int]]
"""The command of one ego at step `seq`."""


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


def reset_many(
    backend: HighwayBackend, scenario: str, egos: int, seed: int = 1, **changes: OptionValue
) -> MultiObservation:
    return backend.reset_many(
        scenario, seed, options(backend, scenario, egos=egos, **changes), egos
    )


def running(frame: MultiObservation) -> list[str]:
    return [e.id for e in frame.egos if not (e.terminated or e.truncated)]


def as_observation(frame: MultiObservation, ego: EgoObservation) -> Observation:
    return Observation(
        frame.seq, frame.time, ego.ego, ego.neighbours, ego.events, ego.action, road=ego.road
    )


def drive(
    backend: HighwayBackend, first: MultiObservation, policy: Policy, steps: int | None = None
) -> list[MultiObservation]:
    """Step every running ego until the episode ends (or for `steps` steps); seq 0 and every
    frame after it."""
    frames, frame = [first], first
    for seq in range(1, 1 + (steps or 5000)):
        by_id = {e.id: e for e in frame.egos}
        commands = {ego: policy(by_id[ego], seq) for ego in running(frame)}
        frame = backend.step_many(seq, commands)
        frames.append(frame)
        if frame.terminated or frame.truncated:
            return frames
    assert steps is not None, "the episode never ended"
    return frames


def idm(idm_driver: IDMDriver) -> Policy:
    def policy(ego: EgoObservation, seq: int) -> tuple[float, int]:
        obs = Observation(seq, 0.0, ego.ego, ego.neighbours, ego.events, ego.action)
        return idm_driver.act(obs)

    return policy


def test_the_scenarios_offer_egos(backend: HighwayBackend) -> None:
    for info in backend.scenarios():
        assert info.options["egos"] == 1
    assert backend.max_egos == MAX_HIGHWAY_EGOS == 16


def test_three_egos_on_one_lane_see_each_other(backend: HighwayBackend) -> None:
    first = reset_many(backend, "cf", 3, **COLUMN)
    assert first.seq == 0 and first.time == pytest.approx(5.0)
    assert [e.id for e in first.egos] == IDS  # highway-env's controlled_vehicles: rear first
    assert not (first.terminated or first.truncated or any(e.reason for e in first.egos))
    positions = [e.ego.position for e in first.egos]
    assert positions == sorted(positions) and positions[0] > 0 and positions[-1] < LENGTH
    rear, middle, front = first.egos
    assert rear.neighbours.leader.id == "ego.1" and rear.neighbours.follower.id == "h1"
    assert middle.neighbours.leader.id == "ego.2" and middle.neighbours.follower.id == "ego.0"
    assert not front.neighbours.leader.present and front.neighbours.follower.id == "ego.1"
    assert rear.neighbours.leader.gap == pytest.approx(middle.neighbours.follower.gap)
    assert rear.neighbours.leader.gap == pytest.approx(positions[1] - 5.0 - positions[0])
    assert middle.neighbours.leader.speed == pytest.approx(front.ego.speed)
    assert rear.neighbours.leader.speed == pytest.approx(middle.ego.speed)


def test_each_ego_applies_its_own_command(backend: HighwayBackend) -> None:
    first = reset_many(backend, "cf", 3, **COLUMN)
    frame = backend.step_many(1, {"ego.0": (-50.0, 1), "ego.1": (0.5, 0), "ego.2": (-1.0, 0)})
    assert frame.seq == 1 and frame.time == pytest.approx(first.time + 0.1)
    rear, middle, front = frame.egos
    assert rear.action.acceleration == -6.0 and rear.action.acceleration_limited_by == "bounds"
    assert rear.action.lane_change_refused == "no_lane" and rear.events.lane_change_refused
    assert middle.action.acceleration == 0.5 and middle.ego.acceleration == 0.5
    assert front.action.acceleration == -1.0
    for before, after, applied in zip(first.egos, frame.egos, (-6.0, 0.5, -1.0), strict=True):
        assert after.ego.speed == pytest.approx(before.ego.speed + 0.1 * applied, abs=1e-9)


def test_three_egos_on_three_lanes_each_with_its_own_neighbours(backend: HighwayBackend) -> None:
    adjacent = {"vehicles_count": 4, "vehicles_behind": 4}  # the egos spawn one after another
    first = reset_many(backend, "cflc", 3, 4, report_ceiling=False, **adjacent)
    assert [e.id for e in first.egos] == IDS
    assert len({e.ego.lane for e in first.egos}) > 1  # on different lanes (random)
    frames = drive(backend, first, idm(IDMDriver()), steps=40)
    frame = frames[-1]
    assert not (frame.terminated or frame.truncated)
    seen_ego_neighbour = False
    for frame in frames:
        by_id = {e.id: e for e in frame.egos}
        assert len({e.ego.position for e in frame.egos}) == 3
        for ego in frame.egos:
            slots = ("leader", "follower", "left_leader", "left_follower",
                     "right_leader", "right_follower")  # fmt: skip
            for slot in slots:
                neighbour = getattr(ego.neighbours, slot)
                assert neighbour.id != ego.id
                if neighbour.id in by_id:
                    seen_ego_neighbour = True
                    other = by_id[neighbour.id]
                    assert neighbour.speed == pytest.approx(other.ego.speed)
                    ahead = other.ego.position - ego.ego.position - 5.0
                    behind = ego.ego.position - other.ego.position - 5.0
                    expected = ahead if "leader" in slot else behind
                    assert neighbour.gap == pytest.approx(expected, abs=0.5)  # lateral offsets
    assert seen_ego_neighbour


def test_lane_changes_are_each_egos_own(backend: HighwayBackend) -> None:
    free = {"vehicles_count": 0, "vehicles_behind": 0, "report_ceiling": False}
    first = reset_many(backend, "cflc", 3, 4, **free)
    lanes = {e.id: e.ego.lane for e in first.egos}
    moving = next(e.id for e in first.egos if e.ego.lane < 2)
    frame = backend.step_many(1, {ego: (0.0, 1 if ego == moving else 0) for ego in IDS})
    by_id = {e.id: e for e in frame.egos}
    assert by_id[moving].events.lane_change_started and by_id[moving].ego.changing_lane == 1
    assert all(not e.events.lane_change_started and e.ego.changing_lane == 0
               for e in frame.egos if e.id != moving)  # fmt: skip
    for seq in range(2, 60):
        frame = backend.step_many(seq, {ego: (0.0, 0) for ego in IDS})
        if {e.id: e for e in frame.egos}[moving].events.lane_change_completed:
            break
    else:
        pytest.fail("the lane change did not complete within 6 s")
    after = {e.id: e.ego.lane for e in frame.egos}
    assert after == {**lanes, moving: lanes[moving] + 1}


def test_an_ego_that_crashes_ends_alone_and_leaves_the_road(backend: HighwayBackend) -> None:
    # ego.0, h0, ego.1, h1, ego.2, h2 (near_split of 3 humans over 3 egos): ego.1 runs into h1
    spread = {"vehicles_count": 3, "vehicles_behind": 0, "max_episode_time": 30.0}
    first = reset_many(backend, "cf", 3, 5, **spread, report_ceiling=False)
    assert [e.neighbours.leader.id for e in first.egos] == ["h0", "h1", "h2"]
    careful = idm(IDMDriver())

    def policy(ego: EgoObservation, seq: int) -> tuple[float, int]:
        return (3.0, 0) if ego.id == "ego.1" else careful(ego, seq)

    frames = drive(backend, first, policy)
    crash = next(f for f in frames if "ego.1" not in running(f))
    ended = {e.id: e for e in crash.egos if e.terminated or e.truncated}
    assert list(ended) == ["ego.1"]
    mine = ended["ego.1"]
    assert mine.terminated and mine.reason == "collision" and mine.events.collision
    assert mine.events.collision_with == "h1"
    assert not (crash.terminated or crash.truncated or crash.reason)
    assert running(crash) == ["ego.0", "ego.2"]
    later = frames[frames.index(crash) + 1 :]
    assert later and all([e.id for e in f.egos] == ["ego.0", "ego.2"] for f in later)
    assert all(n.id != "ego.1" for f in later for e in f.egos
               for n in (e.neighbours.leader, e.neighbours.follower))  # fmt: skip
    last = frames[-1]
    assert last.truncated and not last.terminated and last.reason == "time_limit"
    assert all(e.truncated and e.reason == "time_limit" for e in last.egos)
    assert last.time == pytest.approx(first.time + 30.0)
    with pytest.raises(BackendError) as refused:
        backend.step_many(len(frames), {"ego.0": (0.0, 0), "ego.2": (0.0, 0)})
    assert refused.value.code == ErrorCode.OUT_OF_ORDER


def test_two_egos_that_collide_end_both_and_leave_the_road(backend: HighwayBackend) -> None:
    first = reset_many(backend, "cf", 3, 2, **COLUMN, report_ceiling=False)
    frames = drive(backend, first, lambda ego, seq: (3.0 if ego.id == "ego.1" else 0.0, 0))
    crash = next(f for f in frames if len(running(f)) < len(f.egos))
    ended = {e.id: e.events.collision_with for e in crash.egos if e.terminated}
    assert ended == {"ego.1": "ego.2", "ego.2": "ego.1"}
    assert running(crash) == ["ego.0"] and not crash.terminated
    after = frames[frames.index(crash) + 1]
    assert [e.id for e in after.egos] == ["ego.0"]
    assert not after.egos[0].neighbours.leader.present  # both are gone, nobody ahead


def test_the_last_ego_to_end_terminates_the_episode(backend: HighwayBackend) -> None:
    free = {"vehicles_count": 0, "vehicles_behind": 0, "report_ceiling": False}
    first = reset_many(backend, "cf", 2, 3, **free)
    frames = drive(backend, first, lambda ego, seq: (3.0 if ego.id == "ego.1" else 0.0, 0))
    reasons = [(e.id, e.reason) for f in frames for e in f.egos if e.reason]
    assert reasons == [("ego.1", "end_of_road"), ("ego.0", "end_of_road")]
    last = frames[-1]
    assert last.terminated and not last.truncated and last.reason == "end_of_road"
    assert [e.id for e in last.egos] == ["ego.0"] and last.egos[0].ego.position == LENGTH


def test_the_time_limit_truncates_every_ego(backend: HighwayBackend) -> None:
    first = reset_many(backend, "cflc", 3, 7, max_episode_time=2.0, report_ceiling=False)
    frames = drive(backend, first, lambda ego, seq: (0.0, 0))
    assert len(frames) == 21
    assert all(not f.reason and not any(e.reason for e in f.egos) for f in frames[:-1])
    last = frames[-1]
    assert last.truncated and not last.terminated and last.reason == "time_limit"
    assert [e.id for e in last.egos] == IDS
    assert all(e.truncated and not e.terminated and e.reason == "time_limit" for e in last.egos)


def test_a_multi_observation_survives_the_wire(backend: HighwayBackend) -> None:
    first = reset_many(backend, "cflc", 3, 8, report_ceiling=False)
    frames = drive(backend, first, lambda ego, seq: (0.5, 1 if seq == 2 else 0), steps=5)
    frames.append(replace(frames[-1], truncated=True, reason="time_limit"))
    for frame in frames:
        assert decode_reply(encode(frame)) == frame


def test_many_egos_are_deterministic(backend: HighwayBackend) -> None:
    def stream(seed: int) -> list[MultiObservation]:
        first = reset_many(backend, "cflc", 3, seed, max_episode_time=3.0, report_ceiling=False)
        return drive(backend, first, lambda ego, seq: ((seq % 3) - 1.0, int(seq % 7 == 1)))

    once = stream(11)
    assert stream(11) == once
    assert stream(12) != once


def test_one_ego_through_reset_many_is_the_one_ego_episode(backend: HighwayBackend) -> None:
    for scenario in ("cf", "cflc", "merge"):
        plain = HighwayBackend()
        obs = plain.reset(scenario, 9, options(plain, scenario))
        multi = reset_many(backend, scenario, 1, 9)
        pattern = [(0.5, 0), (0.0, 1), (-0.5, 0), (1.0, 0), (-1.0, -1)] * 4
        for seq, command in enumerate([None, *pattern]):
            if command is not None:
                obs = plain.step(seq, *command)
                multi = backend.step_many(seq, {SINGLE_EGO_ID: command})
            assert [e.id for e in multi.egos] == [SINGLE_EGO_ID]
            (mine,) = multi.egos
            assert as_observation(multi, mine) == replace(
                obs, terminated=False, truncated=False, reason="", ceiling=None
            )
            assert (mine.terminated, mine.truncated, mine.reason) == (
                obs.terminated, obs.truncated, obs.reason,
            )  # fmt: skip


def test_the_simulator_can_drive_every_ego(backend: HighwayBackend) -> None:
    first = reset_many(backend, "cflc", 3, 9, ego_driver="simulator", max_episode_time=3.0)
    frames = drive(backend, first, lambda ego, seq: (3.0, 1))
    for frame in frames[1:]:
        for ego in frame.egos:
            assert ego.action.acceleration_limited_by == "simulator"
            assert ego.action.lane_change_refused == "simulator_drives"
    assert frames[-1].truncated


def test_sixteen_egos_fit_and_seventeen_are_refused(backend: HighwayBackend) -> None:
    many = reset_many(backend, "cflc", MAX_HIGHWAY_EGOS, 1, report_ceiling=False)
    assert [e.id for e in many.egos] == [f"ego.{k}" for k in range(MAX_HIGHWAY_EGOS)]
    frame = backend.step_many(1, {e.id: (0.0, 0) for e in many.egos})
    assert len(frame.egos) == MAX_HIGHWAY_EGOS
    with pytest.raises(BackendError) as refused:
        reset_many(backend, "cf", MAX_HIGHWAY_EGOS + 1)
    assert refused.value.code == ErrorCode.INVALID_OPTION
    assert "at most 16" in str(refused.value)
    after = backend.step_many(2, {e.id: (0.0, 0) for e in many.egos})  # the episode goes on
    assert after.seq == 2


def test_egos_placed_beyond_the_road_are_refused(backend: HighwayBackend) -> None:
    crowded: dict[str, OptionValue] = {
        "vehicles_count": 200,
        "vehicles_behind": 190,
        "vehicles_density": 0.1,
    }
    with pytest.raises(BackendError) as refused:
        reset_many(backend, "cf", 3, 1, **crowded)
    assert refused.value.code == ErrorCode.INVALID_OPTION
    assert "ego." in str(refused.value)


def test_an_ego_that_ends_inside_a_decision_is_observed_where_it_ended(
    backend: HighwayBackend,
) -> None:
    spread = {"vehicles_count": 3, "vehicles_behind": 0, "max_episode_time": 30.0}
    first = reset_many(backend, "cf", 3, 5, **spread, decision_interval=1.0, report_ceiling=False)
    careful = idm(IDMDriver())

    def policy(ego: EgoObservation, seq: int) -> tuple[float, int]:
        return (3.0, 0) if ego.id == "ego.1" else careful(ego, seq)

    frames = drive(backend, first, policy)
    crash = next(f for f in frames if "ego.1" not in running(f))
    mine = next(e for e in crash.egos if e.id == "ego.1")
    assert mine.reason == "collision" and mine.events.collision_with == "h1"
    assert mine.neighbours.leader.id == "h1" and mine.neighbours.leader.gap < 0.5  # at the crash
    assert crash.time == pytest.approx(first.time + crash.seq * 1.0)  # the others drove on
    assert running(crash) == ["ego.0", "ego.2"]
    assert frames[-1].truncated and frames[-1].time == pytest.approx(first.time + 30.0)


def test_every_ego_sees_the_road_ahead(backend: HighwayBackend) -> None:
    first = reset_many(backend, "cflc", 3, 2, max_episode_time=2.0, report_ceiling=False)
    for frame in drive(backend, first, lambda ego, seq: (0.0, int(seq % 5 == 1))):
        for ego in frame.egos:
            assert ego.road == road_ahead(replace(as_observation(frame, ego), road=None))


def test_egos_merge_one_after_another_from_the_ramp(backend: HighwayBackend) -> None:
    merge = {"main_lanes": 2, "acceleration_lane": 250.0, "ramp_length": 150.0,
             "ramp_vehicles": 0, "vehicles_count": 6, "report_ceiling": False,
             "warmup": 7.0}  # fmt: skip
    first = reset_many(backend, "merge", 2, 3, **merge)
    rear, front = first.egos
    assert (rear.id, front.id) == ("ego.0", "ego.1")
    assert 0.0 < rear.ego.position < front.ego.position < 400.0
    assert (rear.ego.lane_count, front.ego.lane_count) == (1, 3)  # the ramp; the lane after it
    assert rear.neighbours.leader.id == "ego.1"  # seen across the ramp's end
    assert front.neighbours.follower.id == "ego.0"
    assert rear.neighbours.leader.gap == pytest.approx(front.ego.position - 5.0 - rear.ego.position)
    for ego in first.egos:
        assert ego.road == Road(pytest.approx(400.0 - ego.ego.position), int(ego.ego.lane_count > 1),
                                ROAD_RANGE if ego.ego.lane_count > 1 else 0.0, 0.0)  # fmt: skip

    def merging(ego: EgoObservation, seq: int) -> tuple[float, int]:
        road, leader = ego.road, ego.neighbours.leader
        assert road is not None
        acceleration = min(1.0, ego.ego.speed_limit - ego.ego.speed)
        if leader.present:
            keep = 0.5 * (leader.gap - 5.0 - 1.5 * ego.ego.speed) + leader.speed - ego.ego.speed
            acceleration = min(acceleration, keep)
        return acceleration, road.lanes_to_change

    frames = drive(backend, first, merging)
    ends = {e.id: e.reason for frame in frames for e in frame.egos if e.reason}
    assert ends == {"ego.0": EndReason.END_OF_ROAD, "ego.1": EndReason.END_OF_ROAD}
    completed = {e.id for frame in frames for e in frame.egos if e.events.lane_change_completed}
    assert completed == {"ego.0", "ego.1"}
