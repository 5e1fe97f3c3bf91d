"""SUMO scenarios as standard files: a network built by netconvert, routes and a .sumocfg.

Every scenario is written to a cache folder (one subfolder per distinct set of file-affecting
options), so a user can open any of them in sumo-gui or netedit. Built-in scenarios:

* ``cf``   - the paper's car-following case: 2 km, one lane, 80 km/h, dense human traffic.
* ``cflc`` - the paper's integrated case: 2 km, three lanes, 700 veh/h/lane.

A user's own ``.sumocfg`` plus an ego route is a `CustomScenario`.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from xml.etree import ElementTree

from protocol.messages import OptionValue, ScenarioInfo
from sim_server.backends.options import COMMON_OPTIONS, TRAFFIC_OPTIONS, TrafficOptions

ROAD_STEP_LENGTH = 0.1
"""The simulation step of the built-in roads (s), written into their .sumocfg."""

EGO_ID = "ego"
EGO_TYPE = "ego"
EGO_ROUTE = "ego_route"
HUMAN_TYPE = "human"


@dataclass(frozen=True)
class RoadScenario:
    """A straight road with Poisson human traffic on every lane."""

    name: str
    description: str
    lanes: int
    length: float = 2000.0
    speed_limit: float = 80 / 3.6
    defaults: dict[str, OptionValue] = field(default_factory=dict)

    def info(self) -> ScenarioInfo:
        options = {**COMMON_OPTIONS, **TRAFFIC_OPTIONS, **self.defaults}
        return ScenarioInfo(self.name, self.description, options, ROAD_STEP_LENGTH)


@dataclass(frozen=True)
class CustomScenario:
    """A user's own .sumocfg; the ego drives `ego_route`, defined in the user's route files."""

    name: str
    sumocfg: Path
    ego_route: str

    def info(self) -> ScenarioInfo:
        description = f"user scenario {self.sumocfg} with ego route {self.ego_route!r}"
        step_length = self.step_length()
        options = dict(COMMON_OPTIONS)
        interval = options["decision_interval"]
        assert isinstance(interval, float)
        steps = round(interval / step_length)
        if steps < 1 or abs(steps * step_length - interval) > 1e-9:
            options["decision_interval"] = step_length  # the default must be one that resets
        return ScenarioInfo(self.name, description, options, step_length)

    def step_length(self) -> float:
        """The config's ``<step-length value=.../>`` (SUMO's default 1 s when absent)."""
        try:
            found = ElementTree.parse(self.sumocfg).find(".//step-length")
        except (OSError, ElementTree.ParseError):
            return 1.0
        return float(found.get("value", "1")) if found is not None else 1.0


Scenario = RoadScenario | CustomScenario

BUILTIN_SCENARIOS: dict[str, RoadScenario] = {
    s.name: s
    for s in (
        RoadScenario(
            "cf",
            "car following: 2 km single lane, 80 km/h, 1500 veh/h human traffic (paper 4.3)",
            lanes=1,
        ),
        RoadScenario(
            "cflc",
            "car following and lane changing: 2 km, 3 lanes, 80 km/h, 700 veh/h/lane (paper 4.5)",
            lanes=3,
            defaults={"flow": 700.0},
        ),
    )
}


def default_cache_dir() -> Path:
    """Where scenario files are written: $XDG_CACHE_HOME/av-bridge/scenarios."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "av-bridge" / "scenarios"


def find_netconvert() -> str:
    """The netconvert binary from the eclipse-sumo wheel (or a SUMO installation on PATH)."""
    found = shutil.which("netconvert")
    if found:
        return found
    try:
        import sumo  # eclipse-sumo wheel

        candidate = Path(sumo.SUMO_HOME) / "bin" / "netconvert"
        if candidate.exists():
            return str(candidate)
    except ImportError:
        pass
    raise FileNotFoundError("netconvert not found: install eclipse-sumo (pip install eclipse-sumo)")


def build_road(
    scenario: RoadScenario,
    traffic: TrafficOptions | Mapping[str, OptionValue],
    cache_dir: Path,
) -> Path:
    """Write (or reuse) the files of a road scenario; returns the path of its .sumocfg.

    `traffic` may also be the scenario's options as a dict (they are parsed). The folder name is
    a hash of the files' contents, so a change of options or of this generator never reuses
    stale files.
    """
    if not isinstance(traffic, TrafficOptions):
        traffic = TrafficOptions.parse(traffic)
    texts = {
        "road.nod.xml": _nodes(scenario),
        "road.edg.xml": _edges(scenario),
        "routes.rou.xml": _routes(scenario, traffic),
        f"{scenario.name}.sumocfg": _config(),
    }
    digest = hashlib.sha256(json.dumps(texts, sort_keys=True).encode()).hexdigest()[:12]
    folder = cache_dir / f"{scenario.name}-{digest}"
    config = folder / f"{scenario.name}.sumocfg"
    if config.exists():
        return config
    tmp = folder.with_name(f"{folder.name}.tmp{os.getpid()}")
    tmp.mkdir(parents=True, exist_ok=True)
    for name, text in texts.items():
        (tmp / name).write_text(text)
    _run_netconvert(tmp)
    try:
        tmp.rename(folder)
    except OSError:  # another process built the same scenario meanwhile
        shutil.rmtree(tmp, ignore_errors=True)
    return config


def _nodes(scenario: RoadScenario) -> str:
    return (
        "<nodes>\n"
        '    <node id="start" x="0" y="0"/>\n'
        f'    <node id="end" x="{scenario.length:.2f}" y="0"/>\n'
        "</nodes>\n"
    )


def _edges(scenario: RoadScenario) -> str:
    return (
        "<edges>\n"
        f'    <edge id="road" from="start" to="end" numLanes="{scenario.lanes}" '
        f'speed="{scenario.speed_limit:.4f}"/>\n'
        "</edges>\n"
    )


def _run_netconvert(folder: Path) -> None:
    result = subprocess.run(
        [
            find_netconvert(),
            "--node-files", str(folder / "road.nod.xml"),
            "--edge-files", str(folder / "road.edg.xml"),
            "--output-file", str(folder / "road.net.xml"),
            "--no-turnarounds", "true",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )  # fmt: skip
    if result.returncode != 0:
        raise RuntimeError(f"netconvert failed ({result.returncode}): {result.stderr.strip()}")


def _routes(scenario: RoadScenario, traffic: TrafficOptions) -> str:
    flow, mean, dev = traffic.flow, traffic.speed_factor_mean, traffic.speed_factor_dev
    flows = "".join(
        f'    <flow id="human{lane}" type="human" route="{EGO_ROUTE}" begin="0" end="86400" '
        f'period="exp({flow / 3600:.6f})" departLane="{lane}" departPos="base" '
        'departSpeed="max"/>\n'
        for lane in range(scenario.lanes)
        if flow > 0
    )
    return (
        "<routes>\n"
        f'    <vType id="{HUMAN_TYPE}" vClass="passenger" carFollowModel="Krauss" '
        f'sigma="{traffic.sigma}" '
        f'speedFactor="normc({mean},{dev},0.5,1.5)" lcModel="LC2013"/>\n'
        f'    <vType id="{EGO_TYPE}" vClass="passenger" accel="3" decel="6" emergencyDecel="9" '
        'sigma="0" speedFactor="1" speedDev="0" color="0,0,1"/>\n'
        f'    <route id="{EGO_ROUTE}" edges="road"/>\n'
        f"{flows}"
        "</routes>\n"
    )


def _config() -> str:
    return (
        "<configuration>\n"
        "    <input>\n"
        '        <net-file value="road.net.xml"/>\n'
        '        <route-files value="routes.rou.xml"/>\n'
        "    </input>\n"
        "    <time>\n"
        f'        <step-length value="{ROAD_STEP_LENGTH}"/>\n'
        "    </time>\n"
        "    <processing>\n"
        '        <collision.action value="warn"/>\n'
        '        <collision.mingap-factor value="0"/>\n'
        '        <time-to-teleport value="-1"/>\n'
        '        <lanechange.duration value="2"/>\n'
        "    </processing>\n"
        "    <report>\n"
        '        <no-step-log value="true"/>\n'
        '        <no-warnings value="true"/>\n'
        "    </report>\n"
        "</configuration>\n"
    )
