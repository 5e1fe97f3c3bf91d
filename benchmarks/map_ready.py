"""How long until `sim-server --osm FILE` (or `--net FILE`) is ready, the first time and cached?

Starts a real ``sim-server`` on the map twice: with an empty scenario cache (netconvert builds
the network, the server reads its roads into a graph) and again with the cache just written,
and times each from the command to its ``listening on`` line. Then resets one episode on it
(seeded traffic, an ego trip) and reports the reset's time and the trip's length, so that
"ready" means a map a client can drive.

    python benchmarks/map_ready.py --osm town.osm.xml
    python benchmarks/map_ready.py --net motorway.net.xml.gz --save

This is a measurement, not a test: the issue's targets are 60 s the first time and 5 s from
the cache.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent_client.envs.remote_env import RemoteEnv
from protocol.readiness import LISTENING, stop_process, wait_for_line

READY_TIMEOUT_S = 600.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--osm", type=Path, help="an OpenStreetMap export")
    source.add_argument("--net", type=Path, help="a SUMO network")
    parser.add_argument("--seed", type=int, default=1, help="the reset's seed")
    parser.add_argument("--save", action="store_true", help="write benchmarks/results/...json")
    args = parser.parse_args()
    path: Path = args.osm or args.net
    flag = "--osm" if args.osm else "--net"
    if not path.is_file():
        print(f"error: {flag} {path}: no such file", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="map-ready-") as cache:
        first = start(flag, path, Path(cache))
        cached = start(flag, path, Path(cache), args.seed)
    result = {"map": path.name, "flag": flag, "first_s": first["ready_s"], **cached}
    result["cached_s"] = result.pop("ready_s")
    print(
        f"{path.name}: ready in {result['first_s']:.1f} s the first time, "
        f"{result['cached_s']:.1f} s from the cache; a reset (traffic, warm-up, ego trip of "
        f"{result['route_m']:.0f} m) {result['reset_s']:.1f} s"
    )
    if args.save:
        out = (
            ROOT
            / "benchmarks"
            / "results"
            / f"map-ready-{path.name}-{time.strftime('%Y-%m-%d')}.json"
        )
        machine = f"{platform.node()} {platform.machine()}, Python {platform.python_version()}"
        payload = {"command": " ".join(sys.argv), "machine": machine, **result}
        out.write_text(json.dumps(payload, indent=1) + "\n")
        print(f"wrote {out}")
    return 0


def start(flag: str, path: Path, cache: Path, seed: int | None = None) -> dict[str, Any]:
    """Start a server on the map with `cache` as its cache; time it to readiness, and with
    `seed` time one reset on it too."""
    command = [sys.executable, "-m", "sim_server.cli", "--bind", "tcp://127.0.0.1:0",
               "--log-level", "WARNING", flag, str(path), "--scenario-name", "map"]  # fmt: skip
    env = {**os.environ, "XDG_CACHE_HOME": str(cache)}
    started = time.monotonic()
    server = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env
    )
    try:
        address = wait_for_line(server, LISTENING, READY_TIMEOUT_S)
        found: dict[str, Any] = {"ready_s": time.monotonic() - started}
        if seed is not None:
            env_ = RemoteEnv(address, "map", reset_timeout_s=READY_TIMEOUT_S)
            try:
                began = time.monotonic()
                _, info = env_.reset(seed=seed)
                found["reset_s"] = time.monotonic() - began
                route = info["observation"].route
                found["route_m"] = route.length if route is not None else float("nan")
            finally:
                env_.close()
        return found
    finally:
        stop_process(server)


if __name__ == "__main__":
    sys.exit(main())
