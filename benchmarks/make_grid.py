"""A network nobody here drew: SUMO's netgenerate grid, randomTrips traffic, an ego route.

Writes ``grid.net.xml`` (netgenerate: 4 x 4 junctions 250 m apart, two lanes each way,
priority junctions, no U-turns), ``trips.rou.xml`` (randomTrips: a vehicle every 2 s for an
hour, routed and validated) and ``ego.rou.xml`` (route ``ego``: east over two junctions, a left
turn that only the left lane may take, north, a right turn, east) with ``grid.sumocfg`` into
`--out`. Then drive it as a user would drive their own network:

    python benchmarks/make_grid.py --out runs/grid
    python benchmarks/routes.py --sumocfg runs/grid/grid.sumocfg --ego-route ego --episodes 50

The config sets no step length: SUMO's default of 1 s, so a decision every second.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import sumo

EGO_ROUTE = "A0B0 B0C0 C0C1 C1C2 C2D2 D2D3"
SUMOCFG = """<configuration>
    <input>
        <net-file value="grid.net.xml"/>
        <route-files value="ego.rou.xml,trips.rou.xml"/>
    </input>
</configuration>
"""


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for the network files")
    parser.add_argument("--seed", type=int, default=7, help="randomTrips' seed")
    args = parser.parse_args()
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    bin_dir, tools = Path(sumo.SUMO_HOME) / "bin", Path(sumo.SUMO_HOME) / "tools"
    netgenerate = [str(bin_dir / "netgenerate"), "--grid", "--grid.number", "4",
                   "--grid.length", "250", "--default.lanenumber", "2", "--default.speed",
                   "16.67", "--no-turnarounds", "true", "-o", "grid.net.xml"]  # fmt: skip
    trips = [sys.executable, str(tools / "randomTrips.py"), "-n", "grid.net.xml", "-e", "3600",
             "-p", "2.0", "--validate", "-r", "trips.rou.xml", "--seed", str(args.seed),
             "--fringe-factor", "5"]  # fmt: skip
    env = {**os.environ, "SUMO_HOME": str(sumo.SUMO_HOME)}
    for command in (netgenerate, trips):
        subprocess.run(command, cwd=out, check=True, env=env, timeout=300,
                       stdout=subprocess.DEVNULL)  # fmt: skip
    (out / "ego.rou.xml").write_text(
        f'<routes>\n    <route id="ego" edges="{EGO_ROUTE}"/>\n</routes>\n'
    )
    (out / "grid.sumocfg").write_text(SUMOCFG)
    print(f"wrote {out / 'grid.sumocfg'} (ego route: ego = {EGO_ROUTE})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
