"""The SUMO backend in-process through libsumo (real SUMO, one simulation per process)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from agent_client.idm import IDMDriver
from protocol.errors import ErrorCode
from protocol.messages import Observation, OptionValue
from sim_server.backend import BackendError
from sim_server.scenarios import EGO_ROUTE, CustomScenario
from sim_server.sumo_backend import SumoBackend

pytestmark = pytest.mark.sumo


@pytest.fixture(scope="module")
def backend(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SumoBackend]:
    cache = tmp_path_factory.mktemp("scenarios")
    sumo = SumoBackend(cache_dir=cache)
    yield sumo
    sumo.close()


def options(backend: SumoBackend, scenario: str, **changes: OptionValue) -> dict[str, OptionValue]:
    info = {s.name: s for s in backend.scenarios()}[scenario]
    return {**info.options, **changes}


def run(
    backend: SumoBackend,
    first: Observation,
    actions: Iterator[tuple[float, int]] | list[tuple[float, int]],
) -> list[Observation]:
    stream = [first]
    for seq, (acceleration, lane_change) in enumerate(actions, start=1):
        obs = backend.step(seq, acceleration, lane_change)
        stream.append(obs)
        if obs.terminated or obs.truncated:
            break
    return stream


def idm_episode(
    backend: SumoBackend, scenario: str, seed: int, steps: int, **changes: OptionValue
) -> list[Observation]:
    driver = IDMDriver()
    obs = backend.reset(scenario, seed, options(backend, scenario, **changes))
    stream = [obs]
    for seq in range(1, steps + 1):
        obs = backend.step(seq, *driver.act(obs))
        stream.append(obs)
        if obs.terminated or obs.truncated:
            break
    return stream


def test_reset_inserts_the_ego_after_the_warm_up(backend: SumoBackend) -> None:
    obs = backend.reset("cf", 1, options(backend, "cf"))
    assert obs.seq == 0
    assert obs.time >= 30.0
    assert obs.ego.lane_count == 1
    assert obs.ego.speed_limit == pytest.approx(80 / 3.6, abs=0.01)
    assert 0 < obs.ego.position < 10


def test_commanded_acceleration_is_realised_exactly(backend: SumoBackend) -> None:
    obs = backend.reset("cf", 2, options(backend, "cf"))
    checked = 0
    for seq, request in enumerate([0.5, -0.5, 1.0, -1.5, 0.2, -0.3] * 3, start=1):
        obs = backend.step(seq, request, 0)
        if obs.action.acceleration_limited_by:
            continue
        assert obs.action.acceleration == request
        assert obs.ego.acceleration == pytest.approx(request, abs=1e-6)
        checked += 1
    assert checked >= 10


def test_accelerations_beyond_the_bounds_are_clipped_and_reported(backend: SumoBackend) -> None:
    backend.reset("cf", 3, options(backend, "cf"))
    obs = backend.step(1, -50.0, 0)
    assert obs.action.requested_acceleration == -50.0
    assert obs.action.acceleration >= backend.action_schema.acceleration_min
    assert obs.action.acceleration_limited_by in {"bounds", "standstill"}
    assert obs.ego.acceleration == pytest.approx(obs.action.acceleration, abs=1e-6)


def test_the_ego_never_exceeds_the_speed_limit(backend: SumoBackend) -> None:
    first = backend.reset("cflc", 4, options(backend, "cflc"))
    stream = run(backend, first, [(3.0, 0)] * 300)
    assert max(o.ego.speed for o in stream) <= first.ego.speed_limit + 1e-9
    assert any(o.action.acceleration_limited_by == "speed_limit" for o in stream)


def test_full_throttle_ends_in_a_reported_collision_with_the_ceiling(backend: SumoBackend) -> None:
    first = backend.reset("cf", 5, options(backend, "cf"))
    last = run(backend, first, [(3.0, 0)] * 3000)[-1]
    assert last.terminated and not last.truncated
    assert last.reason == "collision"
    assert last.events.collision and last.events.collision_with
    assert last.neighbours.leader.gap < 0.5  # real overlap (or about to), not "closer than minGap"
    assert last.ceiling is not None and last.ceiling.average_speed is not None
    assert (
        last.ceiling.arrival_time is not None
        and last.ceiling.arrival_time > last.ceiling.depart_time
    )


def test_an_idm_episode_reaches_the_end_of_the_road(backend: SumoBackend) -> None:
    stream = idm_episode(backend, "cf", 6, 5000)
    last = stream[-1]
    assert last.reason == "end_of_road" and last.terminated
    assert last.ego.position == pytest.approx(2000.0)
    assert not any(o.events.collision for o in stream)
    assert last.ceiling is not None and last.ceiling.arrival_time is not None
    assert last.ceiling.arrival_time <= last.time  # one lane: the leader-at-entry arrives first


def test_lane_change_takes_two_seconds_and_completes(backend: SumoBackend) -> None:
    first = backend.reset("cflc", 7, options(backend, "cflc"))
    direction = 1 if first.ego.lane < 2 else -1
    stream = [first]
    for seq in range(1, 80):
        obs = backend.step(seq, 0.0, direction if seq % 40 == 1 else 0)
        stream.append(obs)
        if obs.events.lane_change_completed:
            break
    started = [o for o in stream if o.events.lane_change_started]
    assert started, [o.action for o in stream if o.action.requested_lane_change]
    done = next(o for o in stream if o.events.lane_change_completed)
    assert (
        done.ego.lane == started[0].ego.lane + direction
        or done.ego.lane == first.ego.lane + direction
    )
    assert done.time - started[0].time == pytest.approx(2.0, abs=0.25)


def test_lane_change_requests_are_refused_with_a_reason(backend: SumoBackend) -> None:
    first = backend.reset("cf", 8, options(backend, "cf"))
    obs = backend.step(1, 0.0, 1)
    assert obs.action.lane_change_refused == "no_lane"
    assert obs.events.lane_change_refused and obs.action.lane_change == 0
    # Dense three-lane traffic: some requests are refused because the gap is too small.
    first = backend.reset("cflc", 9, options(backend, "cflc", flow=1800.0))
    refusals, lanes_before = [], first.ego.lane
    obs = first
    for seq in range(1, 400):
        direction = 1 if obs.ego.lane == 0 else -1
        obs = backend.step(seq, 0.0, direction)
        if obs.action.lane_change_refused == "gap_too_small":
            refusals.append(obs)
        if obs.terminated or obs.truncated:
            break
    assert refusals, "no request was refused for lack of gap in dense traffic"
    assert all(o.action.lane_change == 0 and not o.events.lane_change_started for o in refusals)
    assert lanes_before in range(3)


def test_same_seed_same_stream_bit_for_bit(backend: SumoBackend) -> None:
    a = idm_episode(backend, "cflc", 11, 300)
    b = idm_episode(backend, "cflc", 11, 300)
    c = idm_episode(backend, "cflc", 12, 300)
    assert a == b
    assert a != c


def test_decision_interval_repeats_the_action(backend: SumoBackend) -> None:
    first = backend.reset("cf", 13, options(backend, "cf", decision_interval=1.0))
    obs = backend.step(1, 0.0, 0)
    assert obs.time == pytest.approx(first.time + 1.0)
    with pytest.raises(BackendError) as caught:
        backend.reset("cf", 13, options(backend, "cf", decision_interval=0.15))
    assert caught.value.code is ErrorCode.INVALID_OPTION


def test_time_limit_truncates(backend: SumoBackend) -> None:
    stream = idm_episode(backend, "cf", 14, 1000, max_episode_time=3.0)
    assert stream[-1].truncated and not stream[-1].terminated
    assert stream[-1].reason == "time_limit"
    assert len(stream) - 1 == 30


def test_an_unreasonable_stop_ends_the_episode(backend: SumoBackend) -> None:
    first = backend.reset("cf", 15, options(backend, "cf"))
    last = run(backend, first, [(-6.0, 0)] * 600)[-1]
    assert last.terminated and last.reason == "stopped"
    assert last.ego.speed < 1.0


def test_insertion_is_bounded_and_reported(backend: SumoBackend) -> None:
    with pytest.raises(BackendError) as caught:
        backend.reset(
            "cf",
            1,
            options(backend, "cf", flow=3600.0, insertion_timeout=0.1, speed_factor_mean=0.5),
        )
    assert caught.value.code is ErrorCode.INSERTION_FAILED
    assert backend.reset("cf", 1, options(backend, "cf")).seq == 0  # and the next reset works


def test_sumo_can_drive_the_ego_for_recording_human_trajectories(backend: SumoBackend) -> None:
    first = backend.reset("cf", 16, options(backend, "cf", ego_driver="sumo"))
    stream = run(backend, first, [(3.0, 1)] * 3000)  # requests are ignored
    assert stream[-1].reason == "end_of_road"
    assert not any(o.events.collision for o in stream)
    assert all(o.action.acceleration_limited_by == "simulator" for o in stream[1:])
    assert stream[5].action.lane_change_refused == "simulator_drives"
    assert max(abs(o.ego.acceleration - o.action.acceleration) for o in stream[1:-1]) < 1e-9
    # A human driver, not the agent's full throttle: it follows its leader.
    assert min(o.neighbours.leader.gap for o in stream if o.neighbours.leader.present) > 0.5


def test_a_users_own_sumocfg_is_a_scenario(backend: SumoBackend, tmp_path: Path) -> None:
    backend.reset("cf", 1, options(backend, "cf"))  # builds the cf files
    built = next(Path(backend._cache_dir).glob("cf-*/cf.sumocfg"))
    user = SumoBackend(cache_dir=tmp_path, custom=(CustomScenario("mine", built, EGO_ROUTE),))
    assert "mine" in [s.name for s in user.scenarios()]
    obs = user.reset("mine", 3, options(user, "mine"))
    assert obs.ego.lane_count == 1
    assert user.step(1, 0.0, 0).seq == 1
