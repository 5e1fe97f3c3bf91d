"""Calibrate IDM on human trajectories recorded through the bridge (the paper's §4.4 baseline).

1. `record_segments` drives episodes with the reset option ``ego_driver="sumo"``: the ego is one
   of the scenario's human drivers and every observation reports what it did. Steps with a
   leader within car-following range are kept and split into `Segment`s at every gap in leader
   presence, leader change (a cut-in, a lane change) or jump in time.
2. `fit_idm` simulates an IDM follower against each recorded leader: it starts at the recorded
   speed and gap, the leader's rear is where it was recorded (ego position + gap), and the
   follower moves by a ballistic update every step (0.1 s in our scenarios). The objective is the
   RMSE of the simulated gap against the recorded one, pooled over all samples (metres); its
   normalised form sqrt(sum err^2 / sum gap^2) is reported too (same minimiser). A seeded
   differential evolution searches the bounds (the whole population simulated at once with
   numpy), then L-BFGS-B refines (its gradient, too, is one vectorised simulation).

`calibration_document` gives the JSON that ``agent-client drive --policy idm:FILE`` reads.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from agent_client.drivers.episode import Idle, run_episode
from agent_client.drivers.idm import IDMParams
from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import UsageError
from protocol.messages import Observation, OptionValue

PARAM_NAMES = ("a", "b", "T", "s0", "v0", "delta")
"""Order of the IDM parameters in parameter vectors."""

DEFAULT_BOUNDS: dict[str, tuple[float, float]] = {
    "a": (0.3, 4.0),
    "b": (0.3, 5.0),
    "T": (0.3, 3.0),
    "s0": (0.5, 6.0),
    "v0": (5.0, 40.0),
    "delta": (1.0, 8.0),
}
"""Search box of the fit (m, s, m/s, m/s^2): wide around published IDM calibrations."""

FOLLOWING_HEADWAY_S = 3.0
"""s: a step counts as car following when the leader is within this headway (or 20 m)."""
FOLLOWING_GAP_M = 20.0
"""m: the car-following range at low speed: max(20 m, 3 s x speed) in all. Farther behind, a
human drives at its own desired speed (SUMO draws one per driver): one IDM cannot follow every
driver falling back behind a faster leader, and such stretches would dominate the spacing error."""
MIN_SEGMENT_S = 10.0
"""Car-following stretches shorter than this (s) are dropped: too short to tell parameters."""
WINDOW_S = 60.0
"""Longer stretches are cut into windows of this length, each simulated from its recorded start."""
MIN_GAP = 0.1
"""m: the IDM interaction term uses max(gap, MIN_GAP), as `agent_client.drivers.idm` does."""


# --------------------------------------------------------------------------- recording


@dataclass(frozen=True, eq=False)
class Segment:
    """Car following behind one leader, sampled every simulation step."""

    seed: int
    leader_id: str
    time: np.ndarray
    speed: np.ndarray
    acceleration: np.ndarray
    gap: np.ndarray
    leader_speed: np.ndarray
    position: np.ndarray

    def __len__(self) -> int:
        return len(self.time)

    @property
    def duration(self) -> float:
        return float(self.time[-1] - self.time[0]) if len(self.time) else 0.0

    @property
    def leader_position(self) -> np.ndarray:
        """Position of the leader's rear on the ego's route (m)."""
        return self.position + self.gap


def segments_from_observations(
    observations: Sequence[Observation],
    seed: int,
    step_length: float,
    min_duration: float = MIN_SEGMENT_S,
) -> list[Segment]:
    """Split an episode into car-following segments: leader present and near, same leader, no jump
    in time; segments shorter than `min_duration` are dropped."""
    return [
        _segment(run, seed)
        for run in _following_runs(observations, step_length)
        if len(run) >= 2 and run[-1].time - run[0].time >= min_duration - 1e-9
    ]


def _is_following(obs: Observation) -> bool:
    """A leader within car-following range, and nothing that breaks the trajectory."""
    leader = obs.neighbours.leader
    near = leader.gap <= max(FOLLOWING_GAP_M, FOLLOWING_HEADWAY_S * obs.ego.speed)
    return leader.present and near and not obs.events.collision and not obs.events.teleported


def _following_runs(
    observations: Iterable[Observation], step_length: float
) -> list[list[Observation]]:
    """Consecutive following observations behind one leader, without a jump in time."""
    runs: list[list[Observation]] = []
    current: list[Observation] = []
    for obs in observations:
        usable = _is_following(obs)
        if current:
            last = current[-1]
            jump = obs.time - last.time > 1.5 * step_length
            if not usable or jump or obs.neighbours.leader.id != last.neighbours.leader.id:
                runs.append(current)
                current = []
        if usable:
            current.append(obs)
    if current:
        runs.append(current)
    return runs


def _segment(run: Sequence[Observation], seed: int) -> Segment:
    return Segment(
        seed=seed,
        leader_id=run[0].neighbours.leader.id,
        time=np.array([o.time for o in run]),
        speed=np.array([o.ego.speed for o in run]),
        acceleration=np.array([o.ego.acceleration for o in run]),
        gap=np.array([o.neighbours.leader.gap for o in run]),
        leader_speed=np.array([o.neighbours.leader.speed for o in run]),
        position=np.array([o.ego.position for o in run]),
    )


def record_segments(
    env: RemoteEnv,
    seeds: Iterable[int],
    min_duration: float = MIN_SEGMENT_S,
    on_episode: Callable[[int, list[Segment], int], None] | None = None,
) -> list[Segment]:
    """Record human drivers through a `RemoteEnv` (``ego_driver="sumo"``, one step per decision).

    `on_episode(seed, segments, steps)` is called after each episode (progress).
    """
    step_length = env.step_length
    assert step_length is not None  # RemoteEnv knows it once connected
    if "ego_driver" not in env.scenario_options:
        raise UsageError(
            f"scenario {env.scenario} has no ego_driver option: calibrate-idm records the "
            "simulator's own drivers (docs/protocol.md §2.3)"
        )
    options: dict[str, OptionValue] = {"ego_driver": "sumo"}
    for name, value in (("decision_interval", step_length), ("report_ceiling", False)):
        if name in env.scenario_options:  # a scenario without it already decides every step
            options[name] = value
    segments: list[Segment] = []
    for seed in seeds:
        observations = run_episode(env, Idle(), seed, options=options).observations
        found = segments_from_observations(observations, seed, step_length, min_duration)
        segments.extend(found)
        if on_episode is not None:
            on_episode(seed, found, len(observations) - 1)
    return segments


# --------------------------------------------------------------------------- simulation


@dataclass(frozen=True, eq=False)
class SegmentBatch:
    """Segments cut into windows and padded into (windows, steps) arrays for vectorised runs."""

    dt: float
    leader_position: np.ndarray
    leader_speed: np.ndarray
    position: np.ndarray
    gap: np.ndarray
    mask: np.ndarray
    """True where a recorded sample is compared (never the first, which is the initial state)."""
    speed0: np.ndarray

    @property
    def windows(self) -> int:
        return self.gap.shape[0]

    @property
    def samples(self) -> int:
        return int(self.mask.sum())


def make_batch(segments: Sequence[Segment], dt: float, window_s: float = WINDOW_S) -> SegmentBatch:
    """Cut segments into windows of at most `window_s` and pad them (edge values, masked out)."""
    if not segments:
        raise ValueError("no car-following segments to fit on")
    steps = max(2, round(window_s / dt) + 1)
    pieces: list[tuple[Segment, int, int]] = []
    for segment in segments:
        start = 0
        while len(segment) - start >= 2:
            stop = min(start + steps, len(segment))
            if stop - start >= 2:
                pieces.append((segment, start, stop))
            start = stop - 1  # the next window starts where this one ended
            if stop == len(segment):
                break
    length = max(stop - start for _, start, stop in pieces)
    shape = (len(pieces), length)
    leader_position, leader_speed = np.zeros(shape), np.zeros(shape)
    position, gap = np.zeros(shape), np.zeros(shape)
    mask = np.zeros(shape, dtype=bool)
    for row, (segment, start, stop) in enumerate(pieces):
        n = stop - start
        origin = segment.position[start]  # local coordinates keep the numbers small
        for target, values in (
            (leader_position, segment.leader_position[start:stop] - origin),
            (leader_speed, segment.leader_speed[start:stop]),
            (position, segment.position[start:stop] - origin),
            (gap, segment.gap[start:stop]),
        ):
            target[row, :n] = values
            target[row, n:] = values[-1]
        mask[row, 1:n] = True
    speed0 = np.array([segment.speed[start] for segment, start, _ in pieces])
    return SegmentBatch(dt, leader_position, leader_speed, position, gap, mask, speed0)


def simulate(
    params: np.ndarray,
    batch: SegmentBatch,
    acceleration_bounds: tuple[float, float] | None = None,
    keep_gaps: bool = False,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Run IDM followers for S parameter vectors (S, 6) on every window at once.

    Returns the sum of squared gap errors per parameter vector (S,) and, with `keep_gaps`, the
    simulated gaps (S, windows, steps). The update is ballistic: x += v dt + a dt^2 / 2, with the
    speed kept at or above zero (a follower that would reverse stops where its speed hits zero).
    """
    params = np.atleast_2d(np.asarray(params, dtype=float))
    a, b, T, s0, v0, delta = (params[:, i, None] for i in range(len(PARAM_NAMES)))
    two_sqrt_ab = 2.0 * np.sqrt(a * b)
    v0 = np.maximum(v0, 1e-6)
    count, (windows, steps) = params.shape[0], batch.gap.shape
    dt = batch.dt
    speed = np.broadcast_to(batch.speed0, (count, windows)).copy()
    x = np.broadcast_to(batch.position[:, 0], (count, windows)).copy()
    sse = np.zeros(count)
    gaps = np.empty((count, windows, steps)) if keep_gaps else None
    if gaps is not None:
        gaps[:, :, 0] = batch.leader_position[:, 0] - x
    for k in range(steps - 1):
        gap = batch.leader_position[:, k] - x
        closing = speed - batch.leader_speed[:, k]
        desired = s0 + np.maximum(0.0, speed * T + speed * closing / two_sqrt_ab)
        acc = a * (1.0 - (speed / v0) ** delta - (desired / np.maximum(gap, MIN_GAP)) ** 2)
        if acceleration_bounds is not None:
            acc = np.clip(acc, acceleration_bounds[0], acceleration_bounds[1])
        new_speed = speed + acc * dt
        stops = new_speed < 0.0
        x += np.where(
            stops, speed * speed / (-2.0 * np.minimum(acc, -1e-12)), 0.5 * (speed + new_speed) * dt
        )
        speed = np.maximum(new_speed, 0.0)
        error = batch.position[:, k + 1] - x  # = simulated gap - recorded gap
        sse += np.square(np.where(batch.mask[:, k + 1], error, 0.0)).sum(axis=1)
        if gaps is not None:
            gaps[:, :, k + 1] = batch.leader_position[:, k + 1] - x
    return sse, gaps


def gap_rmse(
    params: np.ndarray,
    batch: SegmentBatch,
    acceleration_bounds: tuple[float, float] | None = None,
) -> np.ndarray:
    """Pooled RMSE (m) of the simulated gap for each parameter vector (S, 6) -> (S,)."""
    sse, _ = simulate(params, batch, acceleration_bounds)
    return np.sqrt(sse / batch.samples)


# --------------------------------------------------------------------------- fitting


@dataclass
class CalibrationResult:
    """Fitted parameters, their errors and what the fit cost."""

    params: IDMParams
    gap_rmse: float
    """Pooled RMSE of the simulated gap (m): the objective."""
    gap_nrmse: float
    """sqrt(sum err^2 / sum gap^2): the same error relative to the recorded gaps."""
    global_gap_rmse: float
    """The objective after differential evolution, before the local refinement."""
    generations: int
    evaluations: int
    seconds: float
    segments: int
    windows: int
    samples: int
    bounds: dict[str, tuple[float, float]]
    settings: dict[str, Any] = field(default_factory=dict)

    @property
    def at_bounds(self) -> list[str]:
        """Parameters within 0.5 % of the search range from a bound (poorly determined)."""
        found = []
        for name, (low, high) in self.bounds.items():
            value = getattr(self.params, name)
            if min(value - low, high - value) <= 0.005 * (high - low):
                found.append(name)
        return found


def _as_params(x: np.ndarray) -> IDMParams:
    return IDMParams(**{name: float(value) for name, value in zip(PARAM_NAMES, x, strict=True)})


def fit_idm(
    segments: Sequence[Segment],
    dt: float,
    *,
    bounds: Mapping[str, tuple[float, float]] | None = None,
    seed: int = 0,
    maxiter: int = 40,
    popsize: int = 10,
    window_s: float = WINDOW_S,
    acceleration_bounds: tuple[float, float] | None = None,
    local_maxiter: int = 200,
    on_generation: Callable[[int, float], None] | None = None,
) -> CalibrationResult:
    """Fit the six IDM parameters to recorded gaps: differential evolution, then L-BFGS-B.

    The population of differential evolution is popsize x 6; `maxiter` caps its generations.
    `on_generation(generation, best_rmse)` reports progress.
    """
    box = {**DEFAULT_BOUNDS, **(bounds or {})}
    limits = np.array([box[name] for name in PARAM_NAMES], dtype=float)
    batch = make_batch(segments, dt, window_s)
    started = time.monotonic()
    objective = _Objective(batch, acceleration_bounds)
    found, generations = _global_search(objective, limits, seed, maxiter, popsize, on_generation)
    refined = _local_refinement(objective, found.x, limits, local_maxiter)
    best = refined.x if refined.fun <= found.fun else found.x
    rmse, nrmse = _gap_errors(best, batch, acceleration_bounds)
    return CalibrationResult(
        params=_as_params(best),
        gap_rmse=rmse,
        gap_nrmse=nrmse,
        global_gap_rmse=float(found.fun),
        generations=generations,
        evaluations=objective.evaluations,
        seconds=time.monotonic() - started,
        segments=len(segments),
        windows=batch.windows,
        samples=batch.samples,
        bounds={
            name: (float(lo), float(hi)) for name, (lo, hi) in zip(PARAM_NAMES, limits, strict=True)
        },
        settings={
            "update": "ballistic",
            "dt": dt,
            "window_s": window_s,
            "acceleration_bounds": list(acceleration_bounds) if acceleration_bounds else None,
            "global": {
                "method": "scipy.optimize.differential_evolution",
                "seed": seed,
                "maxiter": maxiter,
                "popsize": popsize,
                "strategy": "best1bin",
            },
            "local": {"method": "L-BFGS-B", "maxiter": local_maxiter, "message": refined.message},
        },
    )


@dataclass
class _Objective:
    """The pooled gap RMSE of (S, 6) parameter matrices, counting the parameter sets run."""

    batch: SegmentBatch
    acceleration_bounds: tuple[float, float] | None
    evaluations: int = 0

    def __call__(self, matrix: np.ndarray) -> np.ndarray:
        self.evaluations += matrix.shape[0]
        return gap_rmse(matrix, self.batch, self.acceleration_bounds)


def _global_search(
    objective: _Objective,
    limits: np.ndarray,
    seed: int,
    maxiter: int,
    popsize: int,
    on_generation: Callable[[int, float], None] | None,
) -> tuple[Any, int]:
    """Seeded differential evolution over the box; returns its result and the generations run."""
    from scipy.optimize import differential_evolution

    generations = 0

    def progress(intermediate_result: Any) -> None:
        nonlocal generations
        generations += 1
        if on_generation is not None:
            on_generation(generations, float(intermediate_result.fun))

    found = differential_evolution(
        lambda population: objective(population.T),  # vectorised: (6, S) -> (S,)
        limits,
        seed=seed,
        maxiter=maxiter,
        popsize=popsize,
        tol=1e-3,
        polish=False,
        vectorized=True,
        updating="deferred",
        callback=progress,
    )
    return found, generations


def _local_refinement(
    objective: _Objective, start: np.ndarray, limits: np.ndarray, maxiter: int
) -> Any:
    """L-BFGS-B from `start` inside the box, its gradient from one vectorised simulation."""
    from scipy.optimize import minimize

    steps = 1e-6 * (limits[:, 1] - limits[:, 0])

    def value_and_gradient(x: np.ndarray) -> tuple[float, np.ndarray]:
        """Objective and its central-difference gradient (13 parameter sets at once)."""
        upper = np.minimum(x + np.diag(steps), limits[:, 1])
        lower = np.maximum(x - np.diag(steps), limits[:, 0])
        values = objective(np.vstack([x[None, :], upper, lower]))
        width = np.diag(upper) - np.diag(lower)
        gradient = (values[1 : 1 + len(x)] - values[1 + len(x) :]) / width
        return float(values[0]), gradient

    return minimize(
        value_and_gradient,
        start,
        jac=True,
        method="L-BFGS-B",
        bounds=limits,
        options={"maxiter": maxiter},
    )


def _gap_errors(
    best: np.ndarray, batch: SegmentBatch, acceleration_bounds: tuple[float, float] | None
) -> tuple[float, float]:
    """Gap RMSE (m) and NRMSE (relative to the recorded gaps) of one parameter vector."""
    sse, _ = simulate(best[None, :], batch, acceleration_bounds)
    recorded = float(np.square(np.where(batch.mask, batch.gap, 0.0)).sum())
    rmse = float(math.sqrt(sse[0] / batch.samples))
    return rmse, float(math.sqrt(sse[0] / recorded)) if recorded > 0 else math.nan


def calibration_document(
    result: CalibrationResult, data: Mapping[str, Any], versions: Mapping[str, str] | None = None
) -> dict[str, Any]:
    """The JSON of a calibration: ``params`` (IDMParams fields), fit, data, bounds, versions."""
    return {
        "params": result.params.to_dict(),
        "fit": {
            "objective": "RMSE of the simulated gap against the recorded gap, pooled (m)",
            "gap_rmse_m": result.gap_rmse,
            "gap_nrmse": result.gap_nrmse,
            "global_gap_rmse_m": result.global_gap_rmse,
            "at_bounds": result.at_bounds,
            "generations": result.generations,
            "evaluations": result.evaluations,
            "seconds": round(result.seconds, 2),
            **result.settings,
        },
        "data": {
            **data,
            "segments": result.segments,
            "windows": result.windows,
            "samples": result.samples,
        },
        "bounds": {name: list(pair) for name, pair in result.bounds.items()},
        "versions": dict(versions or {}),
    }
