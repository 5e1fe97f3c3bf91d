"""What SUMO measures beyond the ego's observation (real SUMO, libsumo): SSM conflicts, traffic.

libsumo is one simulation per process: this module holds one backend; libsumo is read directly
for the ground truth.
"""

from __future__ import annotations

from collections.abc import Iterator

import libsumo
import pytest

from agent_client.drivers.idm import IDMDriver
from protocol.codec import decode_reply, encode
from protocol.messages import EndReason, Observation, OptionValue
from sim_server.backends.sumo.backend import SumoBackend
from sim_server.backends.sumo.scenarios import EGO_ID
from sim_server.backends.sumo.ssm import DRAC_THRESHOLD, PET_THRESHOLD_S, TTC_THRESHOLD_S

pytestmark = pytest.mark.sumo


@pytest.fixture(scope="module")
def backend(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SumoBackend]:
    sumo = SumoBackend(cache_dir=tmp_path_factory.mktemp("scenarios"))
    yield sumo
    sumo.close()


@pytest.fixture(scope="module")
def traci_backend(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SumoBackend]:
    sumo = SumoBackend(cache_dir=tmp_path_factory.mktemp("scenarios"), traci=True)
    yield sumo
    sumo.close()


def options(backend: SumoBackend, scenario: str, **changes: OptionValue) -> dict[str, OptionValue]:
    info = {s.name: s for s in backend.scenarios()}[scenario]
    return {**info.options, **changes}


def drive(backend: SumoBackend, first: Observation, acceleration: float) -> list[Observation]:
    """Step at a constant acceleration until the episode ends (at most 3,000 steps)."""
    observations = [first]
    obs = first
    while not (obs.terminated or obs.truncated) and obs.seq < 3000:
        obs = backend.step(obs.seq + 1, acceleration, 0)
        observations.append(obs)
    return observations


def test_every_sumo_scenario_offers_the_measures_off_by_default(backend: SumoBackend) -> None:
    for info in backend.scenarios():
        assert info.options["ssm"] is False and info.options["report_traffic"] is False


def test_an_ego_that_rams_its_leader_has_a_conflict_with_it(backend: SumoBackend) -> None:
    first = backend.reset("cf", 3, options(backend, "cf", ssm=True, report_ceiling=False))
    assert first.safety is None
    observations = drive(backend, first, 3.0)
    last = observations[-1]
    assert last.reason == EndReason.COLLISION
    assert all(o.safety is None for o in observations[:-1])
    safety = last.safety
    assert safety is not None
    thresholds = (safety.ttc_threshold, safety.drac_threshold, safety.pet_threshold)
    assert thresholds == (TTC_THRESHOLD_S, DRAC_THRESHOLD, PET_THRESHOLD_S)
    rammed = [c for c in safety.conflicts if c.foe == last.events.collision_with]
    assert len(rammed) == 1
    conflict = rammed[0]
    assert conflict.min_ttc is not None and conflict.min_ttc < 1.0
    assert conflict.max_drac is not None and conflict.max_drac > DRAC_THRESHOLD
    assert first.time <= conflict.begin <= conflict.end <= last.time + 1e-9
    assert 0 < conflict.ttc_below <= conflict.end - conflict.begin + 0.1
    assert conflict.ttc_integral > 0
    assert decode_reply(encode(last)) == last  # on the wire as sent


def test_over_traci_every_episode_gets_its_whole_log(traci_backend: SumoBackend) -> None:
    """A TraCI load is acknowledged before SUMO has written the old log out: not read early."""
    for _ in range(3):
        reset = options(traci_backend, "cf", ssm=True, report_ceiling=False)
        last = drive(traci_backend, traci_backend.reset("cf", 3, reset), 3.0)[-1]
        assert last.reason == EndReason.COLLISION and last.safety is not None
        assert last.events.collision_with in {c.foe for c in last.safety.conflicts}


def test_on_the_ring_only_the_clients_driving_counts(backend: SumoBackend) -> None:
    """SUMO drives the ring's ego through the warm-up: its encounters then are not the agent's."""
    reset = options(backend, "ring", ssm=True, max_episode_time=5.0, warmup=200.0)
    first = backend.reset("ring", 1, reset)
    last = drive(backend, first, 0.0)[-1]
    assert last.safety is not None
    assert all(c.begin >= first.time - 1e-9 for c in last.safety.conflicts)
    assert 0 <= last.safety.ttc_below <= last.time - first.time + 1e-9
    for conflict in last.safety.conflicts:
        assert conflict.ttc_below <= conflict.end - conflict.begin + 0.1 + 1e-9


def test_a_careful_ego_has_fewer_and_milder_conflicts(backend: SumoBackend) -> None:
    reset = options(backend, "cf", ssm=True, report_ceiling=False, max_episode_time=60.0)
    obs = backend.reset("cf", 3, reset)
    driver = IDMDriver()
    while not (obs.terminated or obs.truncated):
        acceleration, lane_change = driver.act(obs)
        obs = backend.step(obs.seq + 1, acceleration, lane_change)
    assert obs.reason == EndReason.TIME_LIMIT
    assert obs.safety is not None
    assert all(c.min_ttc is None or c.min_ttc > 1.0 for c in obs.safety.conflicts)


def test_without_the_option_there_are_no_measures(backend: SumoBackend) -> None:
    first = backend.reset("cf", 3, options(backend, "cf", max_episode_time=1.0))
    last = drive(backend, first, 0.0)[-1]
    assert first.traffic is None and last.safety is None and last.traffic is None


def test_traffic_reports_every_other_vehicle_as_sumo_sees_it(backend: SumoBackend) -> None:
    reset = options(backend, "cflc", report_traffic=True, max_episode_time=5.0)
    obs = backend.reset("cflc", 4, reset)
    previous: dict[str, float] = {}
    while True:
        traffic = obs.traffic
        assert traffic is not None
        done = obs.terminated or obs.truncated  # SUMO has run on for the ceiling since
        running = set(libsumo.vehicle.getIDList()) - {EGO_ID}
        assert done or (set(traffic.id) == running and len(traffic.id) == len(running))
        columns = (traffic.vehicle_type, traffic.lane, traffic.position, traffic.speed)
        assert all(len(column) == len(traffic) for column in columns)
        for i, vehicle in enumerate(traffic.id):
            if not done:
                assert traffic.speed[i] == pytest.approx(libsumo.vehicle.getSpeed(vehicle))
            assert traffic.position[i] >= previous.get(vehicle, 0.0)  # an odometer
            previous[vehicle] = traffic.position[i]
            if traffic.leader[i]:
                assert 0 < traffic.gap[i] <= backend.sensor_range
        follower = obs.neighbours.follower
        if follower.present:  # the ego's follower sees the ego, at the same gap
            row = traffic.id.index(follower.id)
            assert traffic.leader[row] == EGO_ID
            assert traffic.gap[row] == pytest.approx(follower.gap, abs=1e-6)
            assert traffic.leader_speed[row] == pytest.approx(obs.ego.speed)
        assert decode_reply(encode(obs)) == obs
        if done:
            break
        obs = backend.step(obs.seq + 1, 0.0, 0)


def test_no_log_outlives_its_episode(backend: SumoBackend) -> None:
    backend.reset("cf", 5, options(backend, "cf", ssm=True))  # abandoned at once
    logs = backend._logs
    assert logs is not None and len(list(logs.iterdir())) <= 1
    drive(backend, backend.reset("cf", 5, options(backend, "cf", ssm=True)), 3.0)
    assert list(logs.iterdir()) == []  # read and deleted; the abandoned one too
