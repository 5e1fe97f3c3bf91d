"""Many egos in one SUMO simulation (protocol 1.4: `reset_many` / `step_many`), real SUMO.

libsumo is one simulation per process: this module holds one libsumo backend (its ground truth
read from libsumo directly) and one TraCI backend for the byte-for-byte comparison.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import libsumo
import pytest

from agent_client.drivers.idm import IDMDriver
from protocol.codec import decode_reply, encode
from protocol.errors import ErrorCode
from protocol.messages import (
    EgoObservation,
    EndReason,
    MultiObservation,
    Observation,
    OptionValue,
    Traffic,
)
from sim_server.backends.sumo.backend import SumoBackend
from sim_server.backends.sumo.scenarios import EGO_TYPE, RING_EDGES, RingOptions
from sim_server.errors import BackendError

pytestmark = pytest.mark.sumo

SPEED_MODE_NO_CHECKS = 32
LANE_CHANGE_MODE_REQUESTS_ONLY = 512


@pytest.fixture(scope="module")
def scenario_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("scenarios")


@pytest.fixture(scope="module")
def backend(scenario_dir: Path) -> Iterator[SumoBackend]:
    sumo = SumoBackend(cache_dir=scenario_dir)
    yield sumo
    sumo.close()


@pytest.fixture(scope="module")
def traci_backend(scenario_dir: Path) -> Iterator[SumoBackend]:
    sumo = SumoBackend(cache_dir=scenario_dir, traci=True)
    yield sumo
    sumo.close()


def options(backend: SumoBackend, scenario: str, **changes: OptionValue) -> dict[str, OptionValue]:
    info = {s.name: s for s in backend.scenarios()}[scenario]
    return {**info.options, **changes}


def reset(
    backend: SumoBackend, scenario: str, seed: int, egos: int, **changes: OptionValue
) -> MultiObservation:
    return backend.reset_many(
        scenario, seed, options(backend, scenario, egos=egos, **changes), egos
    )


def single(multi: MultiObservation, ego: EgoObservation) -> Observation:
    """One ego's part as the `Observation` a one-ego driver reads."""
    return Observation(multi.seq, multi.time, ego.ego, ego.neighbours, ego.events, ego.action)


Policy = Callable[[MultiObservation, EgoObservation], tuple[float, int]]


def idm(drivers: dict[str, IDMDriver]) -> Policy:
    """The client's IDM, one driver per ego."""

    def act(multi: MultiObservation, ego: EgoObservation) -> tuple[float, int]:
        return drivers.setdefault(ego.id, IDMDriver()).act(single(multi, ego))

    return act


def drive(
    backend: SumoBackend,
    first: MultiObservation,
    policy: Policy,
    steps: int = 100_000,
    check: Callable[[MultiObservation], None] | None = None,
) -> list[MultiObservation]:
    """Step every running ego with `policy` until the episode ends (or `steps`)."""
    stream = [first]
    multi = first
    for seq in range(1, steps + 1):
        if multi.terminated or multi.truncated:
            break
        commands = {e.id: policy(multi, e) for e in multi.egos if not e.reason}
        multi = backend.step_many(seq, commands)
        stream.append(multi)
        if check is not None:
            check(multi)
    return stream


def ring_place(vehicle: str, ring_length: float) -> float:
    """Metres from the start of edge ``a`` to the vehicle's front (ground truth, libsumo)."""
    on_b = libsumo.vehicle.getRoadID(vehicle) == RING_EDGES[1]
    return libsumo.vehicle.getLanePosition(vehicle) + (ring_length / 2 if on_b else 0.0)


def around(ring_length: float) -> list[str]:
    """Every vehicle on the ring in the order of their places (ground truth, libsumo)."""
    return sorted(libsumo.vehicle.getIDList(), key=lambda v: ring_place(v, ring_length))


# --------------------------------------------------------------------------- the ring


def test_the_ring_places_the_egos_evenly_and_hands_them_over_after_the_warm_up(
    backend: SumoBackend,
) -> None:
    layout = RingOptions(vehicles=22)
    assert layout.ego_slots(4) == (0, 6, 11, 17)  # round(k x 22 / 4), halves up
    multi = reset(backend, "ring", 1, 4, warmup=0.0)
    ids = [e.id for e in multi.egos]
    assert ids == ["ego.0", "ego.1", "ego.2", "ego.3"]
    assert multi.seq == 0 and not (multi.terminated or multi.truncated or multi.reason)
    assert multi.traffic is None
    vehicles = set(libsumo.vehicle.getIDList())
    assert len(vehicles) == 22 and vehicles >= set(ids)
    assert {f"human{slot}" for slot in (0, 6, 11, 17)}.isdisjoint(vehicles)  # egos hold them
    for ego, slot in zip(multi.egos, (0, 6, 11, 17), strict=True):
        assert ego.ego.position == pytest.approx(layout.ring_position(slot), abs=0.01)
        assert libsumo.vehicle.getTypeID(ego.id) == EGO_TYPE
        assert libsumo.vehicle.getSpeedMode(ego.id) == SPEED_MODE_NO_CHECKS
        assert libsumo.vehicle.getLaneChangeMode(ego.id) == LANE_CHANGE_MODE_REQUESTS_ONLY
        assert not (ego.terminated or ego.truncated or ego.reason)
        assert ego.action.requested_acceleration == 0.0 and not ego.events.collision

    multi = reset(backend, "ring", 1, 4, warmup=60.0)  # the waves' warm-up: humans all
    assert multi.time == pytest.approx(60.0)
    assert all(libsumo.vehicle.getTypeID(e.id) == EGO_TYPE for e in multi.egos)
    assert all(e.ego.speed > 0.0 for e in multi.egos)  # they drove as humans


def test_idm_drives_eight_egos_among_ten_vehicles_their_neighbours_egos_too(
    backend: SumoBackend,
) -> None:
    length = 100.0
    first = reset(backend, "ring", 3, 8, vehicles=10, ring_length=length, warmup=10.0,
                  max_episode_time=30.0)  # fmt: skip
    assert RingOptions(vehicles=10, ring_length=length).ego_slots(8) == (0, 1, 3, 4, 5, 6, 8, 9)
    seen_ego_neighbours: set[str] = set()

    def check(multi: MultiObservation) -> None:
        order = around(length)
        for ego in multi.egos:
            if ego.reason:
                continue  # taken out
            at = order.index(ego.id)
            leader, follower = ego.neighbours.leader, ego.neighbours.follower
            assert leader.id == order[(at + 1) % len(order)]
            assert follower.id == order[at - 1]
            assert leader.gap > 0 and follower.gap > 0 and leader.lateral == 0.0
            front, back = ring_place(ego.id, length), ring_place(leader.id, length) - 5.0
            assert leader.gap == pytest.approx((back - front) % length, abs=1e-6)
            assert ego.ego.position % length == pytest.approx(front, abs=1e-6)
            seen_ego_neighbours.update(n for n in (leader.id, follower.id) if n.startswith("ego."))

    check(first)
    stream = drive(backend, first, idm({}), check=check)
    last = stream[-1]
    assert last.truncated and last.reason == EndReason.TIME_LIMIT and len(stream) == 301
    assert [e.id for e in last.egos] == [f"ego.{k}" for k in range(8)]
    assert all(e.truncated and e.reason == EndReason.TIME_LIMIT for e in last.egos)
    assert not any(e.events.collision for m in stream for e in m.egos)
    assert seen_ego_neighbours == {f"ego.{k}" for k in range(8)}  # every ego followed or led one
    assert all(e.action.acceleration_limited_by in ("", "bounds", "standstill", "speed_limit")
               for m in stream[1:] for e in m.egos)  # fmt: skip


def test_an_ego_ramming_its_leader_ends_alone_and_the_others_go_on(backend: SumoBackend) -> None:
    first = reset(backend, "ring", 1, 4, warmup=30.0, max_episode_time=40.0)
    drivers: dict[str, IDMDriver] = {}

    def ram_with_ego_1(multi: MultiObservation, ego: EgoObservation) -> tuple[float, int]:
        return (3.0, 0) if ego.id == "ego.1" else idm(drivers)(multi, ego)

    stream = drive(backend, first, ram_with_ego_1)
    crash = next(m for m in stream if any(e.terminated for e in m.egos))
    (rammer,) = [e for e in crash.egos if e.terminated]
    assert rammer.id == "ego.1" and rammer.reason == EndReason.COLLISION
    assert rammer.events.collision and rammer.events.collision_with.startswith("human")
    assert rammer.neighbours.leader.id == rammer.events.collision_with
    assert rammer.neighbours.leader.gap <= 0.0  # a real overlap
    assert not (crash.terminated or crash.truncated)  # the episode goes on
    assert [e.id for e in crash.egos] == ["ego.0", "ego.1", "ego.2", "ego.3"]
    after = stream[stream.index(crash) + 1 :]
    assert after and all([e.id for e in m.egos] == ["ego.0", "ego.2", "ego.3"] for m in after)
    assert stream[-1].truncated and stream[-1].reason == EndReason.TIME_LIMIT
    with pytest.raises(BackendError) as refused:
        backend.step_many(len(stream), {"ego.0": (0.0, 0)})
    assert refused.value.code == ErrorCode.OUT_OF_ORDER  # the episode has ended


def test_an_ego_that_collides_is_taken_out_at_that_simulation_step(backend: SumoBackend) -> None:
    first = reset(backend, "ring", 1, 4, warmup=30.0, decision_interval=1.0)
    drivers: dict[str, IDMDriver] = {}
    multi, seq = first, 0
    while not any(e.terminated for e in multi.egos):
        seq += 1
        commands = {
            e.id: (3.0, 0) if e.id == "ego.2" else idm(drivers)(multi, e) for e in multi.egos
        }
        multi = backend.step_many(seq, commands)
        assert seq < 60
    assert [e.id for e in multi.egos if e.terminated] == ["ego.2"]
    assert "ego.2" not in libsumo.vehicle.getIDList()  # gone while the decision went on
    assert {"ego.0", "ego.1", "ego.3"} <= set(libsumo.vehicle.getIDList())
    assert multi.time == pytest.approx(first.time + seq * 1.0)  # the others' full decision


def test_a_collision_between_two_egos_ends_both(backend: SumoBackend) -> None:
    # slots 0, 1, 3, 4, 5, 6, 8, 9 of 10: ego.0 follows ego.1
    first = reset(backend, "ring", 2, 8, vehicles=10, ring_length=100.0, warmup=10.0)
    assert first.egos[0].neighbours.leader.id == "ego.1"
    drivers: dict[str, IDMDriver] = {}

    def ego_0_rams_ego_1(multi: MultiObservation, ego: EgoObservation) -> tuple[float, int]:
        if ego.id == "ego.0":
            return 3.0, 0
        return (-6.0, 0) if ego.id == "ego.1" else idm(drivers)(multi, ego)

    stream = drive(backend, first, ego_0_rams_ego_1, steps=300)
    crash = next(m for m in stream if any(e.terminated for e in m.egos))
    ended = {e.id: e for e in crash.egos if e.terminated}
    assert set(ended) == {"ego.0", "ego.1"}
    assert ended["ego.0"].events.collision_with == "ego.1"
    assert ended["ego.1"].events.collision_with == "ego.0"
    assert all(e.reason == EndReason.COLLISION for e in ended.values())
    following = stream[stream.index(crash) + 1]
    assert [e.id for e in following.egos] == [f"ego.{k}" for k in range(2, 8)]


def test_the_time_limit_truncates_every_ego_at_once(backend: SumoBackend) -> None:
    first = reset(backend, "ring", 1, 4, warmup=10.0, max_episode_time=5.0)
    stream = drive(backend, first, idm({}))
    assert len(stream) == 51
    last = stream[-1]
    assert last.truncated and not last.terminated and last.reason == EndReason.TIME_LIMIT
    assert all(e.truncated and not e.terminated and e.reason == "time_limit" for e in last.egos)
    assert len(last.egos) == 4
    assert not any(v.startswith("ego") for v in libsumo.vehicle.getIDList())


def test_the_last_egos_end_terminates_the_episode(backend: SumoBackend) -> None:
    first = reset(backend, "ring", 1, 2, warmup=30.0)
    stream = drive(backend, first, lambda multi, ego: (3.0, 0), steps=400)
    last = stream[-1]
    assert last.terminated and not last.truncated and last.reason == EndReason.COLLISION
    assert all(e.reason for e in last.egos)


def test_report_traffic_is_every_vehicle_but_the_egos(backend: SumoBackend) -> None:
    first = reset(backend, "ring", 1, 4, warmup=5.0, report_traffic=True)
    stream = drive(backend, first, idm({}), steps=20)
    for multi in stream:
        assert multi.traffic is not None
        assert len(multi.traffic.id) == 18
        assert not any(v.startswith("ego") for v in multi.traffic.id)
    leaders = set(stream[-1].traffic.leader) if stream[-1].traffic else set()
    assert {"ego.0", "ego.1", "ego.2", "ego.3"} <= leaders  # the humans behind the egos


def test_sumo_can_drive_every_ego(backend: SumoBackend) -> None:
    first = reset(backend, "ring", 1, 4, warmup=30.0, ego_driver="sumo", max_episode_time=10.0)
    stream = drive(backend, first, lambda multi, ego: (3.0, 1))  # ignored: SUMO drives
    assert stream[-1].truncated and len(stream) == 101
    for multi in stream[1:]:
        for ego in multi.egos:
            assert ego.action.acceleration_limited_by == "simulator"
            assert ego.action.lane_change_refused == "simulator_drives"
            assert not ego.events.collision


# --------------------------------------------------------------------------- the roads


def test_cflc_egos_enter_one_after_another_and_each_ends_once(backend: SumoBackend) -> None:
    first = reset(backend, "cflc", 1, 3)
    ids = [e.id for e in first.egos]
    assert ids == ["ego.0", "ego.1", "ego.2"]
    departures = [libsumo.vehicle.getDeparture(ego) for ego in ids]
    # SUMO's departure: the start of the simulation step that inserted it
    assert (
        30.0 <= departures[0] <= departures[1] <= departures[2] == pytest.approx(first.time - 0.1)
    )
    for ego in first.egos:  # the checks go off for all of them at the hand-over
        assert libsumo.vehicle.getTypeID(ego.id) == EGO_TYPE
        assert libsumo.vehicle.getSpeedMode(ego.id) == SPEED_MODE_NO_CHECKS
        assert libsumo.vehicle.getLaneChangeMode(ego.id) == LANE_CHANGE_MODE_REQUESTS_ONLY
        assert ego.ego.lane_count == 3 and ego.ego.speed > 0.0
    reported: dict[str, list[int]] = {ego: [] for ego in ids}
    stream = drive(backend, first, idm({}))
    for multi in stream:
        for ego in multi.egos:
            reported[ego.id].append(multi.seq)
    ends = {e.id: (m.seq, e) for m in stream for e in m.egos if e.reason}
    assert set(ends) == set(ids)
    for ego_id, (seq, ego) in ends.items():
        assert ego.reason == EndReason.END_OF_ROAD and ego.events.end_of_road
        assert ego.ego.position == pytest.approx(2000.0)
        assert reported[ego_id] == list(range(seq + 1))  # every step until its end, then none
    last = stream[-1]
    assert last.terminated and last.reason == EndReason.END_OF_ROAD
    assert not any(v.startswith("ego") for v in libsumo.vehicle.getIDList())


def test_too_many_egos_for_the_road_is_an_insertion_failure(backend: SumoBackend) -> None:
    with pytest.raises(BackendError) as failed:
        reset(backend, "cf", 1, 64)
    assert failed.value.code == ErrorCode.INSERTION_FAILED
    assert "reached the end of the road before ego." in failed.value.message


# --------------------------------------------------------------------------- one ego


@pytest.mark.parametrize(
    ("scenario", "changes"),
    [
        ("cf", {"max_episode_time": 20.0}),
        ("cflc", {"max_episode_time": 20.0, "report_traffic": True}),
        ("ring", {"warmup": 20.0, "max_episode_time": 20.0}),
    ],
)
def test_one_ego_through_reset_many_is_the_one_ego_episode(
    backend: SumoBackend, scenario: str, changes: dict[str, OptionValue]
) -> None:
    def lane_changing(obs: Observation, seq: int) -> tuple[float, int]:
        return IDMDriver().act(obs)[0], (1 if obs.ego.lane == 0 else -1) if seq % 37 == 5 else 0

    opts = options(backend, scenario, **changes)
    obs = backend.reset(scenario, 7, opts)
    expected = [obs]
    for seq in range(1, 1000):
        obs = backend.step(seq, *lane_changing(obs, seq))
        expected.append(obs)
        if obs.terminated or obs.truncated:
            break
    multi = backend.reset_many(scenario, 7, {**opts, "egos": 1}, 1)
    got = [multi]
    for seq in range(1, len(expected)):
        (ego,) = multi.egos
        multi = backend.step_many(seq, {ego.id: lane_changing(single(multi, ego), seq)})
        got.append(multi)
    assert got[-1].terminated == expected[-1].terminated
    assert got[-1].truncated == expected[-1].truncated and got[-1].reason == expected[-1].reason
    for obs, multi in zip(expected, got, strict=True):
        (ego,) = multi.egos
        assert ego.id == "ego.0"
        assert (multi.seq, multi.time) == (obs.seq, obs.time)
        assert (ego.ego, ego.neighbours, ego.events, ego.action) == (
            obs.ego,
            obs.neighbours,
            obs.events,
            obs.action,
        )
        assert renamed(multi.traffic, "ego.0", "ego") == obs.traffic
        assert (ego.terminated, ego.truncated, ego.reason) == (
            obs.terminated,
            obs.truncated,
            obs.reason,
        )


def renamed(traffic: Traffic | None, old: str, new: str) -> Traffic | None:
    """`traffic` with the leader `old` called `new`."""
    if traffic is None:
        return None
    return replace(traffic, leader=tuple(new if v == old else v for v in traffic.leader))


# --------------------------------------------------------------------------- refusals


def test_bad_egos_values_are_refused_and_the_running_episode_goes_on(
    backend: SumoBackend,
) -> None:
    first = reset(backend, "ring", 1, 2, warmup=5.0)

    def refused(scenario: str, egos: int, **changes: OptionValue) -> str:
        with pytest.raises(BackendError) as error:
            reset(backend, scenario, 1, egos, **changes)
        assert error.value.code == ErrorCode.INVALID_OPTION
        return error.value.message

    assert "egos 23" in refused("ring", 23) and "vehicles 22" in refused("ring", 23)
    assert "1..1024" in refused("cf", 1025)
    assert "1..1024" in refused("cf", 0)
    assert "ssm" in refused("cflc", 2, ssm=True)
    assert "ssm" in refused("ring", 1, ssm=True)
    multi = backend.step_many(1, {e.id: (0.0, 0) for e in first.egos})  # still running
    assert multi.seq == 1 and len(multi.egos) == 2

    with pytest.raises(BackendError) as wrong:
        backend.step_many(2, {"ego.0": (0.0, 0)})
    assert wrong.value.code == ErrorCode.INVALID_MESSAGE and "ego.1" in wrong.value.message
    with pytest.raises(BackendError) as one:
        backend.step(2, 0.0, 0)
    assert one.value.code == ErrorCode.OUT_OF_ORDER and "multi_step" in one.value.message


# --------------------------------------------------------------------------- the wire


def test_a_multi_observation_from_sumo_survives_the_codec(backend: SumoBackend) -> None:
    first = reset(backend, "cflc", 2, 3, report_traffic=True, max_episode_time=30.0)

    def brake_ego_1_hard(multi: MultiObservation, ego: EgoObservation) -> tuple[float, int]:
        return (-8.0, 1) if ego.id == "ego.1" else IDMDriver().act(single(multi, ego))

    stream = drive(backend, first, brake_ego_1_hard, steps=40)
    assert any(e.action.acceleration_limited_by for m in stream for e in m.egos)
    assert any(e.events.lane_change_started or e.events.lane_change_refused
               for m in stream for e in m.egos)  # fmt: skip
    for multi in stream:
        frame = encode(multi)
        assert decode_reply(frame) == multi
        assert encode(decode_reply(frame)) == frame


def test_traci_gives_the_libsumo_multi_stream_bit_for_bit(
    backend: SumoBackend, traci_backend: SumoBackend
) -> None:
    def lane_changing(multi: MultiObservation, ego: EgoObservation) -> tuple[float, int]:
        acceleration = IDMDriver().act(single(multi, ego))[0]
        return acceleration, (1 if ego.ego.lane == 0 else -1) if multi.seq % 23 == 5 else 0

    for scenario, egos, changes in (
        ("ring", 4, {"warmup": 30.0, "max_episode_time": 20.0}),
        ("cflc", 3, {"max_episode_time": 20.0, "report_traffic": True}),
    ):
        expected = drive(backend, reset(backend, scenario, 5, egos, **changes), lane_changing)
        got = drive(
            traci_backend, reset(traci_backend, scenario, 5, egos, **changes), lane_changing
        )
        assert [encode(m) for m in got] == [encode(m) for m in expected]


# --------------------------------------------------------------------------- ego_share (1.5)


def reset_share(
    backend: SumoBackend, scenario: str, seed: int, share: float, **changes: OptionValue
) -> MultiObservation:
    return backend.reset_many(
        scenario, seed, options(backend, scenario, ego_share=share, **changes), 1
    )


def test_a_share_of_the_road_is_handed_over_after_the_warm_up(backend: SumoBackend) -> None:
    first = reset_share(backend, "cflc", 2, 0.25, report_traffic=True, warmup=100.0)
    on_road = libsumo.vehicle.getIDList()
    egos = [e.id for e in first.egos]
    assert len(egos) == int(0.25 * len(on_road) + 0.5) > 5
    assert first.traffic is not None
    assert sorted([*egos, *first.traffic.id]) == sorted(on_road)  # the rest are the traffic
    departures = [libsumo.vehicle.getDeparture(ego) for ego in egos]
    assert departures == sorted(departures)  # in the order they entered
    for ego in first.egos:
        assert libsumo.vehicle.getTypeID(ego.id) == EGO_TYPE
        assert libsumo.vehicle.getSpeedFactor(ego.id) == 1.0
        assert libsumo.vehicle.getSpeedMode(ego.id) == SPEED_MODE_NO_CHECKS
        assert libsumo.vehicle.getLaneChangeMode(ego.id) == LANE_CHANGE_MODE_REQUESTS_ONLY
        assert ego.ego.position == pytest.approx(libsumo.vehicle.getLanePosition(ego.id))
    again = reset_share(backend, "cflc", 2, 0.25, warmup=100.0)
    assert [e.id for e in again.egos] == egos  # seeded


def test_the_vehicles_that_enter_join_at_the_share(backend: SumoBackend) -> None:
    first = reset_share(backend, "cflc", 3, 0.25, report_traffic=True, max_episode_time=60.0)
    seen = {e.id for e in first.egos} | set(first.traffic.id if first.traffic else ())
    joined: list[str] = []
    frames = [first]

    def check(multi: MultiObservation) -> None:
        running = [e.id for e in frames[-1].egos if not e.reason]
        ids = [e.id for e in multi.egos]
        assert ids[: len(running)] == running  # those that drove into the step, then the new
        for ego in multi.egos[len(running) :]:
            assert ego.id not in joined and not ego.reason
            assert ego.action.acceleration == 0.0 and not ego.events.collision
            assert libsumo.vehicle.getTypeID(ego.id) == EGO_TYPE
            assert libsumo.vehicle.getSpeedMode(ego.id) == SPEED_MODE_NO_CHECKS
            joined.append(ego.id)
        assert multi.traffic is not None
        seen.update(ids, multi.traffic.id)
        frames.append(multi)

    stream = drive(backend, first, idm({}), check=check)
    entered = len(seen) - len(first.egos) - len(first.traffic.id if first.traffic else ())
    assert entered > 20 and abs(len(joined) - 0.25 * entered) <= 1.0  # the share, exactly
    last = stream[-1]
    assert last.truncated and last.time == pytest.approx(first.time + 60.0)
    before = [e.id for e in stream[-2].egos if not e.reason]
    assert [e.id for e in last.egos] == before  # nobody joins a truncated frame
    assert all(e.truncated or e.terminated for e in last.egos)
    assert not any(e.events.collision for m in stream for e in m.egos)  # IDM drives safely


def test_on_the_ring_a_share_is_that_many_slots(backend: SumoBackend) -> None:
    first = reset_share(backend, "ring", 1, 0.5, warmup=5.0)
    assert [e.id for e in first.egos] == [f"ego.{k}" for k in range(11)]


def test_sumo_can_drive_a_share_of_the_road(backend: SumoBackend) -> None:
    first = reset_share(backend, "cflc", 1, 1.0, ego_driver="sumo", max_episode_time=5.0)
    assert len(first.egos) == len(libsumo.vehicle.getIDList())
    drove = {e.id for e in first.egos}

    def check(multi: MultiObservation) -> None:
        for ego in multi.egos:
            if ego.id in drove:  # not one that joins in this frame
                assert ego.action.acceleration_limited_by == "simulator"
            if not ego.reason:
                assert libsumo.vehicle.getTypeID(ego.id) != EGO_TYPE  # humans still
        drove.update(e.id for e in multi.egos)

    stream = drive(backend, first, lambda multi, ego: (3.0, 1), check=check)  # ignored
    assert stream[-1].truncated and len(stream) == 51
