"""SUMO scenarios as standard files: a network built by netconvert, routes and a .sumocfg.

Every scenario is written to a cache folder (one subfolder per distinct set of file-affecting
options), so a user can open any of them in sumo-gui or netedit. Built-in scenarios:

* ``cf``   - the paper's car-following case: 2 km, one lane, 80 km/h, dense human traffic.
* ``cflc`` - the paper's integrated case: 2 km, three lanes, 700 veh/h/lane.
* ``ring`` - a single-lane ring after Sugiyama et al. (2008): 22 vehicles on 230 m, placed
  evenly at reset, whose drivers form stop-and-go waves without any bottleneck.

A user's own ``.sumocfg`` plus an ego route is a `CustomScenario`.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import subprocess
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, NamedTuple
from xml.etree import ElementTree

from protocol.messages import OptionValue, ScenarioInfo
from sim_server.backends.options import (
    COMMON_OPTIONS,
    SHARE_OPTIONS,
    TRAFFIC_OPTIONS,
    Bounds,
    EpisodeOptions,
    ParsedOptions,
    TrafficOptions,
    invalid_option,
)
from sim_server.backends.sumo.humans import human_type

ROAD_STEP_LENGTH = 0.1
"""The simulation step of the built-in roads (s), written into their .sumocfg."""

EGO_ID = "ego"
EGO_TYPE = "ego"
EGO_ROUTE = "ego_route"
HUMAN_TYPE = "human"
EGO_TYPE_LINE = (
    f'    <vType id="{EGO_TYPE}" vClass="passenger" accel="3" decel="6" emergencyDecel="9" '
    'sigma="0" speedFactor="1" speedDev="0" color="0,0,1"/>\n'
)
"""The ego's vType in a route file: no imperfection, no speed spread (the client drives it)."""


@dataclass(frozen=True, slots=True)
class MeasureOptions(ParsedOptions):
    """What SUMO reports beyond the ego's own observation, on every SUMO scenario."""

    ssm: bool = False
    """Equip the ego with SUMO's SSM device and report its conflicts on the last observation
    (`protocol.messages.Safety`)."""
    report_traffic: bool = False
    """Report every other vehicle on every observation (`protocol.messages.Traffic`)."""


MEASURE_OPTIONS = MeasureOptions().as_options()
"""The announced defaults of the measurement options (copy before changing)."""


class ScenarioFiles(NamedTuple):
    """What a reset loads: the .sumocfg, the egos' route in it ("" on the ring, where they are
    placed) and their departLane."""

    config: Path
    ego_route: str
    depart_lane: str = "random"


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
        options = {
            **COMMON_OPTIONS,
            **SHARE_OPTIONS,
            **TRAFFIC_OPTIONS,
            **MEASURE_OPTIONS,
            **self.defaults,
        }
        return ScenarioInfo(self.name, self.description, options, ROAD_STEP_LENGTH)

    def build(self, options: Mapping[str, OptionValue], cache_dir: Path) -> Path:
        """Write (or reuse) this scenario's files for `options`; the path of its .sumocfg."""
        return build_road(self, options, cache_dir)


@dataclass(frozen=True)
class CustomScenario:
    """A user's own .sumocfg; the ego drives `ego_route`, defined in the user's route files, or
    with ``random`` a trip drawn per seed over the network (`RANDOM_ROUTE`)."""

    name: str
    sumocfg: Path
    ego_route: str

    @property
    def random_route(self) -> bool:
        """The ego's trip is drawn per seed (``--ego-route random``)."""
        return self.ego_route == RANDOM_ROUTE

    def info(self) -> ScenarioInfo:
        route = "a trip drawn per seed" if self.random_route else f"ego route {self.ego_route!r}"
        description = f"user scenario {self.sumocfg} with {route}"
        step_length = self.step_length()
        options = {**COMMON_OPTIONS, **SHARE_OPTIONS, **MEASURE_OPTIONS}
        if self.random_route:
            options.update(ego_route_min=1000.0, ego_route_max=4000.0, ego_from="", ego_to="")
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

    def net_file(self) -> Path:
        """The network the config names (``<net-file value=.../>``, relative to the config)."""
        found = ElementTree.parse(self.sumocfg).find(".//net-file")
        if found is None or not found.get("value"):
            raise ValueError(f"{self.sumocfg} names no net-file")
        return (self.sumocfg.parent / found.get("value", "")).resolve()


RANDOM_ROUTE = "random"
"""`CustomScenario.ego_route` that draws the ego's trip per seed."""


RING_SPEED_LIMIT = 30 / 3.6
"""The ring's speed limit (m/s): Sugiyama et al. asked their drivers to cruise at 30 km/h."""
RING_EDGES = ("a", "b")
"""The ring's two half circles: ``a`` from its start (east) to halfway, ``b`` back."""
RING_ROUTES = ("ring_a", "ring_b")
"""The two routes around the ring, starting on edge ``a`` and on edge ``b``."""
RING_VEHICLE_LENGTH = 5.0
"""SUMO's passenger car length (m), of the humans and the ego alike."""
RING_MIN_SPACING = 8.0
"""Shortest ring length per vehicle (m) placed at reset: a car (5 m), the largest minGap of the
human models (2.5 m, Krauss), and 0.5 m to spare."""
RING_HUMAN_MODELS = {
    "eidm": 'carFollowModel="EIDM" accel="1" decel="1.5" minGap="2" tau="1"',
    "idm": 'carFollowModel="IDM" accel="1" decel="1.5" minGap="2" tau="1"',
    "krauss": 'carFollowModel="Krauss" sigma="0.5"',
}
"""The ring's human drivers (`RingOptions.human_model`): the car-following attributes of their
vType. ``eidm`` (the default) is SUMO's Extended IDM, IDM with estimation errors and a reaction
time, whose noise seeds the waves, with the string-unstable IDM parameters of Flow's ring
benchmark (a = 1 m/s², b = 1.5 m/s², s0 = 2 m, T = 1 s); ``idm`` the same without noise (SUMO's
IDM ignores sigma); ``krauss`` the humans of ``cf`` (SUMO's defaults, sigma 0.5). Only ``eidm``
forms waves within minutes (docs/backends.md, "The ring")."""
RING_HORIZON_S = (
    EpisodeOptions.BOUNDS["warmup"].high + EpisodeOptions.BOUNDS["max_episode_time"].high + 60.0
)
"""Longest simulated time of a ring episode (the largest warmup and max_episode_time, and a
minute to spare): the routes go round the ring at least this long at the speed limit."""
RING_OMITTED = ("insertion_timeout", "report_ceiling")
"""Options of the other scenarios the ring does not offer: nobody enters (every vehicle is
placed at reset) and nobody arrives (so there is no leader-at-entry trip to report)."""


@dataclass(frozen=True, slots=True)
class RingOptions(ParsedOptions):
    """The ring's own options (they change its files)."""

    ring_length: float = 230.0
    """Circumference of the ring (m), at the centre of its one lane."""
    vehicles: int = 22
    """Vehicles on the ring, the egos included, placed evenly at reset."""
    human_model: str = "eidm"
    """The humans' car-following model, a key of `RING_HUMAN_MODELS`."""

    BOUNDS: ClassVar[Mapping[str, Bounds]] = {
        "ring_length": Bounds(50.0, 5000.0, unit=" m"),
        "vehicles": Bounds(2, 500),
    }

    def check(self) -> None:
        if self.human_model not in RING_HUMAN_MODELS:
            raise invalid_option(
                f"option human_model must be one of {', '.join(RING_HUMAN_MODELS)}, "
                f"got {self.human_model[:64]!r}"
            )
        if self.ring_length / self.vehicles < RING_MIN_SPACING:
            raise invalid_option(
                f"{self.vehicles} vehicles do not fit on a {self.ring_length:g} m ring: "
                f"at least {RING_MIN_SPACING:g} m each (ring_length >= "
                f"{RING_MIN_SPACING * self.vehicles:g})"
            )

    def slot(self, index: int) -> tuple[str, float]:
        """Where vehicle `index` starts: its route and its front's lane position.

        Fronts are `ring_length / vehicles` apart, slot 0's (the first ego's) 5 m past the
        start of edge ``a`` (its back on the seam, not across it)."""
        half = self.ring_length / 2
        front = RING_VEHICLE_LENGTH + index * self.ring_length / self.vehicles
        return (RING_ROUTES[0], front) if front < half else (RING_ROUTES[1], front - half)

    def ego_slots(self, egos: int) -> tuple[int, ...]:
        """The slots of `egos` egos spread evenly round the ring: round(k x vehicles / egos)
        (halves up), k = 0..egos-1; slot 0 is the first ego's. Refused if egos > vehicles."""
        if egos > self.vehicles:
            raise invalid_option(
                f"option egos {egos} exceeds the ring's vehicles {self.vehicles}: each ego is one "
                "of them (raise vehicles, or ask for fewer egos)"
            )
        return tuple(math.floor(k * self.vehicles / egos + 0.5) for k in range(egos))

    def ring_position(self, index: int) -> float:
        """The front of vehicle `index` at reset, in metres from the start of edge ``a``."""
        route, position = self.slot(index)
        return position if route == RING_ROUTES[0] else position + self.ring_length / 2

    def laps(self) -> int:
        """How often the routes go round the ring: more than any episode can drive."""
        return math.ceil(RING_HORIZON_S * RING_SPEED_LIMIT / self.ring_length) + 1


RING_OPTIONS = RingOptions().as_options()
"""The announced defaults of the ring's own options (copy before changing)."""


@dataclass(frozen=True)
class RingScenario:
    """A single-lane ring with human drivers placed evenly at reset; the ego is one of them."""

    name: str
    description: str
    defaults: dict[str, OptionValue] = field(default_factory=dict)

    def info(self) -> ScenarioInfo:
        common = {k: v for k, v in COMMON_OPTIONS.items() if k not in RING_OMITTED}
        options = {**common, **SHARE_OPTIONS, **RING_OPTIONS, **MEASURE_OPTIONS, **self.defaults}
        return ScenarioInfo(self.name, self.description, options, ROAD_STEP_LENGTH)

    def build(self, options: Mapping[str, OptionValue], cache_dir: Path) -> Path:
        """Write (or reuse) this scenario's files for `options`; the path of its .sumocfg."""
        return build_ring(self, options, cache_dir)


Scenario = RoadScenario | RingScenario | CustomScenario
BuiltinScenario = RoadScenario | RingScenario

BUILTIN_SCENARIOS: dict[str, BuiltinScenario] = {
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
        RingScenario(
            "ring",
            "ring road after Sugiyama et al. 2008: 22 vehicles on a 230 m single-lane circuit, "
            "placed evenly at reset; the humans' stop-and-go waves form without a bottleneck",
            defaults={"warmup": 300.0},
        ),
    )
}


def default_cache_dir() -> Path:
    """Where scenario files are written: $XDG_CACHE_HOME/av-bridge/scenarios."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "av-bridge" / "scenarios"


def find_netconvert() -> str:
    """The netconvert binary from the eclipse-sumo wheel (or a SUMO installation on PATH)."""
    return find_sumo_tool("netconvert")


def find_sumo_tool(name: str) -> str:
    """A SUMO program (``netconvert``, ``netgenerate``) from the eclipse-sumo wheel or a SUMO
    installation on PATH; ``data``: SUMO's data folder (the OSM type maps)."""
    if name != "data":
        found = shutil.which(name)
        if found:
            return found
    try:
        import sumo  # eclipse-sumo wheel

        candidate = Path(sumo.SUMO_HOME) / (name if name == "data" else f"bin/{name}")
        if candidate.exists():
            return str(candidate)
    except ImportError:
        pass
    home = os.environ.get("SUMO_HOME")
    if name == "data" and home:
        return str(Path(home) / "data")
    raise FileNotFoundError(f"{name} not found: install eclipse-sumo (pip install eclipse-sumo)")


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
    }
    return write_scenario(scenario.name, texts, cache_dir)


def build_ring(
    scenario: RingScenario,
    layout: RingOptions | Mapping[str, OptionValue],
    cache_dir: Path,
    ego_slots: tuple[int, ...] = (0,),
) -> Path:
    """Write (or reuse) the files of a ring scenario; returns the path of its .sumocfg.

    Two half-circle edges ``a`` and ``b`` of exactly ``ring_length / 2`` each, joined without
    internal junction lanes, so that a position on the ring is a lane position plus 0 or half
    the length. `layout` may also be the scenario's options as a dict (they are parsed). The
    humans fill every slot but `ego_slots` (the backend places the egos there).
    """
    if not isinstance(layout, RingOptions):
        layout = RingOptions.parse(layout)
    texts = {
        "road.nod.xml": _ring_nodes(layout),
        "road.edg.xml": _ring_edges(layout),
        "routes.rou.xml": _ring_routes(layout, frozenset(ego_slots)),
    }
    return write_scenario(scenario.name, texts, cache_dir, ("--no-internal-links", "true"))


def write_scenario(
    name: str, texts: dict[str, str], cache_dir: Path, netconvert_args: tuple[str, ...] = ()
) -> Path:
    """The files in a folder named by a hash of their contents (never stale), built once: the
    `texts` (``road.nod.xml``, ``road.edg.xml``, optionally ``road.con.xml``, the routes) and
    the .sumocfg, the network made by netconvert."""
    texts = {**texts, f"{name}.sumocfg": sumo_config()}
    digest = hashlib.sha256(json.dumps(texts, sort_keys=True).encode()).hexdigest()[:12]
    folder = cache_dir / f"{name}-{digest}"
    config = folder / f"{name}.sumocfg"
    if config.exists():
        return config
    tmp = folder.with_name(f"{folder.name}.tmp{os.getpid()}")
    tmp.mkdir(parents=True, exist_ok=True)
    for file_name, text in texts.items():
        (tmp / file_name).write_text(text)
    _run_netconvert(tmp, netconvert_args)
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


def _run_netconvert(folder: Path, extra: tuple[str, ...] = ()) -> None:
    connections = folder / "road.con.xml"
    if connections.exists():  # every lane-to-lane link given: netconvert guesses none
        extra = ("--connection-files", str(connections), *extra)
    result = subprocess.run(
        [
            find_netconvert(),
            "--node-files", str(folder / "road.nod.xml"),
            "--edge-files", str(folder / "road.edg.xml"),
            "--output-file", str(folder / "road.net.xml"),
            "--no-turnarounds", "true",
            *extra,
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
        f"{human_type(HUMAN_TYPE, traffic.human_model, traffic.sigma, mean, dev)}"
        f"{EGO_TYPE_LINE}"
        f'    <route id="{EGO_ROUTE}" edges="road"/>\n'
        f"{flows}"
        "</routes>\n"
    )


def _ring_nodes(layout: RingOptions) -> str:
    radius = layout.ring_length / (2 * math.pi)
    return (
        "<nodes>\n"
        f'    <node id="east" x="{radius:.3f}" y="0"/>\n'
        f'    <node id="west" x="{-radius:.3f}" y="0"/>\n'
        "</nodes>\n"
    )


def _ring_edges(layout: RingOptions) -> str:
    """Edge ``a`` the northern half (counter-clockwise from east), ``b`` the southern one."""
    radius = layout.ring_length / (2 * math.pi)

    def arc(start: float) -> str:
        angles = (start + math.pi * k / 32 for k in range(33))
        return " ".join(f"{radius * math.cos(t):.3f},{radius * math.sin(t):.3f}" for t in angles)

    a, b = RING_EDGES
    half = layout.ring_length / 2
    common = f'numLanes="1" speed="{RING_SPEED_LIMIT:.4f}" length="{half:.3f}"'
    return (
        "<edges>\n"
        f'    <edge id="{a}" from="east" to="west" {common} shape="{arc(0.0)}"/>\n'
        f'    <edge id="{b}" from="west" to="east" {common} shape="{arc(math.pi)}"/>\n'
        "</edges>\n"
    )


def _ring_routes(layout: RingOptions, ego_slots: frozenset[int]) -> str:
    """The humans (every slot but the egos') standing at their slots at time 0, driving
    `layout.human_model`; ``human{slot}`` each."""
    laps, (a, b) = layout.laps(), RING_EDGES
    humans = []
    for i in range(layout.vehicles):
        if i in ego_slots:
            continue
        route, position = layout.slot(i)
        humans.append(
            f'    <vehicle id="human{i}" type="{HUMAN_TYPE}" route="{route}" depart="0" '
            f'departLane="0" departPos="{position:.3f}" departSpeed="0"/>\n'
        )
    return (
        "<routes>\n"
        f'    <vType id="{HUMAN_TYPE}" vClass="passenger" {RING_HUMAN_MODELS[layout.human_model]} '
        f'speedFactor="1" speedDev="0" length="{RING_VEHICLE_LENGTH:g}"/>\n'
        f'    <vType id="{EGO_TYPE}" vClass="passenger" accel="3" decel="6" emergencyDecel="9" '
        f'sigma="0" speedFactor="1" speedDev="0" length="{RING_VEHICLE_LENGTH:g}" '
        'color="0,0,1"/>\n'
        f'    <route id="{RING_ROUTES[0]}" edges="{a} {b}" repeat="{laps}"/>\n'
        f'    <route id="{RING_ROUTES[1]}" edges="{b} {a}" repeat="{laps}"/>\n'
        f"{''.join(humans)}"
        "</routes>\n"
    )


def sumo_config() -> str:
    """The .sumocfg of a built-in scenario: its network, its routes, the forced settings."""
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
        '        <collision.check-junctions value="true"/>\n'
        '        <time-to-teleport value="-1"/>\n'
        '        <lanechange.duration value="2"/>\n'
        "    </processing>\n"
        "    <report>\n"
        '        <no-step-log value="true"/>\n'
        '        <no-warnings value="true"/>\n'
        "    </report>\n"
        "</configuration>\n"
    )
