"""IDM calibration without a server: segments from traffic columns, SUMO's stepping, the fit.

The synthetic followers are simulated here with an independent scalar transcription of SUMO's
IDM (``MSCFModel_IDM::_v``) and SUMO's position updates, so that the vectorised simulation is
checked against what SUMO does, not against itself.
"""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from agent_client.constants import PAPER_SPEED_LIMIT
from agent_client.drivers.episode import Idle
from agent_client.drivers.idm import IDMDriver, IDMParams
from agent_client.drivers.spec import load_driver
from agent_client.errors import UsageError
from agent_client.evaluation.calibration import (
    SHARED_NAMES,
    CalibrationResult,
    FollowerV0,
    Model,
    Segment,
    calibration_document,
    choose_vehicle_type,
    detect_update,
    fit_idm,
    follower_sums,
    make_batch,
    recording_options,
    segments_from_observations,
    segments_from_traffic,
    simulate,
    sumo_idm_speed,
    sumo_iterations,
    types_seen,
)
from protocol.messages import Ego, Events, Neighbour, Neighbours, Traffic
from tests.protocol.test_codec import make_observation

DT = 0.1
TRUE = IDMParams(a=1.2, b=1.8, T=1.3, s0=2.5, v0=None, delta=4.0)
RECOVERY_TOLERANCE = 1e-3
"""On noise-free data the fit must recover every parameter within 0.1 % (relative)."""


def sumo_speed(
    p: IDMParams, v0: float, v: float, gap: float, vl: float, dt: float, n: int
) -> float:
    """SUMO's MSCFModel_IDM::_v for one vehicle, transcribed (gap: the net gap, minGap included)."""
    for _ in range(n):
        s = p.s0 + max(0.0, v * p.T + v * (v - vl) / (2 * (p.a * p.b) ** 0.5))
        gap = max(1e-3, gap)
        acc = p.a * (1.0 - (v / max(1e-3, v0)) ** p.delta - (s * s) / (gap * gap))
        v = max(0.0, v + acc * dt / n)
        gap -= max(0.0, (v - vl) * dt / n)
    return v


def leader_speeds(rng: np.random.Generator, steps: int, dt: float) -> np.ndarray:
    """A leader that slows, speeds up and at times drives off (so the follower nears its v0)."""
    t = np.arange(steps) * dt
    target = 14.0 + 6.0 * np.sin(2 * np.pi * t / rng.uniform(30, 60) + rng.uniform(0, 6))
    target += np.where(t % 50 > 35, 12.0, 0.0) * rng.integers(0, 2)
    speeds = [float(target[0])]
    for wanted in target[1:]:  # limited acceleration: +2 / -3 m/s^2
        speeds.append(speeds[-1] + float(np.clip(wanted - speeds[-1], -3 * dt, 2 * dt)))
    return np.array(speeds)


def synthetic_segment(
    p: IDMParams,
    v0: float,
    rng: np.random.Generator,
    follower: str,
    *,
    steps: int = 600,
    dt: float = DT,
    update: str = "euler",
    vl: np.ndarray | None = None,
    start: tuple[float, float] | None = None,
) -> Segment:
    """A follower with desired speed `v0` behind a leader, as SUMO would integrate it."""
    vl = leader_speeds(rng, steps, dt) if vl is None else vl
    gap0, speed0 = start or (float(rng.uniform(15, 40)), float(rng.uniform(8, 20)))
    leader = np.concatenate([[0.0], np.cumsum(vl[1:] * dt)]) + gap0  # the leader: Euler too
    n = sumo_iterations(dt)
    x, v = 0.0, speed0
    xs, vs = [x], [v]
    for k in range(steps - 1):
        new = sumo_speed(p, v0, v, leader[k] - x, vl[k], dt, n)
        x += new * dt if update == "euler" else 0.5 * (v + new) * dt
        v = new
        xs.append(x)
        vs.append(v)
    position, speed = np.array(xs), np.array(vs)
    return Segment(
        seed=0,
        follower_id=follower,
        vehicle_type="car",
        leader_id="leader",
        time=np.arange(steps) * dt,
        speed=speed,
        acceleration=np.r_[0.0, np.diff(speed) / dt],
        gap=leader - position,
        leader_speed=vl,
        position=position,
        max_speed=float(speed.max()),
    )


def shared(p: IDMParams) -> np.ndarray:
    return np.array([getattr(p, name) for name in SHARED_NAMES], dtype=float)


# --------------------------------------------------------------------------- SUMO's stepping


@pytest.mark.parametrize(("dt", "iterations"), [(0.1, 1), (0.2, 1), (0.5, 2), (1.0, 4)])
def test_iterations_follow_sumos_stepping(dt: float, iterations: int) -> None:
    assert sumo_iterations(dt) == iterations  # max(1, int(dt / 0.25 + 0.5))


@pytest.mark.parametrize("iterations", [1, 3])
def test_vectorised_idm_step_is_sumos(iterations: int) -> None:
    rng = np.random.default_rng(5)
    speed, gap = rng.uniform(0, 30, 200), rng.uniform(0.5, 80, 200)
    leader_speed, v0 = rng.uniform(0, 30, 200), rng.uniform(15, 35, 200)
    params = (*(np.full(200, getattr(TRUE, n)) for n in SHARED_NAMES), v0)
    got = sumo_idm_speed(speed, gap, leader_speed, params, 0.5, iterations)
    want = [
        sumo_speed(TRUE, v0[i], speed[i], gap[i], leader_speed[i], 0.5, iterations)
        for i in range(200)
    ]
    assert got == pytest.approx(want, abs=1e-12)


@pytest.mark.parametrize(("update", "dt"), [("euler", 0.1), ("ballistic", 0.1), ("euler", 0.5)])
def test_simulation_reproduces_sumos_trajectories(update: str, dt: float) -> None:
    rng = np.random.default_rng(3)
    segments = [
        synthetic_segment(TRUE, v0, rng, f"f{i}", dt=dt, update=update, steps=int(120 / dt))
        for i, v0 in enumerate((21.0, 27.0))
    ]
    assert detect_update(segments, dt) == update
    batch = make_batch(segments, dt)
    model = Model(dt, update, sumo_iterations(dt))
    v0 = np.array([21.0, 27.0])
    per_window, gaps = simulate(shared(TRUE)[None], v0[None], batch, model, keep_gaps=True)
    assert per_window.sum() == pytest.approx(0.0, abs=1e-16)
    assert gaps is not None and np.abs(gaps[0] - batch.gap)[batch.mask].max() < 1e-9
    longer = shared(IDMParams(a=1.2, b=1.8, T=1.6, s0=2.5, delta=4.0))
    assert simulate(longer[None], v0[None], batch, model)[0].sum() > 10.0  # the error shows it
    other = "ballistic" if update == "euler" else "euler"
    assert simulate(shared(TRUE)[None], v0[None], batch, Model(dt, other, 1))[0].sum() > 0.01


def test_windows_are_packed_end_to_end_and_summed_per_follower() -> None:
    rng = np.random.default_rng(0)
    segments = [
        synthetic_segment(TRUE, 25.0, rng, "long", steps=1301),  # 3 windows: 60 + 60 + 10 s
        synthetic_segment(TRUE, 22.0, rng, "short", steps=150),
        synthetic_segment(TRUE, 28.0, rng, "tiny", steps=120),
    ]
    batch = make_batch(segments, DT, window_s=60.0)
    assert batch.windows == 5
    assert batch.samples == 1300 + 149 + 119  # every step compared once; starts are initial
    assert batch.gap.shape[1] < batch.windows  # short windows share rows
    assert batch.followers == ((0, "long"), (0, "short"), (0, "tiny"))
    assert batch.follower_samples().tolist() == [1300, 149, 119]
    v0 = np.array([[25.0, 22.0, 28.0], [25.0, 22.0, 30.0]])
    per_window, _ = simulate(np.repeat(shared(TRUE)[None], 2, 0), v0, batch, Model(DT))
    sums = follower_sums(per_window, batch)
    assert sums[0] == pytest.approx(0.0, abs=1e-16)
    assert sums[1, :2] == pytest.approx(0.0, abs=1e-16) and sums[1, 2] > 0  # only "tiny" moved


# --------------------------------------------------------------------------- recording


def traffic_observations() -> list:
    """Two vehicles' traffic columns over 60 s (0.1 s steps), with every kind of break."""
    observations = []
    for i in range(600):
        rows = []
        speed_a = 10.0 + 0.01 * i
        if i < 150:  # 15 s behind L1
            rows.append(("A", "car", 0, 100.0 + i, speed_a, "L1", 20.0))
        elif i < 160:  # 1 s without a leader
            rows.append(("A", "car", 0, 100.0 + i, speed_a, "", 200.0))
        elif i < 300:  # 14 s behind L2
            rows.append(("A", "car", 0, 100.0 + i, speed_a, "L2", 25.0))
        elif i < 320:  # L2 drives off: 60 m at ~13 m/s is beyond max(20 m, 3 s x speed)
            rows.append(("A", "car", 0, 100.0 + i, speed_a, "L2", 60.0))
        elif i < 400:  # L2 in range again for 8 s: too short to keep
            rows.append(("A", "car", 0, 100.0 + i, speed_a, "L2", 25.0))
        else:  # behind L3 for 20 s, changing lane at 50 s
            rows.append(("A", "car", 0 if i < 500 else 1, 100.0 + i, speed_a, "L3", 15.0))
        if i < 100 or 150 <= i < 300:  # B leaves for 5 s (a jump in time) and comes back
            rows.append(("B", "bus", 0, 2.0 * i, 20.0 if i == 120 else 8.0, "A", 18.0))
        elif 100 <= i < 150:
            pass
        else:
            rows.append(("B", "bus", 0, 2.0 * i, 8.0, "", 200.0))
        columns = list(zip(*rows, strict=True))
        traffic = Traffic(
            id=columns[0],
            vehicle_type=columns[1],
            lane=columns[2],
            position=columns[3],
            speed=columns[4],
            acceleration=tuple(0.0 for _ in rows),
            leader=columns[5],
            gap=columns[6],
            leader_speed=tuple(9.0 for _ in rows),
        )
        observations.append(make_observation(seq=i, time=30.0 + i * DT, traffic=traffic))
    return observations


def test_segments_from_traffic_split_at_every_break() -> None:
    segments = segments_from_traffic(
        traffic_observations(), seed=4, step_length=DT, min_duration=9.0
    )
    a = [s for s in segments if s.follower_id == "A"]
    assert [(s.leader_id, len(s)) for s in a] == [
        ("L1", 150),
        ("L2", 140),
        ("L3", 100),
        ("L3", 100),
    ]
    assert a[0].leader_position == pytest.approx(a[0].position + 20.0)
    assert a[0].max_speed == pytest.approx(10.0 + 0.01 * 599)  # over the whole track
    b = [s for s in segments if s.follower_id == "B"]
    assert [len(s) for s in b] == [100, 150]  # split where it was away
    assert {s.vehicle_type for s in b} == {"bus"} and b[0].max_speed == 8.0  # 20 m/s at 12 s: away
    assert all(s.seed == 4 for s in segments) and a[0].follower == (4, "A")


def test_types_seen_and_the_type_chosen() -> None:
    segments = segments_from_traffic(
        traffic_observations(), seed=4, step_length=DT, min_duration=9.0
    )
    more = segments_from_traffic(traffic_observations(), seed=5, step_length=DT, min_duration=9.0)
    bus_only = [s for s in more if s.vehicle_type == "bus"]
    seen = types_seen([*segments, *bus_only])
    assert list(seen) == ["bus", "car"]  # two bus followers (two episodes), one car
    assert seen["car"].segments == 4 and seen["bus"].followers == 2
    assert choose_vehicle_type([*segments, *bus_only]) == "bus"
    assert choose_vehicle_type(segments, "bus") == "bus"
    with pytest.raises(UsageError, match=r"'truck' never followed.*car \(1 followers\)"):
        choose_vehicle_type(segments, "truck")


def test_the_ego_source_still_records_a_simulator_driven_ego() -> None:
    absent = Neighbour(False, 200.0, 0.0, 0.0)
    observations = []
    for i in range(300):
        leader = Neighbour(True, 20.0, 0.0, 10.0, "A") if i < 150 else absent
        observations.append(
            make_observation(
                seq=i,
                time=30.0 + i * DT,
                ego=Ego(10.0, 0.0, 0, 1, 100.0 + 1.0 * i, PAPER_SPEED_LIMIT),
                neighbours=Neighbours(absent, absent, leader, absent, absent, absent),
                events=Events(),
            )
        )
    (segment,) = segments_from_observations(observations, seed=2, step_length=DT)
    assert (segment.follower, segment.leader_id, len(segment)) == ((2, "ego"), "A", 150)


def test_recording_options_ask_for_the_traffic_and_refuse_without_it() -> None:
    offered = {"decision_interval": 0.1, "report_ceiling": True, "ego_driver": "agent"}
    env = SimpleNamespace(scenario="x", step_length=0.1, scenario_options=offered)
    with pytest.raises(UsageError, match=r"does not offer report_traffic.*--source ego"):
        recording_options(env, "traffic")  # type: ignore[arg-type]
    env.scenario_options = {**offered, "report_traffic": False}
    options, driver = recording_options(env, "traffic")  # type: ignore[arg-type]
    assert options == {
        "report_traffic": True,
        "decision_interval": 0.1,
        "report_ceiling": False,
        "ego_driver": "sumo",
    }
    assert isinstance(driver, Idle)
    env.scenario_options = {"report_traffic": False}  # no ego_driver: an IDM ego keeps moving
    options, driver = recording_options(env, "traffic")  # type: ignore[arg-type]
    assert options == {"report_traffic": True} and isinstance(driver, IDMDriver)


# --------------------------------------------------------------------------- fitting


@pytest.mark.parametrize(("update", "dt"), [("euler", 0.1), ("ballistic", 0.1), ("euler", 0.5)])
def test_fit_recovers_a_known_idm_with_a_desired_speed_per_follower(update: str, dt: float) -> None:
    rng = np.random.default_rng(1)
    v0s = (20.0, 22.5, 25.0, 27.5, 30.0, 23.0, 26.0, 28.0)
    segments = [
        synthetic_segment(TRUE, v0, rng, f"f{i}", dt=dt, update=update, steps=int(60 / dt))
        for i, v0 in enumerate(v0s)
    ]
    result = fit_idm(segments, dt, seed=0, maxiter=15, popsize=8, replicates=20)
    assert isinstance(result, CalibrationResult)
    assert result.settings["update"] == update
    assert shared(result.params) == pytest.approx(shared(TRUE), rel=RECOVERY_TOLERANCE)
    determined = [f for f in result.v0_followers if f.determined]
    assert len(determined) >= 6
    for follower in determined:
        assert follower.v0 == pytest.approx(v0s[int(follower.id[1:])], rel=RECOVERY_TOLERANCE)
    assert result.gap_rmse < 1e-3 and result.gap_rmse <= result.global_gap_rmse + 1e-12
    assert result.samples == 8 * (int(60 / dt) - 1)
    assert result.at_bounds == [] and result.undetermined == [] and result.wide == []
    for name in SHARED_NAMES:  # the intervals are reported and hold the truth
        low, high = result.intervals[name]
        assert low - 1e-6 <= getattr(TRUE, name) <= high + 1e-6


def test_traffic_in_one_steady_state_is_flagged_undetermined() -> None:
    """Followers that never leave one equilibrium fit any parameters that keep it (the ring
    with noise-free IDM): a perfect fit that determines nothing, and says so."""
    v, v0 = 10.0, 30.0
    equilibrium = (TRUE.s0 + v * TRUE.T) / (1 - (v / v0) ** TRUE.delta) ** 0.5
    rng = np.random.default_rng(2)
    segments = [
        synthetic_segment(TRUE, v0, rng, f"f{i}", vl=np.full(600, v), start=(equilibrium, v))
        for i in range(4)
    ]
    result = fit_idm(segments, DT, seed=0, maxiter=5, popsize=5, replicates=10)
    assert result.gap_rmse < 1e-6
    assert set(result.undetermined) == {"a", "b", "T", "s0", "delta", "v0"}


def test_calibration_file_drives_through_load_driver(tmp_path: Path) -> None:
    params = IDMParams(a=1.1, b=1.7, T=1.2, s0=2.2, v0=19.5, delta=4.0)
    result = CalibrationResult(
        params=params,
        gap_rmse=1.5,
        gap_nrmse=0.1,
        global_gap_rmse=1.6,
        generations=3,
        evaluations=100,
        seconds=1.0,
        segments=2,
        windows=3,
        samples=300,
        bounds={name: (0.0, 50.0) for name in (*SHARED_NAMES, "v0")},
        intervals={name: (0.9 * v, 1.1 * v) for name, v in params.to_dict().items() if v},
        v0_followers=[FollowerV0(1, "f.0", 19.5, 19.0, True), FollowerV0(1, "f.1", 50.0, 9, False)],
        sensitivity={name: 0.2 for name in SHARED_NAMES},
    )
    document = calibration_document(result, {"scenario": "cf", "seeds": [1, 2]}, {"x": "1"})
    path = tmp_path / "idm.json"
    path.write_text(json.dumps(document))
    driver = load_driver(f"idm:{path}")
    assert isinstance(driver, IDMDriver)
    assert driver.params == params
    saved = json.loads(path.read_text())
    assert saved["fit"]["gap_rmse_m"] == 1.5 and saved["fit"]["undetermined"] == []
    assert saved["data"]["seeds"] == [1, 2] and saved["data"]["samples"] == 300
    assert saved["data"]["followers"] == 2 and saved["bounds"]["v0"] == [0.0, 50.0]
    assert (
        saved["intervals"]["T"] == pytest.approx([1.08, 1.32])
        and saved["intervals"]["level"] == 0.9
    )
    assert saved["v0"]["determined"] == 1 and saved["v0"]["at_upper_bound"] == 1
    assert saved["v0"]["per_follower"][0] == {
        "seed": 1, "id": "f.0", "v0": 19.5, "max_speed": 19.0, "determined": True
    }  # fmt: skip
