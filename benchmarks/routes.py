"""Who reaches the end of the route where lanes end? Drivers on merge, exit and lanedrop.

Starts a real SUMO server on a free loopback port and drives every driver (IDM + MOBIL, SUMO's
own driver, IDM, and any policy file given) on the same seeds of each scenario, through the
bridge; prints a table per scenario (the share of episodes that reached the end of the route,
stood at a lane end or collided, the average speed, the route changes and the gaps accepted,
the braking imposed on the new follower) and writes JSON.

    python benchmarks/routes.py --episodes 50
    python benchmarks/routes.py --scenario merge --policy runs/roads/policy.pt --episodes 50
    python benchmarks/routes.py --sumocfg runs/grid/grid.sumocfg --ego-route ego   # your network

The seeds start at 200,000 (`agent-client evaluate`'s): no training run or its evaluations
drove them. This is a measurement, not a test: minutes per driver and scenario.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent_client.defaults import EVALUATION_SEED
from agent_client.drivers.spec import load_driver
from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import UsageError
from agent_client.evaluation.evaluate import evaluate_driver
from agent_client.evaluation.summaries import summarise
from protocol.readiness import LISTENING, stop_process, wait_for_line

SCENARIOS = ("merge", "exit", "lanedrop")
MODELS = ("idm+mobil", "sumo", "idm")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", nargs="+", default=list(SCENARIOS))
    parser.add_argument("--drivers", nargs="+", default=list(MODELS), help="model driver specs")
    parser.add_argument("--policy", nargs="*", default=[], help="policy files to drive too")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=EVALUATION_SEED)
    parser.add_argument(
        "--sumocfg", type=Path, help="drive this network instead (its stem is the scenario)"
    )
    parser.add_argument("--ego-route", default="ego", help="with --sumocfg: the ego's route id")
    parser.add_argument(
        "--out", type=Path, default=ROOT / "runs" / "benchmark" / "routes.json", help="JSON file"
    )
    args = parser.parse_args()
    specs = [*args.drivers, *args.policy]
    try:
        drivers = {spec: load_driver(spec) for spec in specs}
    except UsageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    seeds = list(range(args.seed, args.seed + args.episodes))
    network: list[str] = []
    if args.sumocfg is not None:
        network = ["--sumocfg", str(args.sumocfg), "--ego-route", args.ego_route]
        args.scenario = [args.sumocfg.stem]
    server = subprocess.Popen(
        [sys.executable, "-m", "sim_server.cli", "--bind", "tcp://127.0.0.1:0",
         "--log-level", "WARNING", *network],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
    )  # fmt: skip
    results: dict[str, dict[str, Any]] = {}
    try:
        address = wait_for_line(server, LISTENING, 120.0)
        for scenario in args.scenario:
            env = RemoteEnv(address, scenario, reward="safe")
            try:
                results[scenario] = {}
                for spec, driver in drivers.items():
                    started = time.perf_counter()
                    records = evaluate_driver(env, driver, seeds)
                    figures = summarise(records)
                    figures["seconds"] = time.perf_counter() - started
                    results[scenario][spec] = _kept(figures)
                    print(f"== {scenario}, {spec}: {_line(results[scenario][spec])}", flush=True)
            finally:
                env.close()
            print()
            print(table(scenario, results[scenario]))
            print()
    finally:
        stop_process(server)
    machine = f"{platform.node()} {platform.machine()}, {platform.python_version()}"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    payload = {"machine": machine, "seeds": [seeds[0], seeds[-1]], "results": results}
    args.out.write_text(json.dumps(payload, indent=2))
    print(f"wrote {args.out}")
    return 0


def _kept(figures: dict[str, Any]) -> dict[str, Any]:
    """The figures this benchmark reports (the rest of `summarise`'s are per-sample detail)."""
    keys = ("episodes", "average_speed", "collisions_per_episode", "episodes_with_collision",
            "jerk_share_above_limit", "headway_share_below_1s", "end_reasons", "route",
            "seconds")  # fmt: skip
    return {key: figures.get(key) for key in keys}


def _line(figures: dict[str, Any]) -> str:
    route = figures["route"] or {}
    arrived = route.get("arrival_share")
    return (
        f"arrived {_pct(arrived)}, {figures['episodes_with_collision']} with a collision, "
        f"{figures['average_speed']:.2f} m/s, ends {figures['end_reasons']} "
        f"({figures['seconds']:.0f} s)"
    )


def _pct(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.0f} %"


def _number(value: float | None, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def table(scenario: str, drivers: dict[str, dict[str, Any]]) -> str:
    lines = [
        f"### {scenario}",
        "",
        "| driver | reached the end | stood at a lane end | episodes with a collision | speed "
        "(m/s) | route changes / episode | m before the lane end (median) | gap to leader / "
        "from follower (s, median) | braking imposed (m/s², max) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for spec, figures in drivers.items():
        route = figures["route"] or {}
        lines.append(
            f"| `{spec}` | {_pct(route.get('arrival_share'))} "
            f"| {_pct(route.get('lane_end_share'))} | {figures['episodes_with_collision']} "
            f"| {figures['average_speed']:.2f} "
            f"| {_number(route.get('route_changes_per_episode'))} "
            f"| {_number(route.get('median_lane_end_at_change'), 0)} "
            f"| {_number(route.get('median_lead_headway'))} / "
            f"{_number(route.get('median_lag_headway'))} "
            f"| {_number(route.get('max_follower_braking'))} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
