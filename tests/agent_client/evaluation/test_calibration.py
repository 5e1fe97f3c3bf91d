"""IDM calibration without a server: synthetic trajectories from a known IDM."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from agent_client.constants import PAPER_SPEED_LIMIT
from agent_client.drivers.idm import IDMDriver, IDMParams, idm_acceleration
from agent_client.drivers.spec import load_driver
from agent_client.evaluation.calibration import (
    PARAM_NAMES,
    CalibrationResult,
    Segment,
    calibration_document,
    fit_idm,
    make_batch,
    segments_from_observations,
    simulate,
)
from protocol.messages import Ego, Events, Neighbour, Neighbours
from tests.protocol.test_codec import make_observation

DT = 0.1
RECOVERY_TOLERANCE = 0.01
"""The fit must recover each of the six parameters within 1 % (relative) on noise-free data."""


def leader_speeds(rng: np.random.Generator, steps: int) -> np.ndarray:
    """A leader that slows, speeds up and at times drives off (so the follower reaches v0)."""
    t = np.arange(steps) * DT
    target = 14.0 + 6.0 * np.sin(2 * np.pi * t / rng.uniform(30, 60) + rng.uniform(0, 6))
    target += np.where(t % 50 > 35, 12.0, 0.0) * rng.integers(0, 2)
    speeds = [float(target[0])]
    for wanted in target[1:]:  # limited acceleration: +2 / -3 m/s^2
        speeds.append(speeds[-1] + float(np.clip(wanted - speeds[-1], -3 * DT, 2 * DT)))
    return np.array(speeds)


def synthetic_segment(params: IDMParams, rng: np.random.Generator, steps: int = 600) -> Segment:
    """An IDM follower behind a leader, simulated with the scalar model and a ballistic update."""
    vl = leader_speeds(rng, steps)
    leader = np.concatenate([[0.0], np.cumsum(0.5 * (vl[1:] + vl[:-1]) * DT)]) + rng.uniform(15, 40)
    x, v = 0.0, float(rng.uniform(8, 20))
    xs, vs, accs = [x], [v], [0.0]
    for k in range(steps - 1):
        acc = idm_acceleration(params, v, PAPER_SPEED_LIMIT, leader[k] - x, vl[k])
        new_v = v + acc * DT
        if new_v < 0:
            x += v * v / (-2 * acc)
            new_v = 0.0
        else:
            x += 0.5 * (v + new_v) * DT
        v = new_v
        xs.append(x)
        vs.append(v)
        accs.append(acc)
    position = np.array(xs)
    return Segment(
        seed=0,
        leader_id="leader",
        time=np.arange(steps) * DT,
        speed=np.array(vs),
        acceleration=np.array(accs),
        gap=leader - position,
        leader_speed=vl,
        position=position,
    )


def as_vector(params: IDMParams) -> np.ndarray:
    return np.array([getattr(params, name) for name in PARAM_NAMES], dtype=float)


def test_vectorised_simulation_matches_the_scalar_model() -> None:
    params = IDMParams(a=1.2, b=1.8, T=1.3, s0=2.5, v0=24.0, delta=4.0)
    segment = synthetic_segment(params, np.random.default_rng(3))
    batch = make_batch([segment], DT)
    sse, gaps = simulate(as_vector(params)[None, :], batch, keep_gaps=True)
    assert gaps is not None
    assert gaps[0, 0, : len(segment)] == pytest.approx(segment.gap, abs=1e-9)
    assert sse[0] == pytest.approx(0.0, abs=1e-12)
    other = IDMParams(a=1.2, b=1.8, T=1.8, s0=2.5, v0=24.0, delta=4.0)
    sse_other, _ = simulate(as_vector(other)[None, :], batch)
    assert sse_other[0] > 1.0  # a longer headway opens the gap: the error shows it


def test_batch_cuts_long_segments_into_windows_that_share_their_ends() -> None:
    segment = synthetic_segment(IDMParams(v0=24.0), np.random.default_rng(0), steps=1301)
    batch = make_batch([segment], DT, window_s=60.0)
    assert batch.windows == 3  # 0-60 s, 60-120 s, 120-130 s
    assert batch.samples == 1300  # every step compared once; the starts are initial states
    assert batch.speed0 == pytest.approx(segment.speed[[0, 600, 1200]])


@pytest.mark.parametrize(
    "true",
    [
        IDMParams(a=1.2, b=1.8, T=1.3, s0=2.5, v0=24.0, delta=4.0),
        IDMParams(a=2.0, b=3.0, T=0.9, s0=1.5, v0=20.0, delta=2.5),
    ],
)
def test_fit_recovers_a_known_idm(true: IDMParams) -> None:
    rng = np.random.default_rng(1)
    segments = [synthetic_segment(true, rng) for _ in range(8)]
    result = fit_idm(segments, DT, seed=0, maxiter=30, popsize=8)
    assert isinstance(result, CalibrationResult)
    fitted = as_vector(result.params)
    assert fitted == pytest.approx(as_vector(true), rel=RECOVERY_TOLERANCE)
    assert result.gap_rmse < 0.05  # metres, on gaps of 5-60 m
    assert result.gap_rmse <= result.global_gap_rmse + 1e-12  # the refinement never worsens
    assert result.samples == 8 * 599
    assert result.at_bounds == []


def test_segments_split_at_absence_leader_change_and_distance() -> None:
    absent = Neighbour(False, 200.0, 0.0, 0.0)
    observations = []
    for i in range(500):
        t = 30.0 + i * DT
        if i < 150:  # 15 s behind A
            leader = Neighbour(True, 20.0, 0.0, 10.0, "A")
        elif i < 160:  # 1 s without a leader
            leader = absent
        elif i < 300:  # 14 s behind B
            leader = Neighbour(True, 25.0, 0.0, 10.0, "B")
        elif i < 320:  # B drives off: 60 m at 10 m/s is beyond max(20 m, 3 s x speed)
            leader = Neighbour(True, 60.0, 0.0, 12.0, "B")
        elif i < 400:  # B again within range, 8 s: too short to keep
            leader = Neighbour(True, 25.0, 0.0, 10.0, "B")
        else:  # C cuts in: 10 s
            leader = Neighbour(True, 12.0, 0.0, 10.0, "C")
        observations.append(
            make_observation(
                seq=i,
                time=t,
                ego=Ego(10.0, 0.0, 0, 1, 100.0 + 1.0 * i, PAPER_SPEED_LIMIT),
                neighbours=Neighbours(absent, absent, leader, absent, absent, absent),
                events=Events(),
            )
        )
    segments = segments_from_observations(observations, seed=4, step_length=DT, min_duration=9.0)
    assert [s.leader_id for s in segments] == ["A", "B", "C"]
    assert [len(s) for s in segments] == [150, 140, 100]
    assert segments[0].leader_position == pytest.approx(segments[0].position + 20.0)
    assert all(s.seed == 4 for s in segments)


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
        bounds={name: (0.0, 50.0) for name in PARAM_NAMES},
    )
    document = calibration_document(result, {"scenario": "cf", "seeds": [1, 2]}, {"x": "1"})
    path = tmp_path / "idm.json"
    path.write_text(json.dumps(document))
    driver = load_driver(f"idm:{path}")
    assert isinstance(driver, IDMDriver)
    assert driver.params == params
    saved = json.loads(path.read_text())
    assert saved["fit"]["gap_rmse_m"] == 1.5
    assert saved["data"]["seeds"] == [1, 2] and saved["data"]["samples"] == 300
    assert saved["bounds"]["v0"] == [0.0, 50.0]
