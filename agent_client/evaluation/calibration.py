"""Calibrate IDM on the scenario's own traffic, recorded through the bridge (paper §4.4).

1. `record_segments` resets every episode with ``report_traffic=True`` and one decision per
   simulation step, so every observation carries `protocol.messages.Traffic`: each background
   vehicle's odometer, speed, lane, leader, net gap and leader speed. For every vehicle, the steps
   behind one leader within car-following range, in one lane and without a jump in time, are a
   `Segment` (with the follower's id and vehicle type). The ego is driven by the simulator
   (``ego_driver="sumo"``) so that it moves like the traffic around it; it is never a follower in
   the data, but the vehicles behind it are. (``source="ego"`` records that stand-in ego alone,
   for a server that cannot report its traffic.)
2. `choose_vehicle_type`: one IDM per vehicle type, by default the most frequent among followers.
3. `fit_idm` simulates an IDM follower against each recorded leader the way SUMO integrates its
   IDM (`sumo_idm_speed`, after ``MSCFModel_IDM::_v``): ``max(1, int(dt / stepping + 0.5))``
   internal iterations per step, the net gap (SUMO's gap minus minGap, to which its IDM adds
   minGap back: s0 is the type's minGap) and the position update the recording was made with,
   read off the odometers (SUMO's default Euler x += v' dt, or ballistic). Shared a, b, T, s0 and
   delta are fitted with a desired speed v0 per follower (SUMO draws one per vehicle: speedFactor
   x the lane's limit), each bounded below by the highest speed that follower ever drove (an IDM
   does not pass its v0: this bounds the delta-v0 trade-off from below). The objective is the
   pooled RMSE of the simulated gap. A seeded differential evolution on a subsample, with one
   pooled v0, finds the basin; Levenberg-Marquardt on all data frees every v0 (its Jacobian is one
   vectorised run: each follower's gaps depend on its own v0 only, so one perturbed simulation
   gives every v0's derivative, and the v0s are eliminated by a Schur complement).
4. How sure: `_bootstrap` resamples followers with replacement and refits each replicate from the
   optimum (Gauss-Newton steps with a line search): 90 % percentile intervals.
   `sensitivities` tells what the data cannot determine at all (a 10 % change that the other
   parameters compensate, e.g. traffic in one steady state); parameters at a bound of the search
   box and wide intervals are flagged too.

`calibration_document` gives the JSON that ``agent-client drive --policy idm:FILE`` reads.
"""

from __future__ import annotations

import bisect
import math
import time
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from agent_client.drivers.episode import Driver, Idle, run_episode
from agent_client.drivers.idm import IDMDriver, IDMParams
from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import UsageError
from protocol.messages import Observation, OptionValue

PARAM_NAMES = ("a", "b", "T", "s0", "v0", "delta")
"""The IDM parameters, in `IDMParams` order."""
SHARED_NAMES = ("a", "b", "T", "s0", "delta")
"""The parameters every follower of the calibrated type shares; v0 is each follower's own."""

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
driver is mostly driving at its own desired speed; such stretches tell little about T, s0 or b."""
MIN_SEGMENT_S = 10.0
"""Car-following stretches shorter than this (s) are dropped: too short to tell parameters."""
WINDOW_S = 60.0
"""Longer stretches are cut into windows of this length, each simulated from its recorded start."""

SUMO_IDM_STEPPING = 0.25
"""s: SUMO's default of the IDM's ``stepping`` (cfParam): its IDM takes
``max(1, int(step_length / stepping + 0.5))`` internal iterations per simulation step."""
NUMERICAL_EPS = 1e-3
"""SUMO's floor of the gap (m) and of v0 (m/s) in its IDM (``NUMERICAL_EPS``)."""
UPDATES = ("euler", "ballistic")
"""Position updates: SUMO's default (x += v' dt) and ``--step-method.ballistic``."""

SOURCES = ("traffic", "ego")
"""What is recorded: every background vehicle (``report_traffic``), or the simulator-driven ego."""
EGO_FOLLOWER = "ego"
"""Follower id and vehicle type of the segments recorded from the ego (``source="ego"``)."""

GLOBAL_SAMPLES = 60_000
"""Compared samples (at most) of the subsample differential evolution searches on."""
V0_MARGIN = 1.01
"""The global search's v0 of a follower: max(pooled v0, this x the follower's top speed)."""
V0_SENSITIVITY_M = 0.1
"""m: a follower's v0 counts as determined when changing it by 10 % moves its simulated gaps by
at least this much (RMS); the others never drove near their desired speed."""
BOOTSTRAP_REPLICATES = 100
"""Bootstrap replicates (followers resampled with replacement) of the intervals."""
BOOTSTRAP_STEPS = 2
"""Gauss-Newton steps of each replicate's refit from the optimum (the first one reuses the
optimum's Jacobian; each further one re-linearises at the replicate's own parameters)."""
UNDETERMINED_M = 1e-3
"""m: a parameter is flagged undetermined when a 10 % change of it, the others compensating,
moves the simulated gaps by less than this (RMS): `sensitivities`."""
INTERVAL_LEVEL = 0.90
"""Coverage of the reported percentile intervals."""
WIDE_INTERVAL = 0.25
"""An interval is flagged wide when its half-width exceeds this fraction of the estimate."""
_FD_STEP = 1e-6
"""Finite-difference step, relative to each parameter's search range."""
_SETS_PER_POINT = 13
"""Parameter sets per linearisation: the point, +/- each shared parameter, +/- every v0 at once."""
_CHUNK_POINTS = 20
"""Linearisation points simulated together (bounds the memory of the bootstrap)."""


# --------------------------------------------------------------------------- recording


@dataclass(frozen=True, eq=False)
class Segment:
    """One follower behind one leader, sampled every simulation step."""

    seed: int
    follower_id: str
    vehicle_type: str
    leader_id: str
    time: np.ndarray
    speed: np.ndarray
    acceleration: np.ndarray
    gap: np.ndarray
    """Net gap, bumper to bumper (m): SUMO's leader distance plus the follower's minGap."""
    leader_speed: np.ndarray
    position: np.ndarray
    """The follower's odometer (m)."""
    max_speed: float
    """The follower's highest speed over every step recorded of it, following or not."""

    def __len__(self) -> int:
        return len(self.time)

    @property
    def follower(self) -> tuple[int, str]:
        """Who drove it: (episode seed, vehicle id); ids repeat across episodes."""
        return (self.seed, self.follower_id)

    @property
    def duration(self) -> float:
        return float(self.time[-1] - self.time[0]) if len(self.time) else 0.0

    @property
    def leader_position(self) -> np.ndarray:
        """Position of the leader's rear on the follower's odometer (m)."""
        return self.position + self.gap


def _in_range(gap: np.ndarray, speed: np.ndarray) -> np.ndarray:
    """A leader close enough for car following: 0 < gap <= max(20 m, 3 s x speed)."""
    return (gap > 0.0) & (gap <= np.maximum(FOLLOWING_GAP_M, FOLLOWING_HEADWAY_S * speed))


def segments_from_traffic(
    observations: Sequence[Observation],
    seed: int,
    step_length: float,
    min_duration: float = MIN_SEGMENT_S,
) -> list[Segment]:
    """Every background vehicle's car-following segments in one episode's observations.

    A segment is a run of steps with a leader in range, the same leader, the same lane and no jump
    in time (a vehicle that left and came back); runs shorter than `min_duration` are dropped.
    """
    columns = _traffic_columns(observations)
    return [] if columns is None else _segments_of_columns(columns, seed, step_length, min_duration)


def _segments_of_columns(
    columns: dict[str, np.ndarray], seed: int, step_length: float, min_duration: float
) -> list[Segment]:
    """Segments of traffic-shaped columns (one row per vehicle and step, any order)."""
    ids = columns["id"]
    order = np.lexsort((columns["time"], ids))  # by vehicle, then time
    c = {name: values[order] for name, values in columns.items()}
    same_vehicle = np.r_[False, c["id"][1:] == c["id"][:-1]]
    following = (c["leader"] != "") & _in_range(c["gap"], c["speed"])
    continues = (
        same_vehicle
        & np.r_[False, following[:-1]]
        & np.r_[False, c["leader"][1:] == c["leader"][:-1]]
        & np.r_[False, c["lane"][1:] == c["lane"][:-1]]
        & np.r_[False, np.diff(c["time"]) <= 1.5 * step_length]
    )
    vehicle_starts = np.flatnonzero(~same_vehicle)
    top = np.maximum.reduceat(c["speed"], vehicle_starts)
    max_speed = top[np.cumsum(~same_vehicle) - 1]
    starts = np.flatnonzero(following & ~continues)
    stops = np.append(starts[1:], len(following))
    segments = []
    for start, stop in zip(starts, stops, strict=True):
        stop = start + int(np.argmin(np.append(following[start:stop], False)))  # end of the run
        if stop - start < 2 or c["time"][stop - 1] - c["time"][start] < min_duration - 1e-9:
            continue
        part = slice(start, stop)
        segments.append(
            Segment(
                seed=seed,
                follower_id=str(c["id"][start]),
                vehicle_type=str(c["vehicle_type"][start]),
                leader_id=str(c["leader"][start]),
                time=c["time"][part],
                speed=c["speed"][part],
                acceleration=c["acceleration"][part],
                gap=c["gap"][part],
                leader_speed=c["leader_speed"][part],
                position=c["position"][part],
                max_speed=float(max_speed[start]),
            )
        )
    return segments


def _traffic_columns(observations: Sequence[Observation]) -> dict[str, np.ndarray] | None:
    """The traffic of every observation as flat columns (one row per vehicle and step)."""
    names = ("id", "vehicle_type", "lane", "position", "speed", "acceleration", "leader", "gap")
    lists: dict[str, list[Any]] = {name: [] for name in (*names, "leader_speed", "time")}
    for obs in observations:
        traffic = obs.traffic
        if traffic is None:
            continue
        for name in (*names, "leader_speed"):
            lists[name].extend(getattr(traffic, name))
        lists["time"].extend([obs.time] * len(traffic))
    if not lists["id"]:
        return None
    columns = {name: np.asarray(values) for name, values in lists.items()}
    for name in ("position", "speed", "acceleration", "gap", "leader_speed", "time"):
        columns[name] = columns[name].astype(float)
    return columns


def segments_from_observations(
    observations: Sequence[Observation],
    seed: int,
    step_length: float,
    min_duration: float = MIN_SEGMENT_S,
) -> list[Segment]:
    """The ego's own car-following segments (``source="ego"``: a simulator-driven ego)."""
    observations = [o for o in observations if not (o.events.collision or o.events.teleported)]
    if not observations:
        return []
    leader = [o.neighbours.leader for o in observations]
    columns = {
        "time": np.array([o.time for o in observations]),
        "speed": np.array([o.ego.speed for o in observations]),
        "acceleration": np.array([o.ego.acceleration for o in observations]),
        "gap": np.array([n.gap if n.present else math.inf for n in leader]),
        "leader_speed": np.array([n.speed for n in leader]),
        "position": np.array([o.ego.position for o in observations]),
        "leader": np.array([n.id if n.present else "" for n in leader]),
    }
    count = len(observations)
    as_traffic = {
        **columns,
        "id": np.full(count, EGO_FOLLOWER),
        "vehicle_type": np.full(count, EGO_FOLLOWER),
        "lane": np.array([o.ego.lane for o in observations]),
    }
    return _segments_of_columns(as_traffic, seed, step_length, min_duration)


def record_segments(
    env: RemoteEnv,
    seeds: Iterable[int],
    min_duration: float = MIN_SEGMENT_S,
    on_episode: Callable[[int, list[Segment], int], None] | None = None,
    *,
    source: str = "traffic",
) -> list[Segment]:
    """Record car following through a `RemoteEnv`, one decision per simulation step.

    ``source="traffic"`` (the default) records every background vehicle (reset option
    ``report_traffic``); ``"ego"`` the ego driven by the simulator's own model. `on_episode(seed,
    segments, steps)` is called after each episode (progress).
    """
    step_length = env.step_length
    assert step_length is not None  # RemoteEnv knows it once connected
    options, driver = recording_options(env, source)
    extract = segments_from_traffic if source == "traffic" else segments_from_observations
    segments: list[Segment] = []
    for seed in seeds:
        observations = run_episode(env, driver, seed, options=options).observations
        if source == "traffic" and observations[0].traffic is None:
            raise UsageError(
                f"the server ignored report_traffic on scenario {env.scenario}: its observations "
                "carry no traffic (docs/protocol.md §4)"
            )
        found = extract(observations, seed, step_length, min_duration)
        segments.extend(found)
        if on_episode is not None:
            on_episode(seed, found, len(observations) - 1)
    return segments


def recording_options(env: RemoteEnv, source: str) -> tuple[dict[str, OptionValue], Driver]:
    """The reset options and the ego's driver of a recording, or a `UsageError` naming what the
    scenario lacks."""
    offered = env.scenario_options
    if source not in SOURCES:
        raise UsageError(f"unknown source {source!r}: one of {', '.join(SOURCES)}")
    options: dict[str, OptionValue] = {}
    if source == "traffic":
        if "report_traffic" not in offered:
            raise UsageError(
                f"scenario {env.scenario} does not offer report_traffic: calibrate-idm records the "
                "scenario's own traffic (docs/protocol.md §6); --source ego records the "
                "simulator-driven ego instead"
            )
        options["report_traffic"] = True
    elif "ego_driver" not in offered:
        raise UsageError(
            f"scenario {env.scenario} has no ego_driver option: --source ego records the "
            "simulator's own driver (docs/protocol.md §2.3)"
        )
    for name, value in (("decision_interval", env.step_length), ("report_ceiling", False)):
        if name in offered and value is not None:  # without it a scenario decides every step
            options[name] = value
    if "ego_driver" in offered:
        options["ego_driver"] = "sumo"  # the ego drives like traffic; its actions are ignored
        return options, Idle()
    return options, IDMDriver()  # an ego that keeps moving with the traffic


@dataclass(frozen=True)
class TypeSummary:
    """How much car following one vehicle type contributed."""

    followers: int
    segments: int
    seconds: float


def types_seen(segments: Iterable[Segment]) -> dict[str, TypeSummary]:
    """Vehicle types among the followers, the most frequent first."""
    followers: dict[str, set[tuple[int, str]]] = {}
    count: Counter[str] = Counter()
    seconds: dict[str, float] = {}
    for segment in segments:
        followers.setdefault(segment.vehicle_type, set()).add(segment.follower)
        count[segment.vehicle_type] += 1
        seconds[segment.vehicle_type] = seconds.get(segment.vehicle_type, 0.0) + segment.duration
    ranked = sorted(followers, key=lambda t: (-len(followers[t]), -seconds[t], t))
    return {t: TypeSummary(len(followers[t]), count[t], round(seconds[t], 1)) for t in ranked}


def choose_vehicle_type(segments: Sequence[Segment], requested: str | None = None) -> str:
    """The type to calibrate: `requested`, or the most frequent among followers."""
    seen = types_seen(segments)
    if not seen:
        raise UsageError("no car-following segments were recorded: record more or longer episodes")
    if requested is None:
        return next(iter(seen))
    if requested not in seen:
        raise UsageError(
            f"vehicle type {requested!r} never followed a leader here; types seen: "
            + ", ".join(f"{t} ({s.followers} followers)" for t, s in seen.items())
        )
    return requested


# --------------------------------------------------------------------------- simulation


def sumo_iterations(dt: float, stepping: float = SUMO_IDM_STEPPING) -> int:
    """Internal iterations of SUMO's IDM per simulation step (``MSCFModel_IDM::myIterations``)."""
    return max(1, int(dt / stepping + 0.5))


def sumo_idm_speed(
    speed: np.ndarray,
    gap: np.ndarray,
    leader_speed: np.ndarray,
    params: Sequence[np.ndarray],
    dt: float,
    iterations: int,
) -> np.ndarray:
    """The speed after one simulation step, as SUMO's IDM computes it (``MSCFModel_IDM::_v``).

    `params` are a, b, T, s0, delta, v0 (broadcastable arrays) and `gap` is the net gap (SUMO's
    gap minus minGap, plus minGap again: s0 is the type's minGap). Each iteration applies the
    IDM acceleration for dt / iterations; the gap then shrinks by what the follower closed in
    (never grows: SUMO keeps the leader's speed and ignores a receding leader within a step).
    """
    a, b, T, s0, delta, v0 = params
    two_sqrt_ab = 2.0 * np.sqrt(a * b)
    v0 = np.maximum(v0, NUMERICAL_EPS)
    h = dt / iterations
    for i in range(iterations):
        desired = s0 + np.maximum(0.0, speed * T + speed * (speed - leader_speed) / two_sqrt_ab)
        gap = np.maximum(gap, NUMERICAL_EPS)
        acc = a * (1.0 - (speed / v0) ** delta - (desired / gap) ** 2)
        speed = np.maximum(0.0, speed + acc * h)
        if i < iterations - 1:
            gap = gap - np.maximum(0.0, (speed - leader_speed) * h)
    return speed


def detect_update(segments: Sequence[Segment], dt: float) -> str:
    """The position update the recording was made with, read off the odometers: ``"euler"``
    when x advances by v' dt (SUMO's default), ``"ballistic"`` when by (v + v') dt / 2."""
    euler, ballistic = [], []
    for segment in segments:
        moved = np.diff(segment.position)
        euler.append(np.abs(moved - segment.speed[1:] * dt))
        ballistic.append(np.abs(moved - 0.5 * (segment.speed[1:] + segment.speed[:-1]) * dt))
    if not euler:
        return "euler"
    return (
        "euler"
        if np.median(np.concatenate(euler)) <= np.median(np.concatenate(ballistic))
        else "ballistic"
    )


@dataclass(frozen=True, eq=False)
class SegmentBatch:
    """Segments cut into windows, packed end to end into rows of (steps, rows) arrays.

    Each window starts from its recorded state (speed, position) and is simulated against its
    recorded leader; windows are numbered follower by follower (`window_follower` is sorted), so
    per-follower sums are ``np.add.reduceat(..., follower_windows)``.
    """

    dt: float
    leader_position: np.ndarray
    """(steps, rows): the leader's rear on the follower's odometer, relative to the window start."""
    leader_speed: np.ndarray
    position: np.ndarray
    """(steps, rows): the recorded follower position, relative to the window start."""
    gap: np.ndarray
    mask: np.ndarray
    """True where a recorded sample is compared (never a window's first, its initial state)."""
    starts: dict[int, tuple[np.ndarray, np.ndarray]]
    """Step -> (rows, windows) starting there."""
    ends: dict[int, tuple[np.ndarray, np.ndarray]]
    """Step -> (rows, windows) whose last compared sample is there."""
    speed0: np.ndarray
    """(windows,): the recorded speed at each window's start."""
    window_follower: np.ndarray
    """(windows,): index of each window's follower in `followers`."""
    followers: tuple[tuple[int, str], ...]
    max_speed: np.ndarray
    """(followers,): each follower's top speed (the lower bound of its v0)."""
    follower_windows: np.ndarray
    """Index of each follower's first window."""
    window_samples: np.ndarray

    @property
    def windows(self) -> int:
        return len(self.speed0)

    @property
    def samples(self) -> int:
        return int(self.mask.sum())

    def follower_samples(self) -> np.ndarray:
        """Compared samples per follower."""
        return np.add.reduceat(self.window_samples, self.follower_windows)


_Piece = tuple[Segment, int, int]


def _pieces(segments: Sequence[Segment], dt: float, window_s: float) -> list[_Piece]:
    """Every segment cut into windows of at most `window_s` that share their end samples."""
    steps = max(2, round(window_s / dt) + 1)
    pieces: list[_Piece] = []
    for segment in segments:
        start = 0
        while len(segment) - start >= 2:
            stop = min(start + steps, len(segment))
            pieces.append((segment, start, stop))
            if stop == len(segment):
                break
            start = stop - 1  # the next window starts where this one ended
    return pieces


def make_batch(
    segments: Sequence[Segment],
    dt: float,
    window_s: float = WINDOW_S,
    pieces: Sequence[_Piece] | None = None,
) -> SegmentBatch:
    """Cut segments into windows and pack them (first fit by decreasing length) into rows."""
    pieces = list(pieces) if pieces is not None else _pieces(segments, dt, window_s)
    if not pieces:
        raise ValueError("no car-following segments to fit on")
    followers = sorted({segment.follower for segment, _, _ in pieces})
    index = {who: i for i, who in enumerate(followers)}
    pieces.sort(key=lambda p: (index[p[0].follower], p[0].time[p[1]]))
    length = max(stop - start for _, start, stop in pieces)
    rows, offsets = _pack([stop - start for _, start, stop in pieces], length)
    shape = (length, int(rows.max()) + 1)
    arrays = {
        name: np.zeros(shape) for name in ("leader_position", "leader_speed", "position", "gap")
    }
    mask = np.zeros(shape, dtype=bool)
    starts: dict[int, list[tuple[int, int]]] = {}
    ends: dict[int, list[tuple[int, int]]] = {}
    for window, ((segment, start, stop), row, offset) in enumerate(
        zip(pieces, rows, offsets, strict=True)
    ):
        n, origin = stop - start, segment.position[start]
        part = slice(offset, offset + n)
        arrays["leader_position"][part, row] = segment.leader_position[start:stop] - origin
        arrays["leader_speed"][part, row] = segment.leader_speed[start:stop]
        arrays["position"][part, row] = segment.position[start:stop] - origin
        arrays["gap"][part, row] = segment.gap[start:stop]
        mask[offset + 1 : offset + n, row] = True
        starts.setdefault(int(offset), []).append((int(row), window))
        ends.setdefault(int(offset + n - 1), []).append((int(row), window))
    _hold_padding(arrays, mask)
    window_follower = np.array([index[segment.follower] for segment, _, _ in pieces])
    top = {segment.follower: segment.max_speed for segment, _, _ in pieces}
    return SegmentBatch(
        dt=dt,
        mask=mask,
        starts=_grouped(starts),
        ends=_grouped(ends),
        speed0=np.array([segment.speed[start] for segment, start, _ in pieces]),
        window_follower=window_follower,
        followers=tuple(followers),
        max_speed=np.array([top[who] for who in followers], dtype=float),
        follower_windows=np.flatnonzero(np.r_[True, np.diff(window_follower) != 0]),
        window_samples=np.array([stop - start - 1 for _, start, stop in pieces]),
        **arrays,
    )


def _pack(lengths: Sequence[int], capacity: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and offset of each window: first fit by decreasing length, the rows `capacity` long."""
    rows, offsets = np.zeros(len(lengths), dtype=int), np.zeros(len(lengths), dtype=int)
    free: list[tuple[int, int]] = []  # (room left, row), sorted
    used = 0
    for window in sorted(range(len(lengths)), key=lambda w: -lengths[w]):
        n = lengths[window]
        at = bisect.bisect_left(free, (n, -1))
        if at < len(free):
            room, row = free.pop(at)
        else:
            room, row, used = capacity, used, used + 1
        rows[window], offsets[window] = row, capacity - room
        if room - n >= 2:
            bisect.insort(free, (room - n, row))
    return rows, offsets


def _hold_padding(arrays: dict[str, np.ndarray], mask: np.ndarray) -> None:
    """After a row's last window, hold its last values (never compared: masked out)."""
    for row in range(mask.shape[1]):
        used = np.flatnonzero(mask[:, row])
        last = int(used[-1]) if len(used) else 0
        for values in arrays.values():
            values[last + 1 :, row] = values[last, row]


def _grouped(events: dict[int, list[tuple[int, int]]]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    return {
        k: (np.array([r for r, _ in v]), np.array([w for _, w in v])) for k, v in events.items()
    }


Quantities = Callable[[np.ndarray], np.ndarray]
"""Per-step accumulation: the masked gap errors (sets, rows) -> quantities (Q, rows)."""


@dataclass(frozen=True)
class Model:
    """How the fit simulates a follower: SUMO's IDM stepping and position update."""

    dt: float
    update: str = "euler"
    iterations: int = 1

    def __post_init__(self) -> None:
        if self.update not in UPDATES:
            raise ValueError(f"update must be one of {', '.join(UPDATES)}, got {self.update!r}")


def simulate(
    theta: np.ndarray,
    v0: np.ndarray,
    batch: SegmentBatch,
    model: Model,
    quantities: Quantities | None = None,
    keep_gaps: bool = False,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Run IDM followers for S parameter sets on every window at once.

    `theta` is (S, 5) in `SHARED_NAMES` order, `v0` (S, followers). Returns, per window, the
    quantities accumulated over its compared samples (Q, windows), by default the sum of squared
    gap errors of each set (S, windows); with `keep_gaps` also the simulated gaps (S, steps, rows).
    """
    theta, v0 = np.atleast_2d(theta), np.atleast_2d(v0)
    count = theta.shape[0]
    steps, rows = batch.gap.shape
    a, b, T, s0, delta = (theta[:, i, None] for i in range(len(SHARED_NAMES)))
    measure = quantities or np.square
    speed, x = np.zeros((count, rows)), np.zeros((count, rows))
    v0_now = np.ones((count, rows))
    running: np.ndarray | None = None
    per_window: np.ndarray | None = None
    gaps = np.empty((count, steps, rows)) if keep_gaps else None
    for k in range(steps):
        if k in batch.starts:
            at, windows = batch.starts[k]
            speed[:, at] = batch.speed0[windows]
            x[:, at] = batch.position[k, at]
            v0_now[:, at] = v0[:, batch.window_follower[windows]]
        if gaps is not None:
            gaps[:, k] = batch.leader_position[k] - x
        if k == steps - 1:
            break
        gap = batch.leader_position[k] - x
        new_speed = sumo_idm_speed(
            speed,
            gap,
            batch.leader_speed[k],
            (a, b, T, s0, delta, v0_now),
            model.dt,
            model.iterations,
        )
        x += (
            new_speed * model.dt
            if model.update == "euler"
            else 0.5 * (speed + new_speed) * model.dt
        )
        speed = new_speed
        error = (batch.position[k + 1] - x) * batch.mask[k + 1]  # = simulated gap - recorded gap
        values = measure(error)
        if running is None:
            running = np.zeros_like(values)
            per_window = np.zeros((values.shape[0], batch.windows))
        running += values
        if k + 1 in batch.ends:
            at, windows = batch.ends[k + 1]
            assert per_window is not None
            per_window[:, windows] = running[:, at]
            running[:, at] = 0.0
    assert per_window is not None
    return per_window, gaps


def follower_sums(per_window: np.ndarray, batch: SegmentBatch) -> np.ndarray:
    """Per-window quantities (..., windows) summed per follower (..., followers)."""
    return np.add.reduceat(per_window, batch.follower_windows, axis=-1)


# --------------------------------------------------------------------------- linearisation

_UPPER = np.triu_indices(6)
"""The 21 products of the 6 derivative columns (5 shared parameters and the follower's v0)."""
_QUANTITIES = 1 + 6 + len(_UPPER[0])
"""Per linearisation point and step: e^2, 6 derivative x e, 21 derivative products."""


@dataclass(frozen=True)
class Limits:
    """The search box: shared parameters (5, 2) and each follower's v0 (followers, 2)."""

    shared: np.ndarray
    v0: np.ndarray

    @classmethod
    def of(cls, box: Mapping[str, tuple[float, float]], max_speed: np.ndarray) -> Limits:
        """`box` for the shared parameters; each v0 from its follower's top speed to the top."""
        shared = np.array([box[name] for name in SHARED_NAMES], dtype=float)
        low, high = box["v0"]
        v0 = np.column_stack([np.clip(max_speed, low, high), np.full(len(max_speed), high)])
        return cls(shared, v0)

    def clip(self, theta: np.ndarray, v0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (
            np.clip(theta, self.shared[:, 0], self.shared[:, 1]),
            np.clip(v0, self.v0[:, 0], self.v0[:, 1]),
        )


@dataclass(frozen=True)
class Linearisation:
    """Gauss-Newton sums per point and follower at P points: J'J blocks, J'e and e'e.

    The Jacobian has the 5 shared columns and one v0 column per follower, which only that
    follower's samples depend on: `A` (P, F, 5, 5) is J_shared'J_shared over follower f's
    samples, `c` (P, F, 5) J_shared'J_v0, `d` (P, F) J_v0'J_v0, `g` (P, F, 5) and `gu` (P, F)
    J'e, `sse` (P, F) e'e.
    """

    A: np.ndarray
    c: np.ndarray
    d: np.ndarray
    g: np.ndarray
    gu: np.ndarray
    sse: np.ndarray

    def broadcast(self, points: int) -> Linearisation:
        """The same (single-point) linearisation at `points` points."""
        names = ("A", "c", "d", "g", "gu", "sse")
        arrays = (getattr(self, n) for n in names)
        return Linearisation(*(np.broadcast_to(x, (points, *x.shape[1:])) for x in arrays))


def _derivative_products(error: np.ndarray) -> np.ndarray:
    """Per-step quantities of a linearisation: the errors of P x 13 sets -> (P x 28, rows)."""
    e = error.reshape(-1, _SETS_PER_POINT, error.shape[-1])
    e0 = e[:, 0]
    derivative = np.concatenate([e[:, 1:6] - e[:, 6:11], (e[:, 11] - e[:, 12])[:, None]], axis=1)
    products = derivative[:, _UPPER[0]] * derivative[:, _UPPER[1]]
    stacked = np.concatenate([(e0 * e0)[:, None], derivative * e0[:, None], products], axis=1)
    return stacked.reshape(-1, error.shape[-1])


def linearise(
    theta: np.ndarray, v0: np.ndarray, batch: SegmentBatch, model: Model, limits: Limits
) -> Linearisation:
    """Central differences at P points (theta (P, 5), v0 (P, F)) from one simulation of 13 sets
    each: the point, each shared parameter up and down, and every v0 up and down at once."""
    theta, v0 = np.atleast_2d(theta), np.atleast_2d(v0)
    points = theta.shape[0]
    step = _FD_STEP * (limits.shared[:, 1] - limits.shared[:, 0])
    v0_step = _FD_STEP * float(limits.v0[:, 1].max())
    up = np.minimum(theta[:, None, :] + np.diag(step), limits.shared[:, 1])  # (P, 5, 5)
    down = np.maximum(theta[:, None, :] - np.diag(step), limits.shared[:, 0])
    v0_up = np.minimum(v0 + v0_step, limits.v0[:, 1])
    v0_down = np.maximum(v0 - v0_step, limits.v0[:, 0])
    sets_theta = np.concatenate([theta[:, None], up, down, theta[:, None], theta[:, None]], axis=1)
    same = np.repeat(v0[:, None], 11, axis=1)
    sets_v0 = np.concatenate([same, v0_up[:, None], v0_down[:, None]], axis=1)
    per_window, _ = simulate(
        sets_theta.reshape(-1, len(SHARED_NAMES)),
        sets_v0.reshape(points * _SETS_PER_POINT, -1),
        batch,
        model,
        quantities=_derivative_products,
    )
    sums = follower_sums(per_window, batch).reshape(points, _QUANTITIES, -1)  # (P, 28, F)
    width = np.diagonal(up - down, axis1=1, axis2=2)  # (P, 5)
    v0_width = np.maximum(v0_up - v0_down, 1e-300)  # (P, F); 0 only if the box is a point
    scale = np.concatenate(
        [np.broadcast_to(width[:, :, None], (points, 5, v0.shape[1])), v0_width[:, None]], axis=1
    )  # (P, 6, F)
    derivative_e = sums[:, 1:7] / scale
    full = np.zeros((points, 6, 6, v0.shape[1]))
    full[:, _UPPER[0], _UPPER[1]] = sums[:, 7:]
    full[:, _UPPER[1], _UPPER[0]] = sums[:, 7:]
    full /= scale[:, :, None] * scale[:, None, :]
    return Linearisation(
        A=np.moveaxis(full[:, :5, :5], -1, 1),
        c=np.moveaxis(full[:, :5, 5], -1, 1),
        d=full[:, 5, 5],
        g=np.moveaxis(derivative_e[:, :5], -1, 1),
        gu=derivative_e[:, 5],
        sse=sums[:, 0],
    )


def gauss_newton_step(
    lin: Linearisation,
    weights: np.ndarray,
    damping: np.ndarray,
    theta: np.ndarray,
    v0: np.ndarray,
    limits: Limits,
) -> tuple[np.ndarray, np.ndarray]:
    """The Levenberg-Marquardt step (shared (P, 5), v0 (P, F)) of the follower-weighted least
    squares at P points (theta (P, 5), v0 (P, F)).

    Each follower's v0 is eliminated by its Schur complement, so the system solved is 5 x 5
    whatever the number of followers. A parameter on a bound of the box whose gradient points
    out of it is held there (an active set), so that the others still move as they should.
    """
    w = weights
    A = np.einsum("pf,pfij->pij", w, lin.A)
    g = np.einsum("pf,pfi->pi", w, lin.g)
    c, d, gu = w[..., None] * lin.c, w * lin.d, w * lin.gu
    held = _held(theta, g, limits.shared)  # (P, 5)
    held_v0 = _held(v0, gu, limits.v0)  # (P, F)
    c = np.where(held_v0[..., None] | held[:, None, :], 0.0, c)
    gu = np.where(held_v0, 0.0, gu)
    diagonal = np.diagonal(A, axis1=1, axis2=2)
    floor = 1e-12 * np.maximum(diagonal.max(axis=1), d.max(axis=1)) + 1e-300  # (P,)
    lam = damping[:, None]
    A = A + np.eye(5) * (lam * np.maximum(diagonal, floor[:, None]))[:, None, :]
    d_damped = d + lam * np.maximum(d, floor[:, None])
    H = A - np.einsum("pfi,pfj->pij", c / d_damped[..., None], c)
    r = g - np.einsum("pfi,pf->pi", c, gu / d_damped)
    free = ~held
    H = np.where(free[:, :, None] & free[:, None, :], H, 0.0) + np.eye(5) * held[:, None, :]
    r = np.where(free, r, 0.0)
    shared = -np.einsum("pij,pj->pi", np.linalg.pinv(H, rcond=1e-13), r)
    step_v0 = -(gu + np.einsum("pfi,pi->pf", c, shared)) / d_damped
    return shared, np.where(held_v0, 0.0, step_v0)


def _held(values: np.ndarray, gradient: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Parameters on a bound whose descent direction (-gradient) leads out of the box."""
    span = box[..., 1] - box[..., 0]
    low = (values <= box[..., 0] + 1e-9 * span) & (gradient > 0.0)
    high = (values >= box[..., 1] - 1e-9 * span) & (gradient < 0.0)
    return low | high


def _weighted_sse(
    theta: np.ndarray,
    v0: np.ndarray,
    weights: np.ndarray,
    batch: SegmentBatch,
    model: Model,
) -> np.ndarray:
    """Follower-weighted SSE of P parameter points (P,)."""
    per_window, _ = simulate(theta, v0, batch, model)
    return (follower_sums(per_window, batch) * weights).sum(axis=1)


# --------------------------------------------------------------------------- fitting


@dataclass(frozen=True)
class FollowerV0:
    """One follower's fitted desired speed."""

    seed: int
    id: str
    v0: float
    max_speed: float
    determined: bool
    """Whether its gaps tell its v0 (`V0_SENSITIVITY_M`); else it never drove near it."""


@dataclass
class CalibrationResult:
    """Fitted parameters, how sure the fit is of them, and what it cost."""

    params: IDMParams
    """Shared a, b, T, s0, delta; v0 the median of the determined followers' own v0."""
    gap_rmse: float
    """Pooled RMSE of the simulated gap (m): the objective."""
    gap_nrmse: float
    """sqrt(sum err^2 / sum gap^2): the same error relative to the recorded gaps."""
    global_gap_rmse: float
    """The objective (on all data) at the global search's result, before the refinement."""
    generations: int
    evaluations: int
    """Parameter sets simulated, over all stages."""
    seconds: float
    segments: int
    windows: int
    samples: int
    bounds: dict[str, tuple[float, float]]
    intervals: dict[str, tuple[float, float]] = field(default_factory=dict)
    """90 % bootstrap intervals (followers resampled) of every parameter in `params`."""
    v0_followers: list[FollowerV0] = field(default_factory=list)
    sensitivity: dict[str, float] = field(default_factory=dict)
    """Per parameter: the RMS gap change (m) of a 10 % change, the others compensating."""
    settings: dict[str, Any] = field(default_factory=dict)

    @property
    def followers(self) -> int:
        return len(self.v0_followers)

    @property
    def at_bounds(self) -> list[str]:
        """Parameters within 0.5 % of the search range from a bound (poorly determined)."""
        found = []
        for name, (low, high) in self.bounds.items():
            value = getattr(self.params, name)
            if value is not None and min(value - low, high - value) <= 0.005 * (high - low):
                found.append(name)
        return found

    @property
    def undetermined(self) -> list[str]:
        """Parameters the data cannot tell: those whose `sensitivity` is below `UNDETERMINED_M`,
        and v0 when no follower drove near its desired speed."""
        found = [name for name, value in self.sensitivity.items() if value < UNDETERMINED_M]
        if self.v0_followers and not any(f.determined for f in self.v0_followers):
            found = [*found, "v0"] if "v0" not in found else found
        return found

    @property
    def wide(self) -> list[str]:
        """Parameters whose interval's half-width exceeds `WIDE_INTERVAL` of their value."""
        found = []
        for name, (low, high) in self.intervals.items():
            value = getattr(self.params, name)
            if value is not None and (high - low) / 2 > WIDE_INTERVAL * abs(value):
                found.append(name)
        return found


def _as_params(theta: np.ndarray, v0: float) -> IDMParams:
    values = dict(zip(SHARED_NAMES, (float(x) for x in theta), strict=True))
    return IDMParams(v0=float(v0), **values)


@dataclass
class _Counter:
    """Parameter sets simulated (the fit's work)."""

    sets: int = 0

    def add(self, count: int) -> None:
        self.sets += count


def fit_idm(
    segments: Sequence[Segment],
    dt: float,
    *,
    bounds: Mapping[str, tuple[float, float]] | None = None,
    seed: int = 0,
    maxiter: int = 40,
    popsize: int = 10,
    window_s: float = WINDOW_S,
    update: str = "auto",
    stepping: float = SUMO_IDM_STEPPING,
    local_maxiter: int = 50,
    replicates: int = BOOTSTRAP_REPLICATES,
    bootstrap_steps: int = BOOTSTRAP_STEPS,
    global_samples: int = GLOBAL_SAMPLES,
    on_generation: Callable[[int, float], None] | None = None,
    on_stage: Callable[[str], None] | None = None,
) -> CalibrationResult:
    """Fit IDM to recorded gaps: shared a, b, T, s0, delta and each follower's own v0.

    Differential evolution (a population of popsize x 6, at most `maxiter` generations) on a
    subsample of at most `global_samples` compared samples with one pooled v0, then
    Levenberg-Marquardt on all data with a v0 per follower, then `replicates` bootstrap refits.
    `update` is ``"euler"``, ``"ballistic"`` or ``"auto"`` (read off the odometers); `stepping`
    is the IDM's SUMO cfParam. `on_generation(generation, best_rmse)` and `on_stage(message)`
    report progress.
    """
    started = time.monotonic()
    box = {**DEFAULT_BOUNDS, **(bounds or {})}
    chosen = detect_update(segments, dt) if update == "auto" else update
    model = Model(dt, chosen, sumo_iterations(dt, stepping))
    pieces = _pieces(segments, dt, window_s)
    batch = make_batch(segments, dt, window_s, pieces)
    limits = Limits.of(box, batch.max_speed)
    work = _Counter()
    sub = _subsample(pieces, dt, batch.samples, global_samples, seed)
    found, generations = _global_search(
        sub, model, box, seed, maxiter, popsize, work, on_generation
    )
    theta, v0 = found[:5], _pooled_v0(found[5], batch.max_speed, limits)
    start_sse = float(_weighted_sse(theta, v0, np.ones((1, len(v0))), batch, model)[0])
    work.add(1)
    if on_stage is not None:
        on_stage(
            f"refining on all {batch.samples} samples with a v0 for each of "
            f"{len(batch.followers)} followers (Levenberg-Marquardt)"
        )
    theta, v0, lin, local = _refine(theta, v0, batch, model, limits, local_maxiter, work)
    typical = _determined(lin, v0, batch)
    if on_stage is not None and replicates > 0:
        on_stage(f"bootstrap: {replicates} replicates of the followers, refitted from the optimum")
    intervals = _bootstrap(
        theta, v0, lin, typical, batch, model, limits, replicates, bootstrap_steps, seed, work
    )
    sse = float(lin.sse[0].sum())
    recorded = float(np.square(batch.gap[batch.mask]).sum())
    return CalibrationResult(
        params=_as_params(theta, _weighted_median(v0, _median_weights(typical))),
        gap_rmse=math.sqrt(sse / batch.samples),
        gap_nrmse=math.sqrt(sse / recorded) if recorded > 0 else math.nan,
        global_gap_rmse=math.sqrt(start_sse / batch.samples),
        generations=generations,
        evaluations=work.sets,
        seconds=time.monotonic() - started,
        segments=len(segments),
        windows=batch.windows,
        samples=batch.samples,
        bounds={name: (float(lo), float(hi)) for name, (lo, hi) in box.items()},
        intervals=intervals,
        sensitivity=sensitivities(lin, theta, v0, batch.samples),
        v0_followers=[
            FollowerV0(s, i, float(v), float(top), bool(ok))
            for (s, i), v, top, ok in zip(
                batch.followers, v0, batch.max_speed, typical, strict=True
            )
        ],
        settings={
            "update": chosen,
            "iterations_per_step": model.iterations,
            "stepping": stepping,
            "dt": dt,
            "window_s": window_s,
            "global": {
                "method": "scipy.optimize.differential_evolution",
                "seed": seed,
                "maxiter": maxiter,
                "popsize": popsize,
                "strategy": "best1bin",
                "samples": sub.samples,
                "v0": f"pooled: max(v0, {V0_MARGIN} x each follower's top speed)",
            },
            "local": {"method": "Levenberg-Marquardt", "maxiter": local_maxiter, **local},
            "bootstrap": {
                "replicates": replicates,
                "resampled": "followers, with replacement",
                "refit": f"{bootstrap_steps} Gauss-Newton steps from the optimum",
                "level": INTERVAL_LEVEL,
                "seed": seed,
            },
        },
    )


def _subsample(
    pieces: Sequence[_Piece], dt: float, samples: int, wanted: int, seed: int
) -> SegmentBatch:
    """A seeded random subset of the windows with about `wanted` compared samples."""
    if samples <= wanted:
        return make_batch([], dt, pieces=pieces)
    order = np.random.default_rng(seed).permutation(len(pieces))
    lengths = np.array([stop - start - 1 for _, start, stop in pieces])[order]
    keep = order[: int(np.searchsorted(np.cumsum(lengths), wanted)) + 1]
    return make_batch([], dt, pieces=[pieces[i] for i in sorted(keep)])


def _pooled_v0(pooled: float, max_speed: np.ndarray, limits: Limits) -> np.ndarray:
    """The global search's v0 of each follower: the pooled value, or just above its top speed."""
    return np.clip(np.maximum(pooled, V0_MARGIN * max_speed), limits.v0[:, 0], limits.v0[:, 1])


def _global_search(
    batch: SegmentBatch,
    model: Model,
    box: Mapping[str, tuple[float, float]],
    seed: int,
    maxiter: int,
    popsize: int,
    work: _Counter,
    on_generation: Callable[[int, float], None] | None,
) -> tuple[np.ndarray, int]:
    """Seeded differential evolution over a, b, T, s0, delta and a pooled v0 (6 dimensions)."""
    from scipy.optimize import differential_evolution

    limits = Limits.of(box, batch.max_speed)
    generations = 0

    def objective(population: np.ndarray) -> np.ndarray:  # vectorised: (6, S) -> (S,)
        members = population.T
        work.add(len(members))
        v0 = np.stack([_pooled_v0(p, batch.max_speed, limits) for p in members[:, 5]])
        per_window, _ = simulate(members[:, :5], v0, batch, model)
        return np.sqrt(per_window.sum(axis=1) / batch.samples)

    def progress(intermediate_result: Any) -> None:
        nonlocal generations
        generations += 1
        if on_generation is not None:
            on_generation(generations, float(intermediate_result.fun))

    found = differential_evolution(
        objective,
        np.vstack([limits.shared, [box["v0"]]]),
        seed=seed,
        maxiter=maxiter,
        popsize=popsize,
        tol=1e-3,
        polish=False,
        vectorized=True,
        updating="deferred",
        callback=progress,
    )
    return np.asarray(found.x, dtype=float), generations


def _refine(
    theta: np.ndarray,
    v0: np.ndarray,
    batch: SegmentBatch,
    model: Model,
    limits: Limits,
    maxiter: int,
    work: _Counter,
) -> tuple[np.ndarray, np.ndarray, Linearisation, dict[str, Any]]:
    """Levenberg-Marquardt on all data from (theta, v0), inside the box (steps are clipped)."""
    theta, v0 = limits.clip(theta, v0)
    ones = np.ones((1, len(v0)))
    lin = linearise(theta, v0, batch, model, limits)
    work.add(_SETS_PER_POINT)
    sse, damping, iterations, message = float(lin.sse.sum()), 1e-3, 0, "maxiter reached"
    while iterations < maxiter:
        if math.sqrt(sse / batch.samples) < 1e-9:
            message = "exact fit"
            break
        step_theta, step_v0 = gauss_newton_step(
            lin, ones, np.array([damping]), theta[None], v0[None], limits
        )
        trial_theta, trial_v0 = limits.clip(theta + step_theta[0], v0 + step_v0[0])
        trial = float(_weighted_sse(trial_theta, trial_v0, ones, batch, model)[0])
        work.add(1)
        if trial < sse:
            iterations += 1
            gain, sse = (sse - trial) / sse, trial
            theta, v0, damping = trial_theta, trial_v0, max(damping / 3, 1e-9)
            lin = linearise(theta, v0, batch, model, limits)
            work.add(_SETS_PER_POINT)
            if gain < 1e-9:
                message = "converged (relative gain < 1e-9)"
                break
        else:
            damping *= 4
            if damping > 1e8:
                message = "converged (no step improves)"
                break
    return theta, v0, lin, {"iterations": iterations, "message": message}


def _determined(lin: Linearisation, v0: np.ndarray, batch: SegmentBatch) -> np.ndarray:
    """Followers whose gaps move by `V0_SENSITIVITY_M` (RMS) when their v0 changes by 10 %."""
    samples = np.maximum(batch.follower_samples(), 1)
    return np.sqrt(lin.d[0] * np.square(0.1 * v0) / samples) >= V0_SENSITIVITY_M


def sensitivities(
    lin: Linearisation, theta: np.ndarray, v0: np.ndarray, samples: int
) -> dict[str, float]:
    """How well the data determine each parameter, linearised at the optimum: the RMS change (m)
    of the simulated gaps when it moves by 10 % and the other parameters re-adjust to compensate.

    For a shared parameter the others include every follower's v0; for ``v0`` it is every v0
    scaled by 10 % together, the shared ones compensating. It is sqrt(1 / (H^-1)_pp / samples),
    H the Gauss-Newton matrix in units of those 10 % steps. Near zero: the data cannot tell the
    parameter, however good the fit (traffic in one steady state, for instance)."""
    A, c, d = lin.A[0].sum(axis=0), lin.c[0], lin.d[0]
    scale = 0.1 * np.abs(theta)
    keep = d > 0
    H = A - np.einsum("fi,fj->ij", c[keep] / d[keep, None], c[keep])
    found = _profile(scale[:, None] * H * scale[None, :], samples)
    step = 0.1 * v0  # every v0 by 10 %: one more column, J_v0 @ step
    M = np.zeros((6, 6))
    M[:5, :5] = scale[:, None] * A * scale[None, :]
    M[:5, 5] = M[5, :5] = scale * (c * step[:, None]).sum(axis=0)
    M[5, 5] = float((d * step * step).sum())
    values = (*found, _profile(M, samples)[5])
    return {name: float(x) for name, x in zip((*SHARED_NAMES, "v0"), values, strict=True)}


def _profile(H: np.ndarray, samples: int) -> np.ndarray:
    """sqrt(1 / (H^-1)_pp / samples) of a symmetric positive semi-definite H, robust to its
    null directions (their eigenvalues are floored, so those parameters come out near 0)."""
    eigenvalues, vectors = np.linalg.eigh(H)
    floor = max(1e-12 * float(eigenvalues.max()), 1e-300)
    inverse_diagonal = (np.square(vectors) / np.maximum(eigenvalues, floor)).sum(axis=1)
    return np.asarray(np.sqrt(1.0 / inverse_diagonal / samples))


def _median_weights(determined: np.ndarray) -> np.ndarray:
    """Which followers the typical v0 is the median of: the determined ones, or all if none."""
    return determined.astype(float) if determined.any() else np.ones(len(determined))


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    order = np.argsort(values)
    cumulative = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])


def _bootstrap(
    theta: np.ndarray,
    v0: np.ndarray,
    lin: Linearisation,
    typical: np.ndarray,
    batch: SegmentBatch,
    model: Model,
    limits: Limits,
    replicates: int,
    steps: int,
    seed: int,
    work: _Counter,
) -> dict[str, tuple[float, float]]:
    """Percentile intervals from refits of follower-resampled data, started at the optimum."""
    if replicates <= 0:
        return {}
    count = len(v0)
    rng = np.random.default_rng(seed)
    weights = rng.multinomial(count, np.full(count, 1.0 / count), size=replicates).astype(float)
    thetas, v0s = np.repeat(theta[None], replicates, 0), np.repeat(v0[None], replicates, 0)
    current = weights @ lin.sse[0]
    damping = np.full(_CHUNK_POINTS, 1e-6)
    for step in range(steps):
        for rows in _chunks(replicates):
            n = rows.stop - rows.start
            if step == 0:  # every replicate starts at the optimum: its Jacobian serves them all
                at = lin.broadcast(n)
            else:
                at = linearise(thetas[rows], v0s[rows], batch, model, limits)
                work.add(_SETS_PER_POINT * n)
            step_theta, step_v0 = gauss_newton_step(
                at, weights[rows], damping[:n], thetas[rows], v0s[rows], limits
            )
            best_theta, best_v0, best = _line_search(
                thetas[rows], v0s[rows], step_theta, step_v0, weights[rows], batch, model, limits
            )
            work.add(n * len(_LINE_SEARCH))
            better = best < current[rows]
            thetas[rows] = np.where(better[:, None], best_theta, thetas[rows])
            v0s[rows] = np.where(better[:, None], best_v0, v0s[rows])
            current[rows] = np.where(better, best, current[rows])
    typical_weights = weights * _median_weights(typical)
    medians = np.array(
        [
            _weighted_median(v, w) if w.sum() > 0 else math.nan
            for v, w in zip(v0s, typical_weights, strict=True)
        ]
    )  # nan: a replicate that drew none of the determined followers
    tail = (1.0 - INTERVAL_LEVEL) / 2
    values = dict(zip(SHARED_NAMES, thetas.T, strict=True)) | {"v0": medians}
    return {
        name: (
            float(np.nanquantile(values[name], tail)),
            float(np.nanquantile(values[name], 1 - tail)),
        )
        for name in PARAM_NAMES
    }


_LINE_SEARCH = (1.0, 0.5, 0.25, 0.125)
"""Fractions of a bootstrap replicate's Gauss-Newton step tried at once; the best is kept."""


def _line_search(
    theta: np.ndarray,
    v0: np.ndarray,
    step_theta: np.ndarray,
    step_v0: np.ndarray,
    weights: np.ndarray,
    batch: SegmentBatch,
    model: Model,
    limits: Limits,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The best of the step fractions `_LINE_SEARCH` at P points (one simulation of P x 4 sets):
    its parameters and its weighted SSE."""
    fractions = np.array(_LINE_SEARCH)[:, None, None]
    trial_theta, trial_v0 = limits.clip(theta + fractions * step_theta, v0 + fractions * step_v0)
    k, points = len(_LINE_SEARCH), theta.shape[0]
    sse = _weighted_sse(
        trial_theta.reshape(k * points, -1),
        trial_v0.reshape(k * points, -1),
        np.tile(weights, (k, 1)),
        batch,
        model,
    ).reshape(k, points)
    pick = np.argmin(sse, axis=0)
    chosen = np.arange(points)
    return trial_theta[pick, chosen], trial_v0[pick, chosen], sse[pick, chosen]


def _chunks(count: int) -> list[slice]:
    return [slice(i, min(i + _CHUNK_POINTS, count)) for i in range(0, count, _CHUNK_POINTS)]


def v0_summary(result: CalibrationResult) -> dict[str, Any]:
    """The followers' own v0: how many are determined, their spread, and each one."""
    followers = result.v0_followers
    determined = np.array([f.v0 for f in followers if f.determined])
    spread = determined if len(determined) else np.array([f.v0 for f in followers])
    top = result.bounds["v0"][1]
    return {
        "pooling": "params.v0 is the median of the determined followers' own v0 (each fitted)",
        "followers": len(followers),
        "determined": len(determined),
        "at_upper_bound": sum(1 for f in followers if f.v0 >= top - 1e-9),
        "median": float(np.median(spread)) if len(spread) else None,
        "p5": float(np.quantile(spread, 0.05)) if len(spread) else None,
        "p95": float(np.quantile(spread, 0.95)) if len(spread) else None,
        "per_follower": [
            {
                "seed": f.seed,
                "id": f.id,
                "v0": round(f.v0, 4),
                "max_speed": round(f.max_speed, 4),
                "determined": f.determined,
            }
            for f in followers
        ],
    }


def calibration_document(
    result: CalibrationResult, data: Mapping[str, Any], versions: Mapping[str, str] | None = None
) -> dict[str, Any]:
    """The JSON of a calibration: ``params`` (IDMParams fields, what ``idm:FILE`` reads),
    ``intervals``, ``fit``, ``v0``, ``data``, ``bounds``, ``versions``."""
    return {
        "params": result.params.to_dict(),
        "intervals": {
            "level": INTERVAL_LEVEL,
            "method": "bootstrap over followers (resampled with replacement, refitted from the "
            "optimum), percentile intervals",
            **{name: list(pair) for name, pair in result.intervals.items()},
        },
        "fit": {
            "objective": "RMSE of the simulated gap against the recorded gap, pooled (m)",
            "gap_rmse_m": result.gap_rmse,
            "gap_nrmse": result.gap_nrmse,
            "global_gap_rmse_m": result.global_gap_rmse,
            "at_bounds": result.at_bounds,
            "wide_intervals": result.wide,
            "undetermined": result.undetermined,
            "sensitivity_m": {
                "meaning": "RMS change of the simulated gaps when the parameter moves by 10 % and "
                "the others, every v0 included, compensate (linearised at the optimum)",
                **result.sensitivity,
            },
            "generations": result.generations,
            "evaluations": result.evaluations,
            "seconds": round(result.seconds, 2),
            **result.settings,
        },
        "v0": v0_summary(result),
        "data": {
            **data,
            "segments": result.segments,
            "followers": result.followers,
            "windows": result.windows,
            "samples": result.samples,
        },
        "bounds": {name: list(pair) for name, pair in result.bounds.items()},
        "versions": dict(versions or {}),
    }
