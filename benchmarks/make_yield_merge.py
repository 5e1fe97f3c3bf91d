"""A ramp that joins a road at a junction where it gives way (no acceleration lane).

Flow's merge benchmark and SMARTS's ``3lane_merge`` join their ramps so. Writes ``merge.net.xml``
(netconvert: a one-lane road at 25 m/s, a 250 m one-lane ramp at 16 m/s meeting it at a priority
junction, the ramp the minor road), ``merge.rou.xml`` (`--flow` veh/h on the road, the ego's
route ``ego`` from the ramp) and ``merge.sumocfg`` (0.1 s steps) into `--out`. Then:

    python benchmarks/make_yield_merge.py --out runs/yield
    python benchmarks/routes.py --sumocfg runs/yield/merge.sumocfg --ego-route ego --episodes 50

A driver that ignores the stop line (protocol 1.7) cuts into the road's traffic there.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sim_server.backends.sumo.scenarios import find_netconvert

NODES = (
    '<nodes><node id="w" x="0" y="0"/><node id="j" x="600" y="0" type="priority"/>'
    '<node id="e" x="1200" y="0"/><node id="r" x="400" y="-150"/></nodes>\n'
)
EDGES = (
    '<edges><edge id="main" from="w" to="j" numLanes="1" speed="25" priority="2"/>'
    '<edge id="on" from="j" to="e" numLanes="1" speed="25" priority="2"/>'
    '<edge id="ramp" from="r" to="j" numLanes="1" speed="16" priority="1" length="250"/>'
    "</edges>\n"
)
SUMOCFG = (
    '<configuration><input><net-file value="merge.net.xml"/>'
    '<route-files value="merge.rou.xml"/></input>'
    '<time><step-length value="0.1"/></time></configuration>\n'
)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for the network files")
    parser.add_argument("--flow", type=float, default=1200.0, help="veh/h on the road")
    args = parser.parse_args()
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    (out / "merge.nod.xml").write_text(NODES)
    (out / "merge.edg.xml").write_text(EDGES)
    subprocess.run(
        [find_netconvert(), "--node-files", str(out / "merge.nod.xml"),
         "--edge-files", str(out / "merge.edg.xml"), "--output-file", str(out / "merge.net.xml"),
         "--no-turnarounds", "true"],
        check=True, timeout=120,
    )  # fmt: skip
    (out / "merge.rou.xml").write_text(
        '<routes><route id="through" edges="main on"/><route id="ego" edges="ramp on"/>'
        f'<flow id="road" route="through" begin="0" end="3600" vehsPerHour="{args.flow}" '
        'departSpeed="max"/></routes>\n'
    )
    (out / "merge.sumocfg").write_text(SUMOCFG)
    print(f"wrote {out / 'merge.sumocfg'} (ego route: ego)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
