"""Do the SUMO ring's human drivers form stop-and-go waves? Speed spread, stops, a picture.

Runs the built-in ``ring`` scenario (Sugiyama et al. 2008: 22 vehicles on 230 m, one lane, all
placed evenly and at rest at time 0) in this process through `SumoBackend`, with the ego driven

* ``sumo`` - by SUMO as one more human driver (``ego_driver="sumo"``): the all-human ring;
* ``idm``  - by the client's IDM (`agent_client.drivers.idm`, its default parameters) through
  the backend's protocol calls, as a learner would drive it.

Every 0.1 s it reads every human vehicle's speed and place on the ring from libsumo directly
(the protocol shows only the ego's neighbours) and prints, per time window, the humans' speed
standard deviation across vehicles (the spread a wave makes: 0 in uniform flow), their mean
speed and the share of their time stopped (slower than 1 m/s); per seed, when the spread first
exceeded 1 m/s and how fast the jam travels; then one line over all seeds. It writes a
time-space diagram (place on the ring against time, coloured by speed) of the first seed and the
figures as JSON into benchmarks/results/ring_waves_HUMANS_EGO.{png,json}. ``--humans`` picks
the ring's ``human_model`` (eidm, the default, idm or krauss).

    python benchmarks/ring_waves.py                       # ego sumo, 5 seeds, 600 s each
    python benchmarks/ring_waves.py --ego idm --seeds 3 --duration 300
    python benchmarks/ring_waves.py --humans krauss        # cf's humans: no waves form

A measurement, not a test; every figure is simulated time, so the machine's load does not
matter (a run of 5 x 600 s takes a few seconds).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import libsumo

from agent_client.drivers.idm import IDMDriver
from protocol.messages import Observation
from sim_server.backends.sumo.backend import SumoBackend
from sim_server.backends.sumo.scenarios import (
    EGO_ID,
    RING_EDGES,
    RING_HUMAN_MODELS,
    RING_SPEED_LIMIT,
)

RESULTS = ROOT / "benchmarks" / "results"
STOPPED = 1.0
"""A vehicle slower than this (m/s) counts as stopped (the bridge's default ``stop_speed``)."""
WAVE_STD = 1.0
"""A 10 s window whose mean speed spread exceeds this (m/s) has a wave."""


@dataclass
class Trace:
    """What the humans did, one row per 0.1 s step: time, speeds, places on the ring."""

    times: list[float] = field(default_factory=list)
    speeds: list[list[float]] = field(default_factory=list)
    places: list[list[float]] = field(default_factory=list)
    ego_places: list[float] = field(default_factory=list)

    def record(self, ring_length: float) -> None:
        """The humans' speeds and every vehicle's place now (ids in a fixed order)."""
        vehicle = libsumo.vehicle
        humans = sorted(v for v in vehicle.getIDList() if v != EGO_ID)
        self.times.append(libsumo.simulation.getTime())
        self.speeds.append([vehicle.getSpeed(v) for v in humans])
        self.places.append([_ring_place(v, ring_length) for v in humans])
        self.ego_places.append(_ring_place(EGO_ID, ring_length))


def _ring_place(vehicle_id: str, ring_length: float) -> float:
    """Metres from the start of edge ``a`` to the vehicle's front."""
    position = libsumo.vehicle.getLanePosition(vehicle_id)
    on_b = libsumo.vehicle.getRoadID(vehicle_id) == RING_EDGES[1]
    return position + (ring_length / 2 if on_b else 0.0)


def run(backend: SumoBackend, seed: int, args: argparse.Namespace) -> Trace:
    """One ring episode of ``args.duration`` s from the even placement (no warm-up)."""
    info = {s.name: s for s in backend.scenarios()}["ring"]
    options = {**info.options, "warmup": 0.0, "max_episode_time": args.duration}
    options.update(ring_length=args.ring_length, human_model=args.humans)
    ego, ring_length = args.ego, args.ring_length
    if ego == "sumo":
        options["ego_driver"] = "sumo"
    obs, trace, driver = backend.reset("ring", seed, options), Trace(), IDMDriver()
    seq = 0
    while not (obs.terminated or obs.truncated):
        trace.record(ring_length)
        seq += 1
        obs = _step(backend, driver, obs, seq)
    return trace


def _step(backend: SumoBackend, driver: IDMDriver, obs: Observation, seq: int) -> Observation:
    acceleration, _ = driver.act(obs)  # ignored when SUMO drives the ego
    return backend.step(seq, acceleration, 0)


def windows(trace: Trace, width: float) -> list[dict[str, float]]:
    """Per window of `width` s: the humans' mean speed spread, mean speed, share stopped."""
    times, speeds = np.array(trace.times), np.array(trace.speeds)
    rows = []
    for start in np.arange(0.0, times[-1], width):
        inside = (times >= start) & (times < start + width)
        chunk = speeds[inside]
        rows.append(
            {
                "start": float(start),
                "end": float(start + width),
                "speed_std": float(chunk.std(axis=1).mean()),
                "mean_speed": float(chunk.mean()),
                "stopped_share": float((chunk < STOPPED).mean()),
            }
        )
    return rows


def wave_onset(trace: Trace) -> float | None:
    """The start of the first 10 s window whose speed spread exceeds `WAVE_STD` (None: none)."""
    for row in windows(trace, 10.0):
        if row["speed_std"] > WAVE_STD:
            return row["start"]
    return None


def jam_speed(trace: Trace, ring_length: float, since: float) -> float | None:
    """How fast the stop-and-go jam travels (m/s, negative: against the traffic), after `since`.

    Each time a human slows below `STOPPED` is a stop (its time and place); the next stop, of
    the vehicle behind, happens within seconds further upstream. The median of place over time
    between consecutive stops less than 5 s apart is the jam's speed (None without stops)."""
    times, speeds = np.array(trace.times), np.array(trace.speeds)
    places = np.array(trace.places)
    below = speeds < STOPPED
    onset = below[1:] & ~below[:-1] & (times[1:, None] >= since)
    rows, columns = np.nonzero(onset)
    order = np.argsort(times[1:][rows], kind="stable")
    t = times[1:][rows][order]
    x = places[1:][rows, columns][order]
    dt, dx = np.diff(t), np.diff(x)
    dx = (dx + ring_length / 2) % ring_length - ring_length / 2  # across the seam
    close = (dt > 0) & (dt < 5.0)
    return float(np.median(dx[close] / dt[close])) if close.any() else None


def plot(trace: Trace, ring_length: float, path: Path, title: str) -> None:
    """Time-space diagram: every human's place on the ring against time, coloured by speed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    times = np.array(trace.times)
    places, speeds = np.array(trace.places), np.array(trace.speeds)
    every = 5  # 0.5 s
    fig, ax = plt.subplots(figsize=(11, 5), dpi=110)
    t = np.repeat(times[::every, None], places.shape[1], axis=1)
    dots = ax.scatter(
        t.ravel(), places[::every].ravel(), c=speeds[::every].ravel(),
        s=1.5, cmap="RdYlGn", vmin=0.0, vmax=RING_SPEED_LIMIT, linewidths=0,
    )  # fmt: skip
    ego = np.array(trace.ego_places[::every])
    ax.scatter(times[::every], ego, s=0.6, c="k", linewidths=0, label="ego")
    ax.set(xlabel="time (s)", ylabel="place on the ring (m)", title=title)
    ax.set_ylim(0, ring_length)
    ax.set_xlim(0, times[-1])
    fig.colorbar(dots, ax=ax, label="speed (m/s)")
    ax.legend(loc="upper right", markerscale=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def summary(traces: dict[int, Trace], width: float, ring_length: float) -> dict[str, Any]:
    """The per-seed windows, onsets and jam speeds (over the second half), and the last
    window's figures over all seeds."""
    per_seed = {seed: windows(trace, width) for seed, trace in traces.items()}
    last = [rows[-1] for rows in per_seed.values()]
    since = traces[min(traces)].times[-1] / 2
    return {
        "windows": per_seed,
        "wave_onset_s": {seed: wave_onset(trace) for seed, trace in traces.items()},
        "jam_speed_kmh": {
            seed: None if (v := jam_speed(trace, ring_length, since)) is None else 3.6 * v
            for seed, trace in traces.items()
        },
        "last_window": {
            key: [row[key] for row in last] for key in ("speed_std", "mean_speed", "stopped_share")
        },
    }


def print_table(
    seed: int, rows: list[dict[str, float]], onset: float | None, jam: float | None
) -> None:
    jam_text = "no jam" if jam is None else f"the jam travels at {jam:+.1f} km/h"
    print(f"seed {seed}: spread > {WAVE_STD:g} m/s from t = {onset} s; {jam_text}")
    print("  window (s)   speed std (m/s)   mean speed (m/s)   stopped (< 1 m/s)")
    for row in rows:
        print(
            f"  {row['start']:4.0f}-{row['end']:4.0f}   {row['speed_std']:15.2f}   "
            f"{row['mean_speed']:16.2f}   {100 * row['stopped_share']:16.1f} %"
        )


def print_overall(result: dict[str, Any]) -> None:
    """One line over all seeds: onsets, the last window's spread and stops, the jam speeds."""
    onsets = [v for v in result["wave_onset_s"].values() if v is not None]
    jams = [v for v in result["jam_speed_kmh"].values() if v is not None]
    last = result["last_window"]
    seeds = len(result["wave_onset_s"])

    def span(values: list[float], scale: float = 1.0, form: str = ".2f") -> str:
        return f"{min(values) * scale:{form}}-{max(values) * scale:{form}}" if values else "none"

    stopped = span(last["stopped_share"], 100, ".1f")
    print(
        f"over {seeds} seeds: waves (spread > {WAVE_STD:g} m/s) in {len(onsets)}, from "
        f"t = {span(onsets, form='.0f')} s; last window: speed std {span(last['speed_std'])} "
        f"m/s, mean speed {span(last['mean_speed'])} m/s, stopped {stopped} %; "
        f"jam speed {span(jams, form='.1f')} km/h"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--ego", choices=("sumo", "idm"), default="sumo")
    parser.add_argument("--seeds", type=int, default=5, help="seeds 1..N")
    parser.add_argument("--duration", type=float, default=600.0, help="simulated s per seed")
    parser.add_argument("--window", type=float, default=60.0, help="s per table row")
    parser.add_argument("--ring-length", type=float, default=230.0, help="m")
    parser.add_argument("--humans", choices=tuple(RING_HUMAN_MODELS), default="eidm")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as cache:
        backend = SumoBackend(cache_dir=Path(cache))
        try:
            traces = {seed: run(backend, seed, args) for seed in range(1, args.seeds + 1)}
        finally:
            backend.close()
    result = summary(traces, args.window, args.ring_length)
    for seed, rows in result["windows"].items():
        print_table(seed, rows, result["wave_onset_s"][seed], result["jam_speed_kmh"][seed])
    print_overall(result)
    args.out.mkdir(parents=True, exist_ok=True)
    name = f"ring_waves_{args.humans}_{args.ego}"
    picture = args.out / f"{name}.png"
    title = (
        f"ring {args.ring_length:g} m, 22 vehicles, humans {args.humans}, "
        f"ego driven by {args.ego}, seed 1"
    )
    plot(traces[1], args.ring_length, picture, title)
    meta = {
        "ego": args.ego,
        "humans": args.humans,
        "ring_length_m": args.ring_length,
        "duration_s": args.duration,
        "window_s": args.window,
        "seeds": args.seeds,
    }
    (args.out / f"{name}.json").write_text(json.dumps({**meta, **result}, indent=1))
    print(f"wrote {picture}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
