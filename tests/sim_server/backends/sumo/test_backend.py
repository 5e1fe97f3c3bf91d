"""The SUMO backend (real SUMO): in-process through libsumo, and over TraCI to a sumo process.

Every behaviour test runs on both; libsumo is one simulation per process, so this module holds
one libsumo backend and one TraCI backend (its own ``sumo`` process).
"""

from __future__ import annotations

import random
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from agent_client.drivers.idm import IDMDriver
from protocol.codec import encode
from protocol.errors import ErrorCode
from protocol.messages import Observation, OptionValue
from sim_server import cli
from sim_server.backends.rules import LANE_CHANGE_TIMEOUT_S
from sim_server.backends.sumo.backend import SumoBackend
from sim_server.backends.sumo.runtime import find_sumo_binary, free_port
from sim_server.backends.sumo.scenarios import EGO_ID, EGO_ROUTE, CustomScenario
from sim_server.errors import BackendError

pytestmark = pytest.mark.sumo


@pytest.fixture(scope="module")
def scenario_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("scenarios")


@pytest.fixture(scope="module")
def libsumo_backend(scenario_dir: Path) -> Iterator[SumoBackend]:
    sumo = SumoBackend(cache_dir=scenario_dir)
    yield sumo
    sumo.close()


@pytest.fixture(scope="module")
def traci_backend(scenario_dir: Path) -> Iterator[SumoBackend]:
    sumo = SumoBackend(cache_dir=scenario_dir, traci=True)
    yield sumo
    sumo.close()


@pytest.fixture(scope="module", params=["libsumo", "traci"])
def backend(request: pytest.FixtureRequest) -> SumoBackend:
    """Each behaviour test runs on both ways to drive SUMO."""
    return request.getfixturevalue(f"{request.param}_backend")  # type: ignore[no-any-return]


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
    # The lane change under way is in the observation from its start to its completion.
    during = stream[stream.index(started[0]) : stream.index(done)]
    assert [o.ego.changing_lane for o in during] == [direction] * len(during)
    assert done.ego.changing_lane == 0
    assert all(o.ego.changing_lane == 0 for o in stream[: stream.index(started[0])])


def test_a_lane_change_sumo_never_begins_is_given_up_not_waited_for(backend: SumoBackend) -> None:
    """SUMO drops a request it could not begin within 2 s (the gap closed): seed 100 has one.

    Without the timeout the ego would wait for it to the end of the episode, every further
    command refused with in_progress.
    """
    rng, driver = random.Random(0), IDMDriver()
    obs = backend.reset("cflc", 100, options(backend, "cflc"))
    started_at: float | None = None
    ends = {"completed": 0, "aborted": 0}
    for seq in range(1, 700):
        command = rng.choice([-1, 1]) if rng.random() < 0.3 else 0
        obs = backend.step(seq, driver.act(obs)[0], command)
        if obs.events.lane_change_started:
            started_at = obs.time
        if obs.events.lane_change_completed or obs.events.lane_change_aborted:
            assert started_at is not None and obs.ego.changing_lane == 0
            ends["aborted" if obs.events.lane_change_aborted else "completed"] += 1
            started_at = None
        if started_at is not None:
            assert obs.ego.changing_lane != 0
            assert obs.time - started_at <= LANE_CHANGE_TIMEOUT_S + 1e-6
        if obs.terminated or obs.truncated:
            break
    assert ends["aborted"] >= 1 and ends["completed"] >= 10, ends


def test_a_lane_change_is_refused_in_progress_exactly_while_one_is_under_way(
    backend: SumoBackend,
) -> None:
    obs = backend.reset("cflc", 7, options(backend, "cflc"))
    direction = 1 if obs.ego.lane < 2 else -1
    verdicts = []  # (a change under way before the step, the step's command refused in_progress)
    for seq in range(1, 120):
        before = obs.ego.changing_lane
        obs = backend.step(seq, 0.0, direction)
        verdicts.append((before != 0, obs.action.lane_change_refused == "in_progress"))
        if obs.terminated or obs.truncated:
            break
    assert all(under_way == refused for under_way, refused in verdicts), verdicts
    assert sum(refused for _, refused in verdicts) >= 10  # a change lasts 2 s: 20 steps


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
    traci = backend.name == "sumo-traci"
    custom = (CustomScenario("mine", built, EGO_ROUTE),)
    user = SumoBackend(cache_dir=tmp_path, custom=custom, traci=traci)
    try:
        assert "mine" in [s.name for s in user.scenarios()]
        obs = user.reset("mine", 3, options(user, "mine"))
        assert obs.ego.lane_count == 1
        assert user.step(1, 0.0, 0).seq == 1
    finally:
        if traci:  # (closing a libsumo backend would close the module's shared simulation)
            user.close()


def test_an_ego_that_vanishes_without_arriving_ends_the_episode_as_lost(
    backend: SumoBackend, monkeypatch: pytest.MonkeyPatch
) -> None:
    first = backend.reset("cflc", 17, options(backend, "cflc"))
    api = backend._api
    real_step = api.simulationStep

    def vaporise_and_step(time: float = 0.0) -> None:
        if EGO_ID in api.vehicle.getIDList():
            api.vehicle.remove(EGO_ID)  # gone without being reported as arrived in this step
        real_step(time)

    backend.step(1, 0.0, 0)
    monkeypatch.setattr(api, "simulationStep", vaporise_and_step)
    obs = backend.step(2, 0.0, 0)
    monkeypatch.undo()
    assert obs.terminated and obs.reason == "ego_lost"
    assert obs.time > first.time
    with pytest.raises(BackendError) as caught:
        backend.step(3, 0.0, 0)
    assert caught.value.code is ErrorCode.OUT_OF_ORDER
    assert backend.reset("cf", 1, options(backend, "cf")).seq == 0


# --------------------------------------------------------------------------- TraCI only


def test_traci_gives_the_libsumo_stream_bit_for_bit(
    libsumo_backend: SumoBackend, traci_backend: SumoBackend
) -> None:
    """Same SUMO release, same seed and actions: the two ways to drive it agree exactly."""
    assert traci_backend.name == "sumo-traci" and libsumo_backend.name == "sumo"
    assert traci_backend.version == libsumo_backend.version

    def lane_changing_idm(backend: SumoBackend, scenario: str, seed: int) -> list[Observation]:
        driver = IDMDriver()
        obs = backend.reset(scenario, seed, options(backend, scenario))
        stream = [obs]
        for seq in range(1, 400):
            change = (1 if obs.ego.lane == 0 else -1) if seq % 37 == 5 else 0
            obs = backend.step(seq, driver.act(obs)[0], change)
            stream.append(obs)
            if obs.terminated or obs.truncated:
                break
        return stream

    for scenario, seed in (("cf", 21), ("cflc", 4)):
        expected = lane_changing_idm(libsumo_backend, scenario, seed)
        got = lane_changing_idm(traci_backend, scenario, seed)
        assert [encode(o) for o in got] == [encode(o) for o in expected]  # the wire bytes
        if scenario == "cflc":
            assert any(o.events.lane_change_completed for o in expected)


def test_traci_attaches_to_a_sumo_another_tool_started(scenario_dir: Path) -> None:
    probe = SumoBackend(cache_dir=scenario_dir, traci=True)
    config = next(scenario_dir.glob("cf-*/cf.sumocfg"), None)
    if config is None:  # build the cf files
        probe.reset("cf", 1, options(probe, "cf"))
        config = next(scenario_dir.glob("cf-*/cf.sumocfg"))
    probe.close()
    port = free_port()
    other = subprocess.Popen(
        [find_sumo_binary(), "-c", str(config), "--remote-port", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        attached = SumoBackend(cache_dir=scenario_dir, traci=True, traci_port=port)
        assert attached.version == probe.version
        first = attached.reset("cflc", 2, options(attached, "cflc"))
        assert first.ego.lane_count == 3
        assert attached.step(1, 0.5, 0).seq == 1
        with pytest.raises(BackendError):  # a refused command keeps the attached SUMO...
            attached.reset("cf", 1, options(attached, "cf", decision_interval=0.15))
        assert attached.reset("cf", 1, options(attached, "cf")).ego.lane_count == 1  # ...usable
        attached.close()
        assert other.wait(timeout=30) == 0  # closing the TraCI connection ends that SUMO
    finally:
        if other.poll() is None:
            other.kill()
            other.wait()


def test_traci_attach_to_nothing_is_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    from sim_server.backends.sumo import runtime as sumo_runtime

    monkeypatch.setattr(sumo_runtime, "TRACI_START_TIMEOUT_S", 0.5)
    port = free_port()
    with pytest.raises(ValueError, match=f"cannot attach to SUMO at localhost:{port}"):
        SumoBackend(traci=True, traci_port=port)


def test_gui_without_a_display_is_refused_at_once(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(ValueError, match="DISPLAY is not set"):
        SumoBackend(traci=True, gui=True)
    assert cli.main(["--bind", "tcp://127.0.0.1:0", "--backend", "sumo-traci", "--gui"]) == 2
    refusal = capsys.readouterr().err
    assert refusal.startswith("sim-server: error: --backend sumo-traci: sumo-gui needs a display")
    assert refusal.count("\n") == 1


def test_gui_on_an_unreachable_display_fails_promptly_with_its_reason(
    monkeypatch: pytest.MonkeyPatch, scenario_dir: Path
) -> None:
    try:
        find_sumo_binary(gui=True)
    except FileNotFoundError:
        pytest.skip("no sumo-gui binary")
    monkeypatch.setenv("DISPLAY", ":977")  # no X server there
    gui = SumoBackend(cache_dir=scenario_dir, traci=True, gui=True)
    started = time.monotonic()
    with pytest.raises(BackendError) as caught:
        gui.reset("cf", 1, options(gui, "cf"))
    assert time.monotonic() - started < 30
    assert caught.value.code is ErrorCode.SIMULATOR_ERROR
    assert "sumo-gui exited" in caught.value.message
    assert "display" in caught.value.message.lower()
    gui.close()


def test_traci_options_need_traci() -> None:
    with pytest.raises(ValueError, match="need traci=True"):
        SumoBackend(gui=True)
    with pytest.raises(ValueError, match="cannot attach"):
        SumoBackend(traci=True, gui=True, traci_port=8813)
