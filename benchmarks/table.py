"""The table nobody tuned to: drivers x maps x seeded trips, every figure with a 95 % interval.

Trains nothing. Drives every driver (policy files, ``pretrained:NAME``, ``idm``, ``idm+mobil``,
``sumo``) on every map over the same test seeds (benchmarks/test_seeds.json, fixed before any
result on them), through real ``sim-server`` processes, and prints per map and driver:

* arrivals (share of trips that reached the end of their route), collisions, red lights passed
  (share of trips with one; Wilson intervals);
* mean speed (m/s, over trips; a t-interval), and the paired difference to the faster of
  IDM + MOBIL and SUMO's own driver on the same trips (a t-interval of the differences);
* travel time of the trips that arrived (s);
* shares of time headways under 1 s and of jerk samples above 5.6 m/s³, and the share of steps
  the safety layer drove (pooled over the trips; bootstrap intervals over trips), by rule;
* lane changes started by the driver, and the share of them that are its own: IDM + MOBIL,
  asked afresh on the same observation, would not have made that change (bootstrap interval).

Maps: the built-in scenarios (``cflc``, ``merge``, ``exit``, ``lanedrop``, ``urban``; ``cf`` on
request), networks SUMO ships with eclipse-sumo (``sumo:A10KW``, a motorway interchange from
OpenStreetMap; ``sumo:bs3d``, Braunschweig's inner city; ``sumo:ramp``; ``sumo:DRT``, a town
from OpenStreetMap), and yours (``--net FILE``, ``--osm FILE``). Each map is served by a server
of its own (``--workers 2``: the trips are spread over two simulators), started and stopped
here.

    python benchmarks/table.py --episodes 50                  # the default grid, baselines only
    python benchmarks/table.py --policy pretrained:roads --episodes 50
    python benchmarks/table.py --maps urban sumo:bs3d --osm town.osm --drivers idm+mobil sumo \
        --episodes 100
    python benchmarks/table.py --rows-of pretrained:cflc --tables benchmarks/results/table-*.json
    python benchmarks/table.py --maps cflc --drivers idm+mobil --policy runs/a/policy.pt \
        runs/b/policy.pt --tuning-seeds 300000 --episodes 100   # choosing: not the test seeds

Writes benchmarks/results/table-DATE.json (``--out``) and a picture beside it. This is a
measurement, not a test: an hour and more for the default grid.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent_client.drivers.episode import run_episode
from agent_client.drivers.mobil import IDMMobilDriver
from agent_client.drivers.spec import load_driver
from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import ServerError, UsageError
from agent_client.evaluation.metrics import EpisodeSummary, episode_summary, safety_rule_shares
from protocol.errors import ErrorCode
from protocol.messages import EndReason, Observation
from protocol.readiness import LISTENING, stop_process, wait_for_line

BUILT_IN = ("cflc", "merge", "exit", "lanedrop", "urban")
ONE_LANE = ("cf",)
"""Built-in too, but not in the default grid: the paper's first case, one lane."""
SHIPPED = {
    "A10KW": "A10KW/osm.net.xml",
    "bs3d": "bs3d/bs.net.xml",
    "ramp": "ramp/ramp.net.xml",
    "DRT": "DRT/osm.net.xml",
}
"""Networks eclipse-sumo ships in tools/game (``sumo:NAME``)."""
DEFAULT_SHIPPED = ("ramp", "DRT")
"""Not ``A10KW`` and ``bs3d`` by default: their signals are the game's, each phase 10,000 s and
1,000 s long (a player switches them), and two thirds of their trips jam behind them whoever
drives (docs/results.md, "Your own map")."""
BASELINES = ("idm", "idm+mobil", "sumo")
STRONG = ("idm+mobil", "sumo")
"""The baselines a policy's speed is compared with, the faster of them per map."""
SEEDS_FILE = ROOT / "benchmarks" / "test_seeds.json"
Z95 = 1.959963984540054
BOOTSTRAP = 2000
SIMULATOR_ERROR = "simulator_error"
"""The end of a trip SUMO itself failed in: not arrived."""


@dataclass(frozen=True)
class Map:
    """A row group of the table: the scenario clients reset, and the server that offers it."""

    name: str
    scenario: str
    server_args: tuple[str, ...] = ()
    options: tuple[tuple[str, Any], ...] = ()


def main() -> int:
    # A kill ends the run as an exception does: its servers are stopped, not orphaned.
    signal.signal(signal.SIGTERM, lambda number, frame: sys.exit(128 + number))
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--maps", nargs="*", default=[*BUILT_IN, *(f"sumo:{n}" for n in DEFAULT_SHIPPED)]
    )
    parser.add_argument("--net", nargs="*", type=Path, default=[], help="your SUMO networks")
    parser.add_argument("--osm", nargs="*", type=Path, default=[], help="your OSM exports")
    parser.add_argument("--drivers", nargs="*", default=list(BASELINES))
    parser.add_argument("--policy", nargs="*", default=[], help="policy files or pretrained:NAME")
    parser.add_argument("--episodes", type=int, default=50, help="test seeds per map (<= 100)")
    parser.add_argument("--option", nargs="*", default=[], help="KEY=VALUE for every reset")
    parser.add_argument(
        "--tuning-seeds",
        type=int,
        metavar="FIRST",
        help="seeds FIRST.. instead of the test seeds: to choose among candidates",
    )
    parser.add_argument("--out", type=Path, help="JSON file (default benchmarks/results/...)")
    parser.add_argument(
        "--rows-of", metavar="DRIVER", help="drive nothing: print DRIVER's rows of --tables"
    )
    parser.add_argument("--tables", nargs="*", type=Path, default=[], help="with --rows-of")
    parser.add_argument("--replot", type=Path, help="drive nothing: draw a table file's picture")
    args = parser.parse_args()
    if args.replot:
        if not args.replot.is_file():
            print(f"error: --replot: no such file: {args.replot}", file=sys.stderr)
            return 2
        drawn = json.loads(args.replot.read_text())["results"]
        picture(args.replot.with_suffix(".png"), drawn, list(next(iter(drawn.values()))))
        print(f"wrote {args.replot.with_suffix('.png')}")
        return 0
    if args.rows_of:
        missing = [p for p in args.tables if not p.is_file()]
        if not args.tables or missing:
            what = f"no such file: {missing[0]}" if missing else "give the --tables"
            print(f"error: --rows-of: {what}", file=sys.stderr)
            return 2
        print(card_rows(args.rows_of, args.tables))
        return 0
    try:
        maps = [*map(parse_map, args.maps), *(user_map(p, "--net") for p in args.net)]
        maps += [user_map(p, "--osm") for p in args.osm]
        specs = [*args.drivers, *args.policy]
        for spec in specs:
            load_driver(spec)  # a typo stops here, before any server starts
        seeds = json.loads(SEEDS_FILE.read_text())["seeds"][: args.episodes]
        if args.tuning_seeds is not None:  # for choosing among candidates: never the test seeds
            seeds = list(range(args.tuning_seeds, args.tuning_seeds + args.episodes))
            if set(seeds) & set(json.loads(SEEDS_FILE.read_text())["seeds"]):
                raise UsageError(f"--tuning-seeds {args.tuning_seeds}: overlaps the test seeds")
        if len(seeds) < args.episodes:
            raise UsageError(f"--episodes {args.episodes}: the test seeds are {len(seeds)}")
        extra = dict(parse_option(o) for o in args.option)
    except UsageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = args.out or ROOT / "benchmarks" / "results" / f"table-{time.strftime('%Y-%m-%d')}.json"
    results: dict[str, dict[str, Any]] = {}
    started = time.monotonic()
    for spot in maps:
        print(f"== {spot.name}: {len(specs)} drivers x {len(seeds)} trips", flush=True)
        episodes = drive_map(spot, specs, seeds, extra)
        results[spot.name] = figures_of(episodes, specs)
        print(table_of(spot.name, results[spot.name], specs), flush=True)
        save(out, args, seeds, results, started)
    whole = overall(results, specs)
    print(overall_text(whole, specs))
    save(out, args, seeds, results, started, whole)
    picture(out.with_suffix(".png"), results, specs)
    print(f"wrote {out} and {out.with_suffix('.png')}")
    return 0


def parse_map(name: str) -> Map:
    if name in BUILT_IN or name in ONE_LANE:
        return Map(name, name)
    if name.startswith("sumo:"):
        import sumo

        path = SHIPPED.get(name.removeprefix("sumo:"))
        if path is None:
            raise UsageError(f"map {name!r}: SUMO ships {', '.join('sumo:' + n for n in SHIPPED)}")
        net = Path(sumo.SUMO_HOME) / "tools" / "game" / path
        return Map(name, "map", ("--net", str(net), "--scenario-name", "map"))
    raise UsageError(
        f"map {name!r}: one of {', '.join(BUILT_IN)}, sumo:NAME, or --net FILE / --osm FILE"
    )


def user_map(path: Path, flag: str) -> Map:
    if not path.is_file():
        raise UsageError(f"{flag} {path}: no such file")
    return Map(path.name, "map", (flag, str(path), "--scenario-name", "map"))


def parse_option(text: str) -> tuple[str, Any]:
    key, sep, value = text.partition("=")
    if not sep:
        raise UsageError(f"--option {text!r}: expected KEY=VALUE")
    for kind in (int, float):
        try:
            return key, kind(value)
        except ValueError:
            pass
    return key, {"true": True, "false": False}.get(value.lower(), value)


def drive_map(
    spot: Map, specs: Sequence[str], seeds: Sequence[int], extra: dict[str, Any]
) -> dict[str, list[EpisodeSummary]]:
    """Every driver over every seed of one map, the seeds spread over two simulators."""
    command = [sys.executable, "-m", "sim_server.cli", "--bind", "tcp://127.0.0.1:0",
               "--workers", "2", "--log-level", "WARNING", *spot.server_args]  # fmt: skip
    server = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    episodes: dict[str, list[EpisodeSummary]] = {spec: [] for spec in specs}
    try:
        addresses = [wait_for_line(server, LISTENING, 300.0) for _ in range(2)]
        halves = [seeds[0::2], seeds[1::2]]
        found: list[dict[str, list[EpisodeSummary]]] = [{}, {}]
        errors: list[BaseException] = []
        progress = Progress(spot.name, len(seeds))

        def work(k: int) -> None:
            try:
                found[k] = drive_seeds(addresses[k], spot, specs, halves[k], extra, progress)
            except BaseException as exc:  # reported below, with the map named
                errors.append(exc)

        threads = [threading.Thread(target=work, args=(k,)) for k in range(2)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        if errors:
            raise RuntimeError(f"map {spot.name}: {errors[0]}") from errors[0]
        for spec in specs:
            merged = found[0][spec] + found[1][spec]
            episodes[spec] = sorted(merged, key=lambda s: s.seed)
    finally:
        stop_process(server)
    return episodes


class Progress:
    """One line per tenth of a map's trips (every driver done on them), from both threads."""

    def __init__(self, name: str, total: int) -> None:
        self.name, self.total, self.done = name, total, 0
        self.started = time.monotonic()
        self.lock = threading.Lock()

    def trip_done(self) -> None:
        with self.lock:
            self.done += 1
            if self.done % max(1, self.total // 10) == 0 or self.done == self.total:
                minutes = (time.monotonic() - self.started) / 60
                line = f"   {self.name}: {self.done}/{self.total} trips, {minutes:.1f} min"
                print(line, flush=True)


def drive_seeds(
    address: str,
    spot: Map,
    specs: Sequence[str],
    seeds: Sequence[int],
    extra: dict[str, Any],
    progress: Progress,
) -> dict[str, list[EpisodeSummary]]:
    env = RemoteEnv(
        address, spot.scenario, reward="safe", reset_timeout_s=600.0, **dict(spot.options), **extra
    )
    found: dict[str, list[EpisodeSummary]] = {spec: [] for spec in specs}
    try:
        for seed in seeds:
            for spec in specs:
                found[spec].append(drive_trip(env, spec, seed))
            progress.trip_done()
    finally:
        env.close()
    return found


def drive_trip(env: RemoteEnv, spec: str, seed: int) -> EpisodeSummary:
    """One driver's trip; a trip SUMO itself fails in (a ``simulator_error`` reply: the server
    rebuilds its simulation at the next reset) is counted as not arrived, its speed that of the
    steps it drove, and the table goes on."""
    speeds: list[float] = []
    own = [0]
    driver = load_driver(spec)

    def record(
        before: Observation, action: tuple[float, int], reward: float, after: Observation
    ) -> None:
        speeds.append(after.ego.speed)
        override = getattr(driver, "override", None)
        layer_changed = override is not None and override.lane_change
        if after.events.lane_change_started and action[1] and not layer_changed:
            # IDM + MOBIL asked afresh (its next decision due now) on the same observation
            own[0] += IDMMobilDriver().act(before)[1] != action[1]

    try:
        summary = episode_summary(run_episode(env, driver, seed, on_step=record))
        return replace(summary, own_lane_changes=own[0])
    except ServerError as exc:
        if exc.code != ErrorCode.SIMULATOR_ERROR:
            raise
        print(f"   {spec}, seed {seed}: {exc.message} (counted as {SIMULATOR_ERROR})", flush=True)
        step = env.step_length or 0.1
        duration = len(speeds) * step
        return EpisodeSummary(
            episode=0, seed=seed, steps=len(speeds), reason=SIMULATOR_ERROR, duration=duration,
            distance=sum(speeds) * step,
            average_speed=float(np.mean(speeds)) if speeds else 0.0, collisions=0,
            jerk_share_above_limit=0.0, max_abs_jerk=0.0, headway_share_below_1s=0.0,
            min_time_headway=None, min_ttc=None, ceiling_speed=None, speed_ratio_to_ceiling=None,
            total_reward=0.0, lane_changes_started=0, lane_changes_refused=0,
        )  # fmt: skip


# ----------------------------------------------------------------------------- figures


def wilson(successes: int, total: int) -> list[float]:
    """95 % Wilson score interval of a share."""
    if total == 0:
        return [math.nan, math.nan]
    p = successes / total
    centre = (p + Z95**2 / (2 * total)) / (1 + Z95**2 / total)
    half = Z95 * math.sqrt(p * (1 - p) / total + Z95**2 / (4 * total**2)) / (1 + Z95**2 / total)
    return [max(0.0, centre - half), min(1.0, centre + half)]


def t_interval(values: Sequence[float]) -> list[float]:
    """95 % interval of a mean (normal approximation with the sample's standard error)."""
    data = np.asarray(values, dtype=float)
    if len(data) < 2:
        return [math.nan, math.nan]
    half = Z95 * data.std(ddof=1) / math.sqrt(len(data))
    return [float(data.mean() - half), float(data.mean() + half)]


def pooled_share(counts: Sequence[float], totals: Sequence[float]) -> tuple[float, list[float]]:
    """A share pooled over trips (sum of counts / sum of totals) and its bootstrap interval
    over trips."""
    c, t = np.asarray(counts, dtype=float), np.asarray(totals, dtype=float)
    if t.sum() == 0:
        return 0.0, [0.0, 0.0]
    rng = np.random.default_rng(0)
    picks = rng.integers(0, len(c), size=(BOOTSTRAP, len(c)))
    sums = t[picks].sum(axis=1)
    shares = np.where(sums > 0, c[picks].sum(axis=1) / np.maximum(sums, 1e-12), 0.0)
    return float(c.sum() / t.sum()), [
        float(np.quantile(shares, 0.025)),
        float(np.quantile(shares, 0.975)),
    ]


def figures_of(episodes: dict[str, list[EpisodeSummary]], specs: Sequence[str]) -> dict[str, Any]:
    """Each driver's figures on one map, and its paired speed difference to the strong
    baselines driven here."""
    table: dict[str, Any] = {}
    for spec in specs:
        runs = episodes[spec]
        n = len(runs)
        arrived = [r for r in runs if r.reason == EndReason.END_OF_ROAD]
        speeds = [r.average_speed for r in runs]
        headway, headway_ci = pooled_share(
            [r.headway_share_below_1s * r.headway_samples for r in runs],
            [r.headway_samples for r in runs],
        )
        jerk, jerk_ci = pooled_share(
            [r.jerk_share_above_limit * r.steps for r in runs], [r.steps for r in runs]
        )
        layer, layer_ci = pooled_share([r.safety_steps for r in runs], [r.steps for r in runs])
        changes = [r.lane_changes_started - r.safety_lane_changes for r in runs]
        own, own_ci = pooled_share([r.own_lane_changes or 0 for r in runs], changes)
        table[spec] = {
            "trips": n,
            "arrivals": len(arrived) / n,
            "arrivals_ci": wilson(len(arrived), n),
            "collisions": sum(r.collisions > 0 for r in runs) / n,
            "collisions_ci": wilson(sum(r.collisions > 0 for r in runs), n),
            "red_lights": sum(r.red_lights > 0 for r in runs) / n,
            "red_lights_ci": wilson(sum(r.red_lights > 0 for r in runs), n),
            "red_lights_passed": sum(r.red_lights for r in runs),
            "speed": float(np.mean(speeds)),
            "speed_ci": t_interval(speeds),
            "travel_time": float(np.mean([r.duration for r in arrived])) if arrived else math.nan,
            "travel_time_ci": t_interval([r.duration for r in arrived]),
            "headway_below_1s": headway,
            "headway_below_1s_ci": headway_ci,
            "jerk_above_limit": jerk,
            "jerk_above_limit_ci": jerk_ci,
            "safety_layer": layer,
            "safety_layer_ci": layer_ci,
            "safety_rules": safety_rule_shares(runs),
            "lane_changes": sum(changes),
            "own_lane_changes": own,
            "own_lane_changes_ci": own_ci,
            "ends": {
                reason: sum(r.reason == reason for r in runs)
                for reason in sorted({r.reason for r in runs})
            },
            "per_trip": [[r.seed, r.reason, r.average_speed, r.duration] for r in runs],
        }
    strong = [s for s in STRONG if s in episodes]
    for spec in specs:
        for base in strong:
            if base == spec:
                continue
            diffs = [
                a.average_speed - b.average_speed
                for a, b in zip(episodes[spec], episodes[base], strict=True)
            ]
            table[spec][f"vs_{base}"] = {
                "difference": float(np.mean(diffs)),
                "ci": t_interval(diffs),
            }
    return table


def overall(results: dict[str, dict[str, Any]], specs: Sequence[str]) -> dict[str, Any]:
    """Over the whole table: each driver's mean speed over every trip, and the worst map."""
    whole: dict[str, Any] = {}
    for spec in specs:
        trips = [t for m in results.values() for t in m[spec]["per_trip"]]
        speeds = [t[2] for t in trips]
        whole[spec] = {
            "speed": float(np.mean(speeds)),
            "speed_ci": t_interval(speeds),
            "trips": len(trips),
        }
        for base in STRONG:
            if base != spec and all(base in m for m in results.values()):
                ratios = {name: m[spec]["speed"] / m[base]["speed"] for name, m in results.items()}
                whole[spec][f"worst_map_vs_{base}"] = min(ratios.items(), key=lambda kv: kv[1])
    return whole


# ----------------------------------------------------------------------------- output


def _ci(values: Sequence[float], digits: int = 2, scale: float = 1.0) -> str:
    low, high = values
    if math.isnan(low):
        return ""
    return f" [{scale * low:.{digits}f}, {scale * high:.{digits}f}]"


def _versus_faster(f: dict[str, Any]) -> str:
    """The paired speed difference to the faster strong baseline (the smaller difference), with
    its interval; "" for a baseline compared with nothing."""
    versus = [f[k] for k in (f"vs_{b}" for b in STRONG) if k in f]
    best = min(versus, key=lambda v: v["difference"]) if versus else None
    return f"{best['difference']:+.2f}{_ci(best['ci'])}" if best else ""


def _rules(f: dict[str, Any]) -> str:
    """The layer's share by rule, " (lane_end 2.61 %, standstill 0.01 %)"; "" where it never
    decided (or a table from before the rules were kept)."""
    rules = f.get("safety_rules") or {}
    return f" ({', '.join(f'{r} {100 * v:.2f} %' for r, v in rules.items())})" if rules else ""


def table_of(name: str, figures: dict[str, Any], specs: Sequence[str]) -> str:
    lines = [
        f"### {name}",
        "",
        "| driver | arrivals | collisions | red lights | speed, m/s | vs the faster baseline, m/s "
        "| travel time, s | headway < 1 s | jerk > 5.6 | safety layer | lane changes: own |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for spec in specs:
        f = figures[spec]
        vs = _versus_faster(f)
        own = (
            "n/a"  # SUMO changes its own driver's lanes: the bridge sees no request
            if spec == "sumo" or "lane_changes" not in f
            else f"{f['lane_changes']}: {100 * f['own_lane_changes']:.0f} %"
            f"{_ci(f['own_lane_changes_ci'], 0, 100)}"
            if f["lane_changes"]
            else "0"
        )
        lines.append(
            f"| `{spec}` | {100 * f['arrivals']:.0f} %{_ci(f['arrivals_ci'], 0, 100)} "
            f"| {100 * f['collisions']:.0f} %{_ci(f['collisions_ci'], 0, 100)} "
            f"| {100 * f['red_lights']:.0f} %{_ci(f['red_lights_ci'], 0, 100)} "
            f"| {f['speed']:.2f}{_ci(f['speed_ci'])} | {vs} "
            f"| {f['travel_time']:.0f}{_ci(f['travel_time_ci'], 0)} "
            f"| {100 * f['headway_below_1s']:.1f} %{_ci(f['headway_below_1s_ci'], 1, 100)} "
            f"| {100 * f['jerk_above_limit']:.2f} %{_ci(f['jerk_above_limit_ci'], 2, 100)} "
            f"| {100 * f['safety_layer']:.2f} %{_ci(f['safety_layer_ci'], 2, 100)}{_rules(f)} "
            f"| {own} |"
        )
    return "\n".join(lines) + "\n"


def card_rows(spec: str, tables: Sequence[Path]) -> str:
    """One driver's rows, one per map, of the table files given: a model card's table."""
    lines = [
        "| map | trips | arrivals | collisions | red lights | speed, m/s | vs the faster baseline, "
        "m/s | headway < 1 s | jerk > 5.6 | safety layer |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for path in tables:
        results = json.loads(path.read_text())["results"]
        for name, figures in results.items():
            f = figures.get(spec)
            if f is None:
                continue
            vs = _versus_faster(f)
            lines.append(
                f"| `{name}` | {f['trips']} | {100 * f['arrivals']:.0f} % "
                f"| {100 * f['collisions']:.0f} % | {100 * f['red_lights']:.0f} % "
                f"| {f['speed']:.2f}{_ci(f['speed_ci'])} | {vs} "
                f"| {100 * f['headway_below_1s']:.1f} % | {100 * f['jerk_above_limit']:.2f} % "
                f"| {100 * f['safety_layer']:.2f} % |"
            )
    return "\n".join(lines) + "\n"


def overall_text(whole: dict[str, Any], specs: Sequence[str]) -> str:
    lines = ["### the whole table", ""]
    for spec in specs:
        w = whole[spec]
        worst = "; ".join(
            f"worst map against {b}: {w[k][0]} {w[k][1]:.3f}x"
            for b in STRONG
            if (k := f"worst_map_vs_{b}") in w
        )
        lines.append(
            f"* `{spec}`: {w['speed']:.2f} m/s{_ci(w['speed_ci'])} over {w['trips']} trips; {worst}"
        )
    return "\n".join(lines) + "\n"


def save(
    out: Path, args: argparse.Namespace, seeds: Sequence[int], results: dict[str, Any],
    started: float, whole: dict[str, Any] | None = None,
) -> None:  # fmt: skip
    out.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "command": " ".join(sys.argv),
        "machine": f"{platform.node()} {platform.machine()}, Python {platform.python_version()}",
        "seeds": [seeds[0], seeds[-1]],
        "minutes": (time.monotonic() - started) / 60,
        "results": results,
        "whole": whole,
    }
    out.write_text(json.dumps(payload, indent=1) + "\n")


def picture(path: Path, results: dict[str, dict[str, Any]], specs: Sequence[str]) -> None:
    """Speed and arrivals per map and driver, with their 95 % intervals; the red lights, the
    collisions and the safety layer's share as numbers over the bars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(results)
    x = np.arange(len(names))
    width = 0.8 / max(len(specs), 1)
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(max(8, 1.6 * len(names)), 8), sharex=True)
    for k, spec in enumerate(specs):
        at = x - 0.4 + width * (k + 0.5)
        speed = [results[n][spec]["speed"] for n in names]
        low = [results[n][spec]["speed_ci"][0] for n in names]
        high = [results[n][spec]["speed_ci"][1] for n in names]
        errors = np.nan_to_num([np.subtract(speed, low), np.subtract(high, speed)])
        top.bar(at, speed, width, yerr=errors, capsize=2, label=spec)
        arrive = [100 * results[n][spec]["arrivals"] for n in names]
        a_low = [100 * results[n][spec]["arrivals_ci"][0] for n in names]
        a_high = [100 * results[n][spec]["arrivals_ci"][1] for n in names]
        bottom.bar(
            at,
            arrive,
            width,
            yerr=[np.subtract(arrive, a_low), np.subtract(a_high, arrive)],
            capsize=2,
        )
        for i, n in enumerate(names):
            f = results[n][spec]
            marks = []
            if f["collisions"]:
                marks.append(f"C{100 * f['collisions']:.0f}%")
            if f["red_lights"]:
                marks.append(f"R{100 * f['red_lights']:.0f}%")
            if f["safety_layer"]:
                marks.append(f"S{100 * f['safety_layer']:.1f}%")
            if marks:
                bottom.text(
                    at[i], 2, "\n".join(marks), ha="center", va="bottom", fontsize=7, rotation=90
                )
    lows = [results[n][spec]["speed_ci"][0] for n in names for spec in specs]
    finite = [v for v in lows if math.isfinite(v)]
    if finite:  # the differences are what matters: the axis starts near the slowest
        top.set_ylim(bottom=max(0.0, 0.9 * min(finite)))
    top.set_ylabel("mean speed, m/s (95 % interval)")
    top.legend(ncol=min(len(specs), 5), fontsize=8, loc="lower center", bbox_to_anchor=(0.5, 1.0))
    bottom.set_ylabel("trips that arrived, % (95 % interval)")
    bottom.set_ylim(0, 105)
    bottom.set_xticks(x, names, rotation=20)
    fig.suptitle(
        "Drivers on every map, the same test trips (C: collisions, R: red lights, S: safety layer)",
        y=0.995,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
