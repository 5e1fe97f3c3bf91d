"""What does the bridge add to SUMO's own step on a city of thousands of vehicles?

The recognition state, the road ahead, the stop line, the next traffic light and the red-light
watch, every step, against bare libsumo stepping the very same traffic. In this process, on the
same network, seed and ego trip (SUMO's own driver drives the ego in both, so that the traffic
evolves identically):

* ``bare``   - after the reset (network loaded, warmed up, ego inserted), libsumo's own loop:
  ``simulationStep()``, ``--steps`` times;
* ``bridge`` - the same reset, then ``SumoBackend.step`` ``--steps`` times: each builds the
  observation a client receives;
* ``wire`` (with ``--wire``) - the same through a real ``sim-server`` over ``direct://``, the
  client decoding each observation: the whole bridge a user runs.

The machine may be shared: the variants alternate, round after round, and the overhead is given
per round (median and range). The network is the built-in city at its largest grid (12 x 12
junctions, two lanes each way, heavy traffic), or yours (``--net``, ``--osm``).

    python benchmarks/city_cost.py                        # the 12 x 12 city
    python benchmarks/city_cost.py --osm town.osm --traffic 60 --save

This is a measurement, not a test.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent_client.transport import connect
from protocol.messages import Hello, Observation, Reset, Step
from protocol.readiness import LISTENING, stop_process, wait_for_line
from protocol.version import PROTOCOL_VERSION
from sim_server.backends.sumo.backend import SumoBackend
from sim_server.backends.sumo.maps import MapNetwork, MapScenario, build_osm

BIG_CITY: dict[str, Any] = {
    "columns": 12,
    "rows": 12,
    "block_length": 200.0,
    "lanes": 2,
    "street_speed": 50 / 3.6,
    "cycle_time": 90.0,
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--net", type=Path, help="a SUMO network instead of the built-in city")
    parser.add_argument("--osm", type=Path, help="an OpenStreetMap export instead")
    parser.add_argument("--traffic", type=float, default=120.0, help="veh/h per lane-km")
    parser.add_argument("--warmup", type=float, default=300.0, help="s before measuring")
    parser.add_argument("--steps", type=int, default=300, help="steps per variant and round")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--wire", action="store_true", help="also through sim-server (direct://)")
    parser.add_argument("--save", action="store_true", help="write benchmarks/results/")
    args = parser.parse_args()
    cache = Path(tempfile.mkdtemp(prefix="city-cost-"))
    scenario, custom, extra = "urban", (), dict(BIG_CITY)
    if args.net or args.osm:
        net = build_osm(args.osm, cache) if args.osm else args.net
        scenario, extra = "map", {}
        custom = (MapScenario("map", "your map", MapNetwork.of(net, cache)),)
    backend = SumoBackend(cache_dir=cache, custom=custom)
    info = {s.name: s for s in backend.scenarios()}[scenario]
    options = {
        **info.options,
        **extra,
        "traffic": args.traffic,
        "warmup": args.warmup,
        "ego_driver": "sumo",
        "ego_route_min": 1500.0,
        "ego_route_max": 6000.0,
        "max_episode_time": 3600.0,
        "report_ceiling": False,
    }
    rounds: dict[str, list[float]] = {"bare": [], "bridge": [], "wire": []}
    vehicles: list[int] = []
    server = client = None
    if args.wire:
        server, client = start_wire(cache, custom, args)
    try:
        for _ in range(args.rounds):
            backend.reset(scenario, args.seed, options)
            api = backend._api
            vehicles.append(api.vehicle.getIDCount())
            start = time.perf_counter()
            for _ in range(args.steps):
                api.simulationStep()
            rounds["bare"].append((time.perf_counter() - start) / args.steps)
            obs = backend.reset(scenario, args.seed, options)
            start = time.perf_counter()
            for seq in range(1, args.steps + 1):
                obs = backend.step(seq, 0.0, 0)
            rounds["bridge"].append((time.perf_counter() - start) / args.steps)
            assert not obs.reason, f"the ego's drive ended early ({obs.reason}): longer trip"
            if client is not None:
                asked = {k: v for k, v in options.items() if info.options.get(k) != v}
                rounds["wire"].append(wire_round(client, scenario, args.seed, asked, args.steps))
            print(
                f"round {len(vehicles)}: {vehicles[-1]} vehicles, bare "
                f"{1e3 * rounds['bare'][-1]:.3f} ms/step, bridge {1e3 * rounds['bridge'][-1]:.3f}"
                + (f", wire {1e3 * rounds['wire'][-1]:.3f}" if rounds["wire"] else ""),
                flush=True,
            )
    finally:
        backend.close()
        if client is not None:
            client.close()
        if server is not None:
            stop_process(server)
    result = summarise(rounds, vehicles, args)
    print(json.dumps(result["overhead"], indent=2))
    if args.save:
        out = ROOT / "benchmarks" / "results" / f"city-cost-{time.strftime('%Y-%m-%d')}.json"
        out.write_text(json.dumps(result, indent=2) + "\n")
        print(f"wrote {out}")
    return 0


def start_wire(cache: Path, custom: Any, args: argparse.Namespace) -> tuple[Any, Any]:
    """A sim-server on a free direct:// port serving the same network, and a client to it."""
    command = [sys.executable, "-m", "sim_server.cli", "--bind", "direct://127.0.0.1:0",
               "--cache-dir", str(cache), "--log-level", "WARNING"]  # fmt: skip
    if args.osm:
        command += ["--osm", str(args.osm), "--scenario-name", "map"]
    elif args.net:
        command += ["--net", str(args.net), "--scenario-name", "map"]
    server = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    address = wait_for_line(server, LISTENING, 120.0)
    client = connect(address, timeout_s=600.0)
    client.request(Hello(PROTOCOL_VERSION, "city_cost"))
    return server, client


def wire_round(client: Any, scenario: str, seed: int, options: dict[str, Any], steps: int) -> float:
    """Seconds per step through the server, the reset not counted."""
    client.request(Reset(scenario, seed, options), 600.0)
    start = time.perf_counter()
    for seq in range(1, steps + 1):
        reply = client.request(Step(seq, 0.0, 0))
        assert isinstance(reply, Observation) and not reply.reason
    return (time.perf_counter() - start) / steps


def summarise(
    rounds: dict[str, list[float]], vehicles: list[int], args: argparse.Namespace
) -> dict[str, Any]:
    """Per-round overheads against bare SUMO: median, lowest and highest."""
    overhead: dict[str, Any] = {
        "vehicles": statistics.median(vehicles),
        "bare_ms_per_step": 1e3 * statistics.median(rounds["bare"]),
    }
    for name in ("bridge", "wire"):
        if not rounds[name]:
            continue
        ratios = [b / a - 1.0 for a, b in zip(rounds["bare"], rounds[name], strict=True)]
        overhead[name] = {
            "ms_per_step": 1e3 * statistics.median(rounds[name]),
            "added_ms_per_step": 1e3
            * statistics.median(b - a for a, b in zip(rounds["bare"], rounds[name], strict=True)),
            "overhead_median": statistics.median(ratios),
            "overhead_range": [min(ratios), max(ratios)],
        }
    return {
        "command": " ".join(sys.argv),
        "machine": f"{platform.machine()} {platform.python_version()}",
        "network": str(args.osm or args.net or "urban 12 x 12"),
        "traffic": args.traffic,
        "steps": args.steps,
        "rounds": rounds,
        "overhead": overhead,
    }


if __name__ == "__main__":
    sys.exit(main())
