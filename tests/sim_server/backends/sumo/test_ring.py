"""The ``ring`` scenario (real SUMO): placed at reset, neighbours across the seam, waves.

libsumo is one simulation per process: this module holds one libsumo backend (its ground truth
read from libsumo directly) and one TraCI backend for the byte-for-byte comparison.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import libsumo
import numpy as np
import pytest

from agent_client.drivers.episode import Episode
from agent_client.drivers.idm import IDMDriver
from agent_client.evaluation.metrics import episode_summary, format_summary
from protocol.codec import encode
from protocol.errors import ErrorCode
from protocol.messages import EndReason, Observation, OptionValue
from sim_server.backends.sumo.backend import SumoBackend
from sim_server.backends.sumo.scenarios import EGO_ID, EGO_TYPE, HUMAN_TYPE, RING_EDGES
from sim_server.errors import BackendError

pytestmark = pytest.mark.sumo

WAVE_SPREAD = 1.0
"""m/s: the humans' speed spread (standard deviation across vehicles, mean over a minute) above
which the ring has waves. Measured with benchmarks/ring_waves.py (from rest, seeds 1-10): the
EIDM noise alone gives 0.1-0.2 in the first minute, developed stop-and-go waves 2.6-2.7, and
the spread passed 1 m/s between 90 and 150 s in every seed (ego driven by SUMO or by IDM); the
humans without waves (``human_model`` krauss, idm) stay at 0.04 and 0.00."""


@pytest.fixture(scope="module")
def backend(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SumoBackend]:
    sumo = SumoBackend(cache_dir=tmp_path_factory.mktemp("scenarios"))
    yield sumo
    sumo.close()


def ring_options(backend: SumoBackend, **changes: OptionValue) -> dict[str, OptionValue]:
    info = {s.name: s for s in backend.scenarios()}["ring"]
    return {**info.options, "warmup": 0.0, **changes}


def ring_place(vehicle: str, ring_length: float) -> float:
    """Metres from the start of edge ``a`` to the vehicle's front (ground truth, libsumo)."""
    on_b = libsumo.vehicle.getRoadID(vehicle) == RING_EDGES[1]
    return libsumo.vehicle.getLanePosition(vehicle) + (ring_length / 2 if on_b else 0.0)


def ahead(front: float, back: float, ring_length: float) -> float:
    """Bumper gap from a front at `front` to a back at `back`, forwards round the ring."""
    return (back - front) % ring_length


def test_the_ring_is_offered_with_its_own_options(backend: SumoBackend) -> None:
    info = {s.name: s for s in backend.scenarios()}["ring"]
    assert info.options["ring_length"] == 230.0
    assert info.options["vehicles"] == 22
    assert info.options["warmup"] == 300.0
    assert info.options["human_model"] == "eidm"
    assert "report_ceiling" not in info.options and "insertion_timeout" not in info.options
    assert "flow" not in info.options
    assert info.step_length == 0.1


@pytest.mark.parametrize(("vehicles", "ring_length"), [(22, 230.0), (23, 230.0), (7, 100.0)])
def test_the_ring_resets_with_the_vehicles_asked_placed_evenly(
    backend: SumoBackend, vehicles: int, ring_length: float
) -> None:
    options = ring_options(backend, vehicles=vehicles, ring_length=ring_length)
    obs = backend.reset("ring", 1, options)
    ids = libsumo.vehicle.getIDList()
    assert len(ids) == vehicles and EGO_ID in ids
    assert libsumo.vehicle.getTypeID(EGO_ID) == EGO_TYPE
    assert obs.seq == 0 and obs.ego.lane_count == 1
    assert obs.ego.speed_limit == pytest.approx(30 / 3.6, abs=0.01)
    places = sorted(ring_place(v, ring_length) for v in ids)
    spacing = np.diff([*places, places[0] + ring_length])
    assert spacing == pytest.approx(np.full(vehicles, ring_length / vehicles), abs=0.05)


def idm_ring_episode(
    backend: SumoBackend, seed: int, seconds: float, check: bool = True
) -> tuple[list[Observation], list[list[float]], set[tuple[str, str, str]]]:
    """An IDM ego for `seconds` from rest: the stream, the humans' speeds at every step, and the
    edges (ego, leader, follower) seen.

    With `check`, every step's leader and follower are compared with libsumo's ground truth."""
    options = ring_options(backend, max_episode_time=seconds)
    length = float(options["ring_length"])  # type: ignore[arg-type]
    driver = IDMDriver()
    obs = backend.reset("ring", seed, options)
    stream, speeds, edges = [obs], [], set()
    while not (obs.terminated or obs.truncated):
        if check:
            edges.add(check_neighbours(obs, length))
        humans = [v for v in libsumo.vehicle.getIDList() if v != EGO_ID]
        speeds.append([libsumo.vehicle.getSpeed(v) for v in humans])
        obs = backend.step(obs.seq + 1, *driver.act(obs))
        stream.append(obs)
    return stream, speeds, edges


def check_neighbours(obs: Observation, length: float) -> tuple[str, str, str]:
    """The leader and follower are there, their gaps are positive and are the ring's; the
    edges of the ego, its leader and its follower."""
    leader, follower = obs.neighbours.leader, obs.neighbours.follower
    assert leader.present and follower.present
    assert leader.gap > 0 and follower.gap > 0
    assert leader.lateral == 0.0 and follower.lateral == 0.0
    ego_front = ring_place(EGO_ID, length)
    ego_back = ego_front - libsumo.vehicle.getLength(EGO_ID)
    leader_back = ring_place(leader.id, length) - libsumo.vehicle.getLength(leader.id)
    assert leader.gap == pytest.approx(ahead(ego_front, leader_back, length), abs=1e-6)
    follower_front = ring_place(follower.id, length)
    assert follower.gap == pytest.approx(ahead(follower_front, ego_back, length), abs=1e-6)
    assert obs.ego.position % length == pytest.approx(ego_front, abs=1e-6)
    road = libsumo.vehicle.getRoadID
    return road(EGO_ID), road(leader.id), road(follower.id)


def test_neighbours_are_right_across_the_seam_and_waves_form_until_the_time_limit(
    backend: SumoBackend,
) -> None:
    stream, speeds, edges = idm_ring_episode(backend, seed=1, seconds=240.0)
    last = stream[-1]
    assert last.truncated and last.reason == EndReason.TIME_LIMIT
    assert last.time - stream[0].time == pytest.approx(240.0)
    assert not any(o.events.end_of_road or o.events.collision for o in stream)
    assert last.ceiling is None
    assert (last.ego.position - stream[0].ego.position) / 230.0 > 2  # laps
    a, b = RING_EDGES
    assert (b, a, b) in edges  # the leader beyond the seam where the loop closes (b -> a)
    assert (a, a, b) in edges  # the follower behind it
    spread = np.array(speeds).std(axis=1)
    assert spread[:600].mean() < 0.5 * WAVE_SPREAD  # the first minute: still uniform
    assert spread[-600:].mean() > WAVE_SPREAD  # the fourth: stop-and-go
    assert (np.array(speeds[-600:]) < 1.0).mean() > 0.1  # humans stop in the waves


@pytest.mark.parametrize("model", ["krauss", "idm"])
def test_the_humans_without_noise_and_instability_keep_a_uniform_flow(
    backend: SumoBackend, model: str
) -> None:
    """The waves are the default model's (EIDM), not an artefact of the ring or the seam."""
    options = ring_options(backend, human_model=model, ego_driver="sumo", max_episode_time=240.0)
    obs, speeds = backend.reset("ring", 1, options), []
    while not (obs.terminated or obs.truncated):
        speeds.append([libsumo.vehicle.getSpeed(v) for v in libsumo.vehicle.getIDList()])
        obs = backend.step(obs.seq + 1, 0.0, 0)
    assert np.array(speeds[-600:]).std(axis=1).mean() < 0.1 * WAVE_SPREAD


def test_the_evaluation_summarises_a_ring_episode_without_a_ceiling(backend: SumoBackend) -> None:
    stream, _, _ = idm_ring_episode(backend, seed=2, seconds=20.0, check=False)
    episode = Episode(seed=2, step_length=0.1)
    for obs in stream:
        episode.add(obs)
    summary = episode_summary(episode)
    assert summary.ceiling_speed is None and summary.speed_ratio_to_ceiling is None
    assert summary.distance > 0 and summary.reason == "time_limit"
    assert "ceiling   n/a" in format_summary(summary)


def test_the_ego_ramming_its_leader_ends_the_episode_in_a_collision(backend: SumoBackend) -> None:
    obs = backend.reset("ring", 3, ring_options(backend))
    for seq in range(1, 200):
        obs = backend.step(seq, 3.0, 0)
        if obs.terminated or obs.truncated:
            break
    assert obs.terminated and obs.reason == EndReason.COLLISION
    assert obs.events.collision_with.startswith("human")


def test_sumo_drives_the_ego_as_one_of_the_humans(backend: SumoBackend) -> None:
    obs = backend.reset("ring", 4, ring_options(backend, ego_driver="sumo", warmup=10.0))
    assert libsumo.vehicle.getTypeID(EGO_ID) == HUMAN_TYPE
    assert obs.time == pytest.approx(10.0)
    obs = backend.step(1, -6.0, 1)
    assert obs.action.acceleration_limited_by == "simulator"
    assert obs.action.lane_change_refused == "simulator_drives"


@pytest.mark.parametrize(
    ("changes", "words"),
    [
        ({"vehicles": 40}, ["40 vehicles", "230 m ring", "ring_length >= 320"]),
        ({"vehicles": 1}, ["vehicles", ">= 2"]),
        ({"ring_length": 10.0}, ["ring_length", ">= 50"]),
        ({"human_model": "wiedemann"}, ["human_model", "eidm, idm, krauss", "'wiedemann'"]),
    ],
)
def test_a_ring_that_cannot_hold_its_vehicles_is_refused(
    backend: SumoBackend, changes: dict[str, OptionValue], words: list[str]
) -> None:
    with pytest.raises(BackendError) as refused:
        backend.reset("ring", 1, ring_options(backend, **changes))
    assert refused.value.code == ErrorCode.INVALID_OPTION
    for word in words:
        assert word in str(refused.value)


def test_traci_gives_the_libsumo_ring_stream_bit_for_bit(
    backend: SumoBackend, tmp_path: Path
) -> None:
    traci = SumoBackend(cache_dir=tmp_path, traci=True)
    try:
        expected, _, _ = idm_ring_episode(backend, seed=5, seconds=15.0, check=False)
        got = [traci.reset("ring", 5, ring_options(traci, max_episode_time=15.0))]
        driver = IDMDriver()
        while not (got[-1].terminated or got[-1].truncated):
            got.append(traci.step(got[-1].seq + 1, *driver.act(got[-1])))
    finally:
        traci.close()
    assert [encode(o) for o in got] == [encode(o) for o in expected]
