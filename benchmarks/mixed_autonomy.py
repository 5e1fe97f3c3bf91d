"""Mixed autonomy: traffic-level figures at shares of automated vehicles, beside all humans.

Starts its own ``sim-server --backend sumo`` on a free loopback port (waits for its readiness
line, stops it at the end) and drives many egos in one SUMO simulation through the bridge with
`agent_client.RemoteParallelEnv` (protocol 1.4), ``report_traffic`` on, so that every step
gives every vehicle's speed and odometer: the egos' own observations and the humans' columns.

* ``--scenario ring`` (default): the Sugiyama ring (22 vehicles on 230 m, humans ``eidm``, which
  form a stop-and-go wave), at AV shares 0, 10, 25, 50 and 100 %: round(share x 22) egos (halves
  up: 0, 2, 6, 11, 22), spread evenly round the ring and handed over at the end of the 300 s
  warm-up (the wave has formed), then 300 s measured. 0 % is the all-human baseline: one ego
  that SUMO drives as a human (``ego_driver: "sumo"``).
* ``--scenario cflc``: 2 km, three lanes, 80 km/h, Krauss humans at 700 veh/h per lane, at AV
  shares 0, 10, 25, 50 and 100 % (protocol 1.5, ``ego_share``): after a 150 s warm-up (the
  road is full by then: 2 km at ~19 m/s) that share of the vehicles on the road is handed over,
  and the same share of the vehicles that enter afterwards joins as they enter, for 300 s.
  0 % is the all-human baseline: every vehicle an ego that SUMO drives as a human
  (``ego_share`` 1 with ``ego_driver: "sumo"``), so that it is measured the same way.

The egos' drivers (``--driver``, one or more): ``idm`` (`agent_client.drivers.idm.IDMDriver`,
its default parameters, one per ego) or a policy file (``runs/NAME/policy.pt``,
`agent_client.drivers.policy.load_policy_driver`, greedy). Its features are computed from each
ego's own observation; the ``cf`` set (speed / speed limit, acceleration, the leader's
presence, gap and speed difference, time headway) does not use ``ego.position``, and on the
ring the leader is found across the seam, so it works there - but a policy trained on the
80 km/h roads driving the 30 km/h ring is a transfer, and the output says so.

Figures per run (every vehicle, and the humans alone): mean speed; the speed standard deviation
across vehicles at each step, averaged over time (0 in uniform flow); each vehicle's speed
standard deviation over time, averaged over vehicles; the share of time stopped (< 1 m/s);
throughput (ring: vehicles past the seam per hour, from the odometers, and Edie's flow, the
distance all drove over ring length x time; cflc: arrivals at the end of the road per hour, and
vehicles past the 1 km mark per hour); collisions of egos (the only ones SUMO reports: its
humans do not crash), each with who drove into whom. The unreasonable-stop end rule is off
(``stop_patience`` 3600 s), since an ego that ended would be taken out of the simulation and
change the traffic being measured. A crashed ego is taken out all the same (the table gives
the vehicles left at the end), and once every ego has crashed the episode is over (the table
gives the time measured).

    python benchmarks/mixed_autonomy.py                                  # ring, IDM egos, 3 seeds
    python benchmarks/mixed_autonomy.py --driver idm runs/bench-cf/cf-safe-0/policy.pt
    python benchmarks/mixed_autonomy.py --scenario cflc

Writes benchmarks/results/mixed_autonomy_{ring,cflc}.json, the ring's time-space diagrams
(mixed_autonomy_ring.png: the all-human ring beside, per driver, ``--diagram-shares``) and
the figures against the share (mixed_autonomy_{ring,cflc}_figures.png). A measurement, not a
test: every figure is simulated time, independent of the machine's load.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent_client import RemoteParallelEnv
from agent_client.drivers.idm import IDMDriver, IDMParams
from agent_client.drivers.policy import PolicyDriver, load_policy_driver
from agent_client.evaluation.traffic_figures import (
    STOPPED_SPEED,
    arrivals,
    edie_flow,
    first_last,
    mean_speed,
    passes,
    per_hour,
    spread_across,
    spread_over_time,
    stopped_share,
)
from protocol.messages import MultiObservation, Observation, OptionValue
from protocol.readiness import LISTENING, NotReady, stop_process, wait_for_line
from sim_server.backends.sumo.scenarios import RING_SPEED_LIMIT, RingOptions

RESULTS = ROOT / "benchmarks" / "results"
READY_TIMEOUT_S = 60.0
"""How long the server may take to print its readiness line."""
VEHICLE_LENGTH = 5.0
"""Every vehicle is SUMO's 5 m passenger car; a road human enters with its back on 0
(``departPos="base"``), so its front is this plus its odometer."""
NO_STOP_RULE = 3600.0
"""``stop_patience`` (s): the unreasonable-stop end rule never fires within an episode."""
SHARES = (0.0, 10.0, 25.0, 50.0, 100.0)
CFLC_MARK = 1000.0
"""m: the point of the road whose passing vehicles are counted."""
CFLC_LENGTH = 2000.0
HUMAN = "human"
"""The label of the all-human baseline in the tables."""
FIGURES = (
    "window_s",
    "vehicles_end",
    "mean_speed",
    "mean_speed_tail",
    "speed_std_tail",
    "speed_std_humans_tail",
    "mean_speed_humans",
    "speed_std",
    "speed_std_humans",
    "speed_std_over_time",
    "speed_std_over_time_humans",
    "throughput",
    "throughput_edie",
    "throughput_humans",
    "throughput_edie_humans",
    "stopped_share",
    "stopped_share_humans",
    "speed_std_humans_vs_base",
    "mean_speed_humans_vs_base",
    "collisions",
    "ego_share",
)


class Driver(Protocol):
    def act(self, obs: Observation) -> tuple[float, int]: ...


@dataclass
class DriverChoice:
    """One ``--driver``: its label, how to make one per ego, what it is, its decision interval."""

    label: str
    make: Callable[[], Driver]
    note: str
    decision_interval: float = 0.1
    policy: PolicyDriver | None = None


def choose_driver(spec: str, scenario: str) -> DriverChoice:
    """``idm`` or a policy file; a policy trained on another scenario is said to be a transfer."""
    if spec == "idm":
        params = IDMParams()
        note = (
            f"the client's IDM, its defaults (a {params.a:g} m/s², b {params.b:g} m/s², "
            f"T {params.T:g} s, s0 {params.s0:g} m, v0 the speed limit), one per ego"
        )
        return DriverChoice("idm", IDMDriver, note)
    path = Path(spec)
    driver = load_policy_driver(path)
    config_file = path.parent / "config.json"
    config: dict[str, Any] = json.loads(config_file.read_text()) if config_file.exists() else {}
    trained_on = str(config.get("scenario", "unknown"))
    interval = float(config.get("decision_interval", 0.1))
    note = (
        f"policy {spec} (feature set {driver.features.name!r}, greedy, {interval:g} s "
        f"decisions), trained on {trained_on}"
    )
    if trained_on != scenario:
        note += (
            f": a transfer to {scenario} (its speed feature is speed / speed limit, so on the "
            f"30 km/h ring it aims at the ring's limit; gaps and headways are those it learned "
            f"at 80 km/h)"
            if scenario == "ring"
            else f": a transfer to {scenario}"
        )
    label = path.parent.name if path.stem == "policy" else path.stem
    return DriverChoice(label, lambda: driver, note, interval, driver)


# --------------------------------------------------------------------------- the server


@contextlib.contextmanager
def sim_server(cache_dir: Path) -> Iterator[str]:
    """A ``sim-server --backend sumo`` subprocess on a free loopback port; its address once it
    has printed its readiness line. Stopped (SIGTERM, then SIGKILL) on the way out."""
    command = [
        sys.executable, "-m", "sim_server.cli", "--bind", "tcp://127.0.0.1:0",
        "--backend", "sumo", "--cache-dir", str(cache_dir), "--log-level", "WARNING",
        "--exit-with-parent",
    ]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with tempfile.TemporaryFile(mode="w+") as log:
        process = subprocess.Popen(
            command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=log, text=True
        )
        try:
            try:
                address = wait_for_line(process, LISTENING, READY_TIMEOUT_S)
            except NotReady as exc:
                log.seek(0)
                raise RuntimeError(f"sim-server did not become ready: {exc}\n{log.read()}") from exc
            yield address
        finally:
            stop_process(process)


# --------------------------------------------------------------------------- one episode


@dataclass
class Trace:
    """Every vehicle's speed and unwrapped front position at every step of one episode."""

    driven: bool
    """The client drove the egos (False: the all-human run, whose egos SUMO drives as humans)."""
    start_of: Callable[[str], float]
    """Where a human's odometer starts (m, its front at entry)."""
    ring_length: float | None = None
    agents: set[str] = field(default_factory=set)
    """The egos the client drove, every one seen (on cflc they join as they enter)."""
    times: list[float] = field(default_factory=list)
    rows: list[dict[str, tuple[float, float]]] = field(default_factory=list)
    humans: list[frozenset[str]] = field(default_factory=list)
    ego_counts: list[int] = field(default_factory=list)
    collisions: dict[tuple[float, str, str], dict[str, Any]] = field(default_factory=dict)
    """Each collision once (an ego-ego one is reported by both): when, who, and how."""
    ends: Counter[str] = field(default_factory=Counter)
    ego_arrivals: int = 0
    gap_error: float = 0.0
    """Ring: the largest difference (m) between a human's reported gap and the one its place and
    its leader's give (a check that the places are right)."""
    ended_last: int = 0
    """Egos whose drive ended (not by the time limit) in the latest frame: they leave after it."""
    _around: dict[str, tuple[str, str]] = field(default_factory=dict)
    """Each ego's leader and follower ids in its latest observation."""

    def record(self, frame: MultiObservation) -> None:
        traffic = frame.traffic
        if traffic is None:
            raise RuntimeError("the frame has no traffic: the server ignored report_traffic")
        row: dict[str, tuple[float, float]] = {}
        self.ended_last = 0
        humans = set(traffic.id)
        if self.driven:
            self.agents.update(ego.id for ego in frame.egos)
        else:  # SUMO drives the egos: humans, counted as such when they leave the road
            humans.update(ego.id for ego in frame.egos if ego.reason in ("", "time_limit"))
        for ego in frame.egos:
            row[ego.id] = (ego.ego.speed, ego.ego.position)
            if ego.events.collision:
                self._collided(frame.time, ego.id, ego.events.collision_with)
            around = ego.neighbours
            self._around[ego.id] = (around.leader.id, around.follower.id)
            if (ego.terminated or ego.truncated) and ego.reason != "time_limit":
                self.ends[ego.reason] += 1
                self.ended_last += 1
                self.ego_arrivals += self.driven and ego.reason == "end_of_road"
        for vehicle, speed, odometer in zip(
            traffic.id, traffic.speed, traffic.position, strict=True
        ):
            row[vehicle] = (speed, self.start_of(vehicle) + odometer)
        if self.ring_length is not None:
            self._check_gaps(row, traffic.id, traffic.leader, traffic.gap)
        self.times.append(frame.time)
        self.rows.append(row)
        self.humans.append(frozenset(humans))
        self.ego_counts.append(len(frame.egos))

    def _collided(self, now: float, ego: str, other: str) -> None:
        """Note a collision once, with who was behind: an ego that drove into the vehicle ahead
        of it in its previous observation, or a vehicle that drove into it from behind."""
        pair = sorted((ego, other))
        key = (round(now, 3), pair[0], pair[1])
        if key in self.collisions:
            return
        leader, follower = self._around.get(ego, ("", ""))
        how = (
            "ego into its leader"
            if other == leader
            else "follower into the ego"
            if other == follower
            else "neither leader nor follower"
        )
        start = self.times[0] if self.times else now
        self.collisions[key] = {"t_s": round(now - start, 1), "ego": ego, "with": other, "how": how}

    def _check_gaps(
        self,
        row: dict[str, tuple[float, float]],
        ids: Sequence[str],
        leaders: Sequence[str],
        gaps: Sequence[float],
    ) -> None:
        assert self.ring_length is not None
        for vehicle, leader, gap in zip(ids, leaders, gaps, strict=True):
            if leader and leader in row:
                ahead = (row[leader][1] - row[vehicle][1]) % self.ring_length - VEHICLE_LENGTH
                self.gap_error = max(self.gap_error, abs(ahead - gap))

    def table(self) -> tuple[list[str], np.ndarray, np.ndarray]:
        """Vehicle ids (in order of appearance), speeds and positions (steps, vehicles), NaN
        where a vehicle is absent."""
        ids: dict[str, int] = {}
        for row in self.rows:
            for vehicle in row:
                ids.setdefault(vehicle, len(ids))
        speeds = np.full((len(self.rows), len(ids)), np.nan)
        positions = np.full_like(speeds, np.nan)
        for t, row in enumerate(self.rows):
            for vehicle, (speed, position) in row.items():
                speeds[t, ids[vehicle]] = speed
                positions[t, ids[vehicle]] = position
        return list(ids), speeds, positions


def drive(
    env: RemoteParallelEnv, seed: int, make: Callable[[], Driver], trace: Trace, max_steps: int
) -> dict[str, Observation]:
    """One episode: reset, then every running ego's driver acts on its own observation until
    no ego is left (or `max_steps`, a guard). Returns the egos' observations at the hand-over."""
    env.reset(seed=seed)
    handed_over = env.last_observations
    frame = env.last_frame
    assert frame is not None
    trace.record(frame)
    drivers: dict[str, Driver] = {}
    for _ in range(max_steps):
        if not env.agents:
            break
        last = env.last_observations
        actions: dict[str, Any] = {}
        for agent in env.agents:
            driver = drivers.get(agent) or drivers.setdefault(agent, make())  # one that joined
            acceleration, lane_change = driver.act(last[agent])
            actions[agent] = {"acceleration": [acceleration], "lane_change": lane_change}
        env.step(actions)
        frame = env.last_frame
        assert frame is not None
        trace.record(frame)
    else:
        raise RuntimeError(f"the episode did not end within {max_steps} steps")
    return handed_over


def policy_features(policy: PolicyDriver, handed_over: dict[str, Observation]) -> list[float]:
    """The policy's features of the first ego at the hand-over, checked to be finite (on the
    ring: its leader found across the seam, ``ego.position`` an odometer it does not read)."""
    first = handed_over[min(handed_over)]
    features = policy.features(first)
    if not np.all(np.isfinite(features)):
        raise RuntimeError(f"non-finite features of {first.ego} / {first.neighbours.leader}")
    return [round(float(x), 4) for x in features]


def _no_reward(prev: Observation | None, obs: Observation, elapsed: float) -> float:
    return 0.0


# --------------------------------------------------------------------------- figures


def _finite(value: float | None) -> float | None:
    return None if value is None or not math.isfinite(value) else round(float(value), 4)


def figures(trace: Trace, scenario: str, length: float, tail: float) -> dict[str, Any]:
    """The traffic-level figures of one episode (None where undefined, e.g. humans at 100 %);
    the ``_tail`` ones over its last `tail` seconds only (has a wave died out?)."""
    ids, speeds, positions = trace.table()
    humans = np.array([vehicle not in trace.agents for vehicle in ids])
    seconds = trace.times[-1] - trace.times[0]
    late = np.array(trace.times) >= trace.times[-1] - tail
    first, last = first_last(positions)
    human_speeds = speeds[:, humans]
    if scenario == "ring":
        count = passes(first, last, 0.0, length)  # the seam, the start of edge a
        human_count = passes(first[humans], last[humans], 0.0, length)
        edie = edie_flow(last - first, length, seconds)
        human_edie = edie_flow(last[humans] - first[humans], length, seconds)
    else:
        human_count = arrivals(trace.humans)
        count = human_count + trace.ego_arrivals
        edie = per_hour(passes(first, last, CFLC_MARK), seconds)
        human_edie = per_hour(passes(first[humans], last[humans], CFLC_MARK), seconds)
    present = (~np.isnan(speeds)).sum(axis=1)
    agents_present = (~np.isnan(speeds[:, ~humans])).sum(axis=1)
    return {
        "window_s": round(seconds, 1),
        "vehicles_start": int(present[0]),
        "vehicles_end": int(present[-1]) - trace.ended_last,
        "vehicles_mean": round(float(present.mean()), 1),
        "ego_share": _finite(float(np.mean(agents_present / np.maximum(present, 1)))),
        "mean_speed": _finite(mean_speed(speeds)),
        "mean_speed_humans": _finite(mean_speed(human_speeds)),
        "speed_std": _finite(spread_across(speeds)),
        "speed_std_humans": _finite(spread_across(human_speeds)),
        "speed_std_over_time": _finite(spread_over_time(speeds)),
        "speed_std_over_time_humans": _finite(spread_over_time(human_speeds)),
        "speed_std_tail": _finite(spread_across(speeds[late])),
        "speed_std_humans_tail": _finite(spread_across(human_speeds[late])),
        "mean_speed_tail": _finite(mean_speed(speeds[late])),
        "throughput": _finite(per_hour(count, seconds)),
        "throughput_edie": _finite(edie),
        "throughput_humans": _finite(per_hour(human_count, seconds)),
        "throughput_edie_humans": _finite(human_edie),
        "stopped_share": _finite(stopped_share(speeds)),
        "stopped_share_humans": _finite(stopped_share(human_speeds)),
        "collisions": len(trace.collisions),
        "collision_list": list(trace.collisions.values()),
        "ego_ends": dict(trace.ends),
        "gap_check_max_error_m": round(trace.gap_error, 4) if scenario == "ring" else None,
    }


def pair_with_baseline(runs: list[dict[str, Any]]) -> None:
    """Add to each run its humans' speed std over the all-human run's of the same seed, and
    the difference of their mean speeds (m/s): the seeds' traffic differs, a pair less so."""
    base = {run["seed"]: run["figures"] for run in runs if run["driver"] == HUMAN}
    for run in runs:
        mine, theirs = run["figures"], base.get(run["seed"], {})
        std, base_std = mine["speed_std_humans"], theirs.get("speed_std_humans")
        speed, base_speed = mine["mean_speed_humans"], theirs.get("mean_speed_humans")
        ratio = std / base_std if std is not None and base_std else None
        change = speed - base_speed if speed is not None and base_speed is not None else None
        mine["speed_std_humans_vs_base"] = None if ratio is None else round(ratio, 4)
        mine["mean_speed_humans_vs_base"] = None if change is None else round(change, 4)


def summarise(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per driver and share: each figure's mean, min and max over the seeds."""
    groups: dict[tuple[str, float], list[dict[str, Any]]] = {}
    for run in runs:
        groups.setdefault((run["driver"], run["share_pct"]), []).append(run)
    out = []
    for (driver, share), group in groups.items():
        egos = group[0]["egos"] if len({r["egos"] for r in group}) == 1 else None
        entry: dict[str, Any] = {"driver": driver, "share_pct": share, "egos": egos}
        entry["egos_per_seed"] = [run["egos"] for run in group]
        entry["seeds"] = [run["seed"] for run in group]
        for name in FIGURES:
            values = [run["figures"][name] for run in group if run["figures"][name] is not None]
            entry[name] = (
                {
                    "mean": round(float(np.mean(values)), 4),
                    "min": round(float(min(values)), 4),
                    "max": round(float(max(values)), 4),
                }
                if values
                else None
            )
        entry["ego_ends"] = dict(sum((Counter(r["figures"]["ego_ends"]) for r in group), Counter()))
        entry["collisions_how"] = dict(
            Counter(c["how"] for r in group for c in r["figures"]["collision_list"])
        )
        out.append(entry)
    return out


# --------------------------------------------------------------------------- output


def _cell(entry: dict[str, Any], name: str, scale: float = 1.0, form: str = ".2f") -> str:
    """Mean (min-max) over the seeds; collisions as the total."""
    value = entry[name]
    if value is None:
        return "-"
    if name == "collisions":
        return f"{round(sum_of(entry, name))}"
    mean, low, high = (scale * value[k] for k in ("mean", "min", "max"))
    return f"{mean:{form}} ({low:{form}}-{high:{form}})"


def sum_of(entry: dict[str, Any], name: str) -> float:
    """The total over the seeds of a figure averaged in `entry`."""
    return float(entry[name]["mean"]) * len(entry["seeds"])


def _count(entry: dict[str, Any], name: str) -> str:
    """A count over the seeds: the value if the same in all, else mean (min-max)."""
    value = entry[name]
    if value["min"] == value["max"]:
        return f"{value['min']:g}"
    return f"{value['mean']:.1f} ({value['min']:g}-{value['max']:g})"


def table(summary: list[dict[str, Any]], scenario: str, tail: float) -> str:
    """The Markdown table: mean over seeds (min-max); collisions summed over the seeds."""
    if scenario == "ring":
        heads = [
            "egos driven by", "AV share", "egos", "measured (s)", "vehicles at the end",
            "mean speed, all (m/s)", "humans", "speed std across vehicles, all (m/s)",
            "humans", "humans / all-human, same seed", f"all, last {tail:g} s",
            "speed std over time, humans (m/s)", "past the seam (veh/h)", "Edie flow (veh/h)",
            "stopped, all (%)", "humans (%)", "collisions",
        ]  # fmt: skip
    else:
        heads = [
            "egos driven by", "AV share", "egos in all (per seed)",
            "share of the vehicles on the road (%)", "window (s)",
            "mean speed, all (m/s)", "humans", "speed std across vehicles, all (m/s)",
            "humans", "humans / all-human, same seed", "arrivals at 2 km, all (veh/h)", "humans",
            "past 1 km, all (veh/h)", "humans", "collisions",
        ]  # fmt: skip
    lines = ["| " + " | ".join(heads) + " |", "|" + " --- |" * len(heads)]
    for entry in summary:
        driver = "humans only" if entry["driver"] == HUMAN else entry["driver"]
        if scenario == "ring":
            cells = [
                driver, f"{entry['share_pct']:.1f} %", str(entry["egos"]),
                _cell(entry, "window_s", form=".0f"), _count(entry, "vehicles_end"),
                _cell(entry, "mean_speed"), _cell(entry, "mean_speed_humans"),
                _cell(entry, "speed_std"), _cell(entry, "speed_std_humans"),
                _cell(entry, "speed_std_humans_vs_base"), _cell(entry, "speed_std_tail"),
                _cell(entry, "speed_std_over_time_humans"),
                _cell(entry, "throughput", form=".0f"), _cell(entry, "throughput_edie", form=".0f"),
                _cell(entry, "stopped_share", 100, ".1f"),
                _cell(entry, "stopped_share_humans", 100, ".1f"), _cell(entry, "collisions"),
            ]  # fmt: skip
        else:
            cells = [
                driver, f"{entry['share_pct']:g} %",
                ", ".join(map(str, entry["egos_per_seed"])) if entry["driver"] != HUMAN else "-",
                _cell(entry, "ego_share", 100, ".1f"),
                _cell(entry, "window_s", form=".0f"),
                _cell(entry, "mean_speed"), _cell(entry, "mean_speed_humans"),
                _cell(entry, "speed_std"), _cell(entry, "speed_std_humans"),
                _cell(entry, "speed_std_humans_vs_base"), _cell(entry, "throughput", form=".0f"),
                _cell(entry, "throughput_humans", form=".0f"),
                _cell(entry, "throughput_edie", form=".0f"),
                _cell(entry, "throughput_edie_humans", form=".0f"), _cell(entry, "collisions"),
            ]  # fmt: skip
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _time_space(
    ax: Any, trace: Trace, length: float, speed_limit: float, title: str, seconds: float
) -> Any:
    """One time-space diagram on `ax` of the first `seconds` after the hand-over: humans as
    dots, the client's egos as lines, both coloured by speed, every 0.5 s; returns the colour
    mapping."""
    from matplotlib.collections import LineCollection
    from matplotlib.colors import Normalize

    ids, speeds, positions = trace.table()
    times = np.array(trace.times) - trace.times[0]
    every = max(1, round(0.5 / max(float(np.median(np.diff(times))), 1e-9)))
    shown = slice(0, int(np.searchsorted(times, seconds, side="right")), every)
    t, places, v = times[shown], positions[shown] % length, speeds[shown]
    agent = np.array([vehicle in trace.agents for vehicle in ids])
    style: dict[str, Any] = {"cmap": "RdYlGn", "norm": Normalize(0.0, speed_limit)}
    tt = np.repeat(t[:, None], places.shape[1], axis=1)
    mapping = ax.scatter(
        tt[:, ~agent].ravel(), places[:, ~agent].ravel(), c=v[:, ~agent].ravel(), s=2.0,
        linewidths=0, rasterized=True, **style,
    )  # fmt: skip
    segments, colours = [], []
    for column in np.flatnonzero(agent):
        points = np.stack([t, places[:, column]], axis=1)
        pairs = np.stack([points[:-1], points[1:]], axis=1)
        keep = np.isfinite(pairs).all(axis=(1, 2)) & (np.diff(places[:, column]) > -length / 2)
        segments.append(pairs[keep])
        colours.append(v[1:, column][keep])
    if segments:
        lines = LineCollection(list(np.concatenate(segments)), linewidths=1.0, **style)
        lines.set_array(np.concatenate(colours))
        lines.set_rasterized(True)
        ax.add_collection(lines)
    for crash in trace.collisions.values():
        crashed = ids.index(crash["ego"])
        seen = np.flatnonzero(np.isfinite(positions[:, crashed]))
        if len(seen) and crash["t_s"] <= seconds:
            place = positions[seen[-1], crashed] % length
            ax.scatter([crash["t_s"]], [place], marker="x", s=40, c="k", linewidths=1.5, zorder=3)
    ax.set(title=title, xlim=(0, min(seconds, times[-1])), ylim=(0, length))
    ax.set_facecolor("0.82")  # the colour map's yellow (~4 m/s) is lost on white
    ax.title.set_fontsize(10)
    return mapping


def plot_time_space(
    baseline: Trace,
    panels: dict[str, list[tuple[str, Trace]]],
    length: float,
    speed_limit: float,
    path: Path,
    seconds: float,
) -> None:
    """The all-human ring on the left (its full height), and one row per driver of the
    chosen shares: place on the ring against time since the hand-over, its first `seconds`."""
    plt = _pyplot()
    rows = max(1, len(panels))
    columns = 1 + max((len(p) for p in panels.values()), default=0)
    fig = plt.figure(figsize=(4.6 * columns + 1.0, 3.6 * rows + 0.9), dpi=110, layout="constrained")
    grid = fig.add_gridspec(rows, columns)
    left = fig.add_subplot(grid[:, 0])
    mapping = _time_space(left, baseline, length, speed_limit, "all humans (0 %), seed 1", seconds)
    left.set(xlabel="time since the hand-over (s)", ylabel="place on the ring (m)")
    axes = [left]
    for row, (driver, shares) in enumerate(panels.items()):
        for column, (title, trace) in enumerate(shares, start=1):
            ax = fig.add_subplot(grid[row, column], sharey=left)
            _time_space(ax, trace, length, speed_limit, f"{title} ({driver}), seed 1", seconds)
            if row == rows - 1:
                ax.set_xlabel("time since the hand-over (s)")
            axes.append(ax)
    fig.colorbar(mapping, ax=axes, label="speed (m/s)", fraction=0.025)
    fig.suptitle(
        "the ring after the hand-over: humans as dots, the client's egos as lines, both coloured "
        "by speed; x: an ego's collision (it leaves the ring)",
        fontsize=10,
    )
    fig.savefig(path)
    plt.close(fig)


_SPEED = ("mean speed", "m/s", [("mean_speed", "all"), ("mean_speed_humans", "humans")])
_SPREAD = (
    "speed std across vehicles",
    "m/s",
    [("speed_std", "all"), ("speed_std_humans", "humans")],
)
_OVER_TIME = (
    "speed std over time, per vehicle",
    "m/s",
    [("speed_std_over_time", "all"), ("speed_std_over_time_humans", "humans")],
)
_COLLISIONS = ("collisions (all seeds)", "", [("collisions", "egos")])
FIGURE_PANELS: dict[str, list[tuple[str, str, list[tuple[str, str]]]]] = {
    "ring": [
        _SPEED,
        _SPREAD,
        _OVER_TIME,
        ("throughput", "veh/h", [("throughput", "past the seam"), ("throughput_edie", "Edie")]),
        (
            "time stopped (< 1 m/s)",
            "%",
            [("stopped_share", "all"), ("stopped_share_humans", "humans")],
        ),
        _COLLISIONS,
    ],
    "cflc": [
        _SPEED,
        _SPREAD,
        _OVER_TIME,
        (
            "throughput",
            "veh/h",
            [("throughput", "arrivals at 2 km, all"), ("throughput_humans", "humans")],
        ),
        ("share of the vehicles on the road", "%", [("ego_share", "egos")]),
        _COLLISIONS,
    ],
}
"""The panels of the figures picture: title, unit (% : a share, drawn x 100), (figure, label)."""


def plot_figures(summary: list[dict[str, Any]], scenario: str, path: Path, title: str) -> None:
    """Each figure against the AV share: per driver the mean
    over seeds with its min-max range; hollow markers where egos crashed (they left the road,
    so fewer vehicles, or a shorter episode, are measured); the all-human baseline dotted."""
    plt = _pyplot()
    panels = FIGURE_PANELS[scenario]
    fig, axes = plt.subplots(2, 3, figsize=(14, 7.6), dpi=110)
    base = next(e for e in summary if e["driver"] == HUMAN)
    drivers = list(dict.fromkeys(e["driver"] for e in summary if e["driver"] != HUMAN))
    x_of = lambda e: e["share_pct"]  # noqa: E731
    markers, styles = ("o", "s", "^", "D"), ("-", "--")
    for ax, (name, unit, series) in zip(axes.ravel(), panels, strict=True):
        scale = 100.0 if unit == "%" else 1.0  # shares as percentages
        for d, driver in enumerate(drivers):
            entries = [base, *(e for e in summary if e["driver"] == driver)]
            for s, (figure, label) in enumerate(series):
                kept = [e for e in entries if e[figure] is not None]
                if not kept:
                    continue
                x = np.array([x_of(e) for e in kept], dtype=float) + 0.6 * d
                if figure == "collisions":
                    y = low = high = np.array([sum_of(e, figure) for e in kept])
                else:
                    y, low, high = (
                        scale * np.array([e[figure][k] for e in kept])
                        for k in ("mean", "min", "max")
                    )
                colour = plt.get_cmap("tab20")((2 * d + s) % 20)  # a dark and a light per driver
                ax.errorbar(
                    x, y, yerr=[y - low, high - y], marker=markers[d % 4], color=colour,
                    linestyle=styles[s % 2], capsize=3, markersize=5,
                    label=f"{label}, {driver}" if len(drivers) > 1 else label,
                )  # fmt: skip
                crashed = np.array([e["collisions"]["mean"] > 0 for e in kept])
                ax.scatter(
                    x[crashed], y[crashed], marker=markers[d % 4], s=26, facecolors="white",
                    edgecolors=colour, linewidths=1.2, zorder=3,
                )  # fmt: skip
        for figure, _ in series[:1]:
            if base[figure] is not None and figure not in ("collisions", "ego_share"):
                ax.axhline(scale * base[figure]["mean"], color="0.5", linestyle=":", linewidth=1)
        if series[0][0] == "collisions":
            from matplotlib.ticker import MaxNLocator

            ax.yaxis.set_major_locator(MaxNLocator(integer=True))
            ax.set_ylim(bottom=-0.5, top=max(ax.get_ylim()[1], 1.5))
        ax.set_title(name, fontsize=10)
        ax.set_ylabel(unit)
        ax.set_xlabel("AV share (%)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# --------------------------------------------------------------------------- main


def ring_plan(args: argparse.Namespace) -> list[tuple[float, int]]:
    """(share %, egos) per share: round(share x vehicles), halves up; 0 % is one human ego."""
    return [(share, math.floor(share / 100 * args.vehicles + 0.5)) for share in args.shares]


def scenario_options(args: argparse.Namespace, interval: float) -> dict[str, OptionValue]:
    options: dict[str, OptionValue] = {
        "warmup": args.warmup,
        "max_episode_time": args.duration,
        "decision_interval": interval,
        "report_traffic": True,
        "stop_patience": NO_STOP_RULE,
    }
    if args.scenario == "ring":
        options.update(
            ring_length=args.ring_length, vehicles=args.vehicles, human_model=args.humans
        )
    elif args.flow is not None:
        options["flow"] = args.flow
    return options


def measure(
    address: str, args: argparse.Namespace, choices: list[DriverChoice]
) -> tuple[list[dict[str, Any]], dict[tuple[str, float], Trace]]:
    """Every (driver, share or count, seed) run: its figures; and the traces of the first seed."""
    ring = args.scenario == "ring"
    layout = RingOptions(ring_length=args.ring_length, vehicles=args.vehicles)

    def start_of(vehicle: str) -> float:
        if not ring:
            return VEHICLE_LENGTH
        if not vehicle.startswith("human"):
            raise RuntimeError(f"unexpected vehicle {vehicle!r} on the ring")
        return layout.ring_position(int(vehicle.removeprefix("human")))

    if ring:
        plan = ring_plan(args)
        length = args.ring_length
    else:
        plan = [(share, -1 if share else 0) for share in args.shares]  # -1: the share's
        length = CFLC_LENGTH
    baseline = DriverChoice(HUMAN, IDMDriver, "SUMO drives every ego as a human")
    jobs: list[tuple[DriverChoice, float, int]] = []
    for share, count in plan:
        if count == 0:
            jobs.append((baseline, share, 0))
        else:
            jobs.extend((choice, share, count) for choice in choices)
    runs: list[dict[str, Any]] = []
    traces: dict[tuple[str, float], Trace] = {}
    for choice, share, count in jobs:
        options: dict[str, Any] = scenario_options(args, choice.decision_interval)
        if count == 0:
            options["ego_driver"] = "sumo"
        max_steps = int(args.duration / choice.decision_interval) + 10
        many: dict[str, Any] = (
            {"egos": max(count, 1)} if ring else {"ego_share": share / 100 if count else 1.0}
        )
        env = RemoteParallelEnv(address, args.scenario, reward=_no_reward, **many, **options)
        try:
            for seed in range(1, args.seeds + 1):
                began = time.perf_counter()
                trace = Trace(count != 0, start_of, length if ring else None)
                handed_over = drive(env, seed, choice.make, trace, max_steps)
                wall = time.perf_counter() - began
                run: dict[str, Any] = {
                    "driver": choice.label,
                    "share_pct": round(100 * count / args.vehicles, 1) if ring else share,
                    "egos": count if ring else len(trace.agents),
                    "seed": seed,
                    "wall_s": round(wall, 1),
                    "figures": figures(trace, args.scenario, length, args.tail),
                }
                if choice.policy is not None:
                    run["features_at_handover"] = policy_features(choice.policy, handed_over)
                runs.append(run)
                if seed == 1:
                    traces[(choice.label, share)] = trace
                print(progress(runs[-1], ring), flush=True)
        finally:
            env.close()
    return runs, traces


def progress(run: dict[str, Any], ring: bool) -> str:
    f = run["figures"]
    what = f"{run['share_pct']:5.1f} %" if ring else f"{run['egos']:2d} egos"

    def num(value: float | None, form: str, scale: float = 1.0) -> str:
        return "-" if value is None else f"{scale * value:{form}}"

    return (
        f"{run['driver']:>12} {what} seed {run['seed']}: {f['window_s']:.0f} s, mean speed "
        f"{num(f['mean_speed'], '.2f')} m/s, speed std {num(f['speed_std'], '.2f')} (humans "
        f"{num(f['speed_std_humans'], '.2f')}) m/s, throughput {num(f['throughput'], '.0f')} "
        f"veh/h, stopped {num(f['stopped_share'], '.1f', 100)} %, collisions "
        f"{f['collisions']}, ends {f['ego_ends'] or '-'}, vehicles {f['vehicles_start']} -> "
        f"{f['vehicles_end']} ({run['wall_s']:.1f} s)"
    ) + "".join(
        f"\n    collision at {c['t_s']} s: {c['ego']} and {c['with']} ({c['how']})"
        for c in f["collision_list"]
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--scenario", choices=("ring", "cflc"), default="ring")
    parser.add_argument(
        "--driver", nargs="+", default=["idm"],
        help="idm and/or policy files (runs/NAME/policy.pt); each drives every share",
    )  # fmt: skip
    parser.add_argument("--shares", type=float, nargs="+", default=list(SHARES), help="%%")
    parser.add_argument(
        "--diagram-shares", type=float, nargs="+", default=[50.0, 100.0],
        help="%% shown in the ring's time-space diagram beside the all-human ring",
    )  # fmt: skip
    parser.add_argument(
        "--diagram-seconds", type=float, default=150.0,
        help="s after the hand-over the time-space diagram shows",
    )  # fmt: skip
    parser.add_argument("--seeds", type=int, default=3, help="seeds 1..N")
    parser.add_argument("--warmup", type=float, help="s (default: ring 300, cflc 150)")
    parser.add_argument("--duration", type=float, default=300.0, help="max_episode_time (s)")
    parser.add_argument(
        "--tail", type=float, default=60.0, help="s at the end for the _tail figures"
    )
    parser.add_argument("--ring-length", type=float, default=230.0, help="m")
    parser.add_argument("--vehicles", type=int, default=22, help="on the ring")
    parser.add_argument("--humans", choices=("eidm", "idm", "krauss"), default="eidm")
    parser.add_argument("--flow", type=float, help="cflc: veh/h per lane (default: cflc's 700)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    if args.flow is not None and args.scenario != "cflc":
        parser.error("--flow is an option of cflc (the ring's density is --vehicles)")
    if args.warmup is None:
        args.warmup = 300.0 if args.scenario == "ring" else 150.0
    if any(not 0.0 <= share <= 100.0 for share in args.shares):
        parser.error(f"--shares must be within 0..100 %, got {args.shares}")
    if 0.0 not in args.shares:
        args.shares = [0.0, *args.shares]
    choices = [choose_driver(spec, args.scenario) for spec in args.driver]
    for choice in choices:
        print(f"driver {choice.label}: {choice.note}", flush=True)
    began = time.perf_counter()
    cache = Path(tempfile.mkdtemp(prefix="av-bridge-mixed-"))
    try:
        with sim_server(cache) as address:
            runs, traces = measure(address, args, choices)
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    pair_with_baseline(runs)
    summary = summarise(runs)
    print(table(summary, args.scenario, args.tail))
    args.out.mkdir(parents=True, exist_ok=True)
    name = f"mixed_autonomy_{args.scenario}" + (f"_flow{args.flow:g}" if args.flow else "")
    notes = [choice.note for choice in choices]
    if args.scenario == "ring":
        errors = [r["figures"]["gap_check_max_error_m"] for r in runs]
        print(
            f"places on the ring checked against the reported gaps: max error {max(errors):.3f} m"
        )
        notes.append(
            "all-human baseline: one ego that SUMO drives as a human (ego_driver sumo); "
            "throughput past the seam from the odometers, Edie's flow = distance / (length x time)"
        )
    else:
        notes.append(
            "ego_share (protocol 1.5): that share of the vehicles on the road at the hand-over, "
            "then of each that enters; all-human baseline: ego_share 1 with ego_driver sumo "
            "(SUMO drives every ego as a human); figure ego_share: the mean share of the vehicles "
            "on the road the client drove; throughput = arrivals at the end of the road per "
            "hour, throughput_edie = vehicles past the 1 km mark per hour, over the episode"
        )
    notes.append(f"stop_patience {NO_STOP_RULE:g} s: the unreasonable-stop end rule is off")
    report = {
        "command": " ".join(["python", "benchmarks/mixed_autonomy.py", *sys.argv[1:]]),
        "machine": f"{platform.machine()}, {os.cpu_count()} cpus, Python "
        f"{platform.python_version()}",
        "wall_s": round(time.perf_counter() - began, 1),
        "scenario": args.scenario,
        "options": scenario_options(args, 0.1),
        "seeds": list(range(1, args.seeds + 1)),
        "stopped_below_ms": STOPPED_SPEED,
        "drivers": {choice.label: choice.note for choice in choices},
        "notes": notes,
        "summary": summary,
        "runs": runs,
    }
    (args.out / f"{name}.json").write_text(json.dumps(report, indent=1) + "\n")
    pictures = [args.out / f"{name}_figures.png"]
    seeds = f"seeds 1-{args.seeds}" if args.seeds > 1 else "seed 1"
    title = (
        f"{args.scenario}: egos driven by {', '.join(c.label for c in choices)}; mean over "
        f"{seeds} with min-max; dotted: all humans; hollow: egos crashed (and left the road)"
    )
    plot_figures(summary, args.scenario, pictures[0], title)
    if args.scenario == "ring":
        chosen = [(share, n) for share, n in ring_plan(args) if n and share in args.diagram_shares]
        panels = {
            choice.label: [
                (f"{n} of {args.vehicles} egos", traces[(choice.label, share)])
                for share, n in chosen
            ]
            for choice in choices
        }
        pictures.insert(0, args.out / f"{name}.png")
        plot_time_space(
            traces[(HUMAN, 0.0)], panels, args.ring_length, RING_SPEED_LIMIT, pictures[0],
            args.diagram_seconds,
        )  # fmt: skip
    print(f"wrote {args.out / (name + '.json')}, " + ", ".join(map(str, pictures)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
