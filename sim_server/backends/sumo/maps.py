"""A user's own map as a scenario: a SUMO network, or an OpenStreetMap export built into one.

``sim-server --net FILE.net.xml[.gz]`` and ``sim-server --osm FILE.osm[.xml|.gz]`` serve the map
as a scenario named after the file. netconvert builds an OSM export once, with the options a
driving study wants (`OSM_OPTIONS`), into the scenario cache (keyed by the file's content, like
the built-in scenarios). Every reset draws from its seed:

* the background traffic: trips between roads of the network's largest strongly connected part,
  as many per hour as ``traffic`` vehicles per hour per lane-kilometre (randomTrips'
  ``--insertion-density``), a ``truck_share`` of them heavy vehicles, the humans' model
  ``human_model``; a first batch starts spread over the network at once, so that a short
  warm-up finds it filled; SUMO routes each trip as it departs (its own router);
* the ego's trip: two roads whose shortest connection is ``ego_route_min`` to
  ``ego_route_max`` metres long, SUMO's fastest route between them (`simulation.findRoute`);
  or between the roads ``ego_from`` and ``ego_to`` where they are given.

So a policy trained on a map meets a different trip every episode. Source: SUMO docs,
"Networks/Import/OpenStreetMap", "Tools/Trip" (randomTrips), "Demand/Shortest or Optimal Path
Routing" (trips routed at departure).
"""

from __future__ import annotations

import hashlib
import math
import os
import random
import shutil
import subprocess
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from protocol.messages import OptionValue, ScenarioInfo
from sim_server.backends.options import (
    COMMON_OPTIONS,
    SHARE_OPTIONS,
    TRAFFIC_OPTIONS,
    Bounds,
    ParsedOptions,
    TrafficOptions,
    invalid_option,
)
from sim_server.backends.sumo.humans import TRUCK_TYPE, human_type, truck_type
from sim_server.backends.sumo.network import RoadGraph, file_digest, weighted_roads
from sim_server.backends.sumo.scenarios import (
    EGO_ROUTE,
    EGO_TYPE,
    EGO_TYPE_LINE,
    HUMAN_TYPE,
    MEASURE_OPTIONS,
    ROAD_STEP_LENGTH,
    ScenarioFiles,
    find_sumo_tool,
)

OSM_OPTIONS: tuple[str, ...] = (
    "--geometry.remove", "true",
    "--ramps.guess", "true",
    "--junctions.join", "true",
    "--tls.guess-signals", "true",
    "--tls.discard-simple", "true",
    "--tls.join", "true",
    "--tls.default-type", "actuated",
    "--roundabouts.guess", "true",
    "--remove-edges.isolated", "true",
    "--keep-edges.by-vclass", "passenger",
    "--junctions.corner-detail", "5",
    "--output.street-names", "true",
    "--output.original-names", "true",
)  # fmt: skip
"""netconvert's options for an OSM export, as SUMO's own osmBuild.py and osmWebWizard.py import
one (SUMO docs, "Networks/Import/OpenStreetMap"): acceleration and deceleration lanes where a
ramp joins (OSM rarely maps them), signals guessed where OSM marks them near a junction and
joined where they belong to one junction, actuated as most modern signals are, roundabouts,
joined junction clusters, only roads a car may drive, isolated pieces dropped. (Waiting points
placed for a vehicle 3 m wide, `--internal-junctions.vehicle-width 3.0`, were tried: they
removed the four Greenville collisions of SUMO's own driver they were meant for, but over 100
trips SUMO's driver collided more often, 8 against 4, and on São Paulo both drivers collided
where they had not: not kept. docs/results.md, "Your own map".)"""
OSM_TIMEOUT_S = 600.0
"""Longest netconvert may take on an OSM export."""
FIRST_FILL_S = 90.0
"""Seconds of trips that start at once, spread over the network, at the start of an episode."""
TRIP_MIN_DISTANCE = 200.0
"""m as the crow flies a background trip goes at least (fewer where the network is small)."""
EGO_ROUTE_TRIES = 50
"""Draws of a start road before the ego's trip is refused."""
EPISODE_SLACK_S = 60.0
"""Seconds of trips beyond the warm-up and the episode's time limit."""
TELEPORT_AFTER_S = 180.0
"""A human stuck this long is taken out of a map's traffic (SUMO's teleport: a gridlock of
humans clears), longer than the ego's ``jam_patience``, after which its own episode ends."""
MAX_DEPART_DELAY_S = 60.0
"""A background trip that cannot start within this (its road full) is dropped."""


@dataclass(frozen=True, slots=True)
class MapOptions(ParsedOptions):
    """The traffic and the ego's trip on a map (they change the episode's route file)."""

    traffic: float = 20.0
    """Background trips per hour per lane-kilometre of the network (randomTrips'
    ``--insertion-density``)."""
    truck_share: float = 0.1
    """Share of the background trips made by heavy vehicles."""
    ego_route_min: float = 1000.0
    """Shortest ego trip (m, by the network's shortest connection)."""
    ego_route_max: float = 4000.0
    """Longest ego trip (m)."""
    ego_from: str = ""
    """The road the ego's trip starts on ("": drawn from the seed)."""
    ego_to: str = ""
    """The road it ends on ("": drawn from the seed)."""

    BOUNDS: ClassVar[Mapping[str, Bounds]] = {
        "traffic": Bounds(0.0, 1000.0, unit=" veh/h per lane-km"),
        "truck_share": Bounds(0.0, 1.0, text="within [0, 1]"),
        "ego_route_min": Bounds(0.0, 1_000_000.0, unit=" m"),
        "ego_route_max": Bounds(0.0, 1_000_000.0, low_excluded=True, unit=" m"),
    }

    def check(self) -> None:
        if self.ego_route_min > self.ego_route_max:
            raise invalid_option(
                f"option ego_route_min {self.ego_route_min:g} m exceeds ego_route_max "
                f"{self.ego_route_max:g} m"
            )
        if bool(self.ego_from) != bool(self.ego_to):
            raise invalid_option("options ego_from and ego_to go together: give both or none")


MAP_OPTIONS = MapOptions().as_options()
HUMAN_OPTIONS = {k: v for k, v in TRAFFIC_OPTIONS.items() if k != "flow"}
"""The humans' options of the built-in roads that a map takes too (not ``flow``: its traffic is
``traffic``, per lane-kilometre)."""


@dataclass(frozen=True)
class MapNetwork:
    """A network an episode runs on: its file and its graph of roads."""

    net_file: Path
    graph: RoadGraph = field(compare=False, repr=False)
    starts: tuple[str, ...] = field(compare=False, repr=False, default=())
    """The roads a trip may start on: from each, the network's largest strongly connected part
    can be reached (its own roads and the roads that lead into it: a map's edge)."""
    ends: tuple[str, ...] = field(compare=False, repr=False, default=())
    """The roads a trip may end on: each can be reached from that part."""

    @classmethod
    def of(cls, net_file: Path, cache_dir: Path) -> MapNetwork:
        graph = RoadGraph.cached(net_file, cache_dir)
        connected = graph.connected()
        if not connected:
            raise ValueError(f"{net_file}: no road a passenger car may drive")
        starts = tuple(graph.reachable(connected, forward=False))
        ends = tuple(graph.reachable(connected))
        return cls(net_file.resolve(), graph, starts, ends)


@dataclass(frozen=True)
class MapScenario:
    """A user's map (``--net`` or ``--osm``)."""

    name: str
    description: str
    network: MapNetwork
    defaults: dict[str, OptionValue] = field(default_factory=dict)

    def info(self) -> ScenarioInfo:
        return ScenarioInfo(
            self.name, self.description, map_options(self.defaults), ROAD_STEP_LENGTH
        )

    def network_for(
        self, options: Mapping[str, OptionValue], seed: int, cache_dir: Path
    ) -> MapNetwork:
        """The network of an episode: the map's own, whatever the seed."""
        return self.network


def map_options(defaults: Mapping[str, OptionValue]) -> dict[str, OptionValue]:
    """The options a map announces: the common ones (a warm-up of a minute, up to a quarter
    of an hour to drive), the humans' and the map's, the measurements, then `defaults`."""
    return {
        **COMMON_OPTIONS,
        "warmup": 60.0,
        "max_episode_time": 900.0,
        **SHARE_OPTIONS,
        **HUMAN_OPTIONS,
        **MAP_OPTIONS,
        **MEASURE_OPTIONS,
        **defaults,
    }


def episode_files(
    network: MapNetwork,
    options: Mapping[str, OptionValue],
    seed: int,
    horizon: float,
    folder: Path,
) -> ScenarioFiles:
    """Write the episode's route file (the vehicle types and the seed's background trips over
    `horizon` seconds) and its .sumocfg into `folder`; the ego's route is added once the
    network is loaded (`ego_route`)."""
    humans = TrafficOptions.parse(options)
    own = MapOptions.parse(options)
    trips = background_trips(network, own, seed, horizon)
    mean, dev = humans.speed_factor_mean, humans.speed_factor_dev
    types = (
        human_type(HUMAN_TYPE, humans.human_model, humans.sigma, mean, dev)
        + truck_type(humans.human_model, humans.sigma)
        + EGO_TYPE_LINE
    )
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "trips.rou.xml").write_text(f"<routes>\n{types}{trips}</routes>\n")
    config = folder / "map.sumocfg"
    config.write_text(map_config(network.net_file))
    return ScenarioFiles(config, EGO_ROUTE, "best")


def background_trips(network: MapNetwork, own: MapOptions, seed: int, horizon: float) -> str:
    """The seed's trips as route-file lines, in order of departure."""
    graph, starts, ends = network.graph, list(network.starts), list(network.ends)
    rate = own.traffic * graph.lane_km(sorted(set(starts) | set(ends))) / 3600.0  # per second
    if rate <= 0.0 or len(ends) < 2:
        return ""
    draw = random.Random(f"traffic:{seed}")
    departures = [0.0] * round(rate * FIRST_FILL_S)
    clock = 0.0
    while True:
        clock += draw.expovariate(rate)
        if clock >= horizon:
            break
        departures.append(clock)
    origins = weighted_roads(graph, starts, draw, len(departures))
    destinations = weighted_roads(graph, ends, draw, len(departures))
    spread = min(TRIP_MIN_DISTANCE, _extent(graph) / 4)
    lines = []
    for k, (depart, start, end) in enumerate(zip(departures, origins, destinations, strict=True)):
        for _ in range(10):  # a trip that goes somewhere
            if end != start and graph.straight_distance(start, end) >= spread:
                break
            end = weighted_roads(graph, ends, draw, 1)[0]
        kind = TRUCK_TYPE if draw.random() < own.truck_share else HUMAN_TYPE
        position = "random_free" if depart == 0.0 else "base"
        lines.append(
            f'    <trip id="h{k}" type="{kind}" depart="{depart:.1f}" from="{start}" to="{end}" '
            f'departLane="best" departPos="{position}" departSpeed="max"/>\n'
        )
    return "".join(lines)


def _extent(graph: RoadGraph) -> float:
    """The network's diagonal (m)."""
    if not graph.junctions:
        return 0.0
    xs = [x for x, _ in graph.junctions.values()]
    ys = [y for _, y in graph.junctions.values()]
    return math.hypot(max(xs) - min(xs), max(ys) - min(ys))


def ego_route(
    api: Any, network: MapNetwork, options: Mapping[str, OptionValue], seed: int
) -> list[str]:
    """The ego's trip: SUMO's fastest route between ``ego_from`` and ``ego_to``, or between two
    roads the seed draws whose shortest connection is ``ego_route_min`` to ``ego_route_max``
    long (the route SUMO picks may be somewhat longer). Refused (`invalid_option`) where the
    network has no such trip."""
    own = MapOptions.parse(options)
    graph = network.graph
    if own.ego_from:
        for road in (own.ego_from, own.ego_to):
            if road not in graph.roads:
                raise invalid_option(
                    f"option ego_from/ego_to: no road {road[:64]!r} a car may drive"
                )
        edges = list(api.simulation.findRoute(own.ego_from, own.ego_to, EGO_TYPE).edges)
        if not edges:
            raise invalid_option(f"no route from {own.ego_from!r} to {own.ego_to!r} for a car")
        return edges
    draw = random.Random(f"ego:{seed}")
    allowed = set(network.starts) | set(network.ends)
    starts = [r for r in network.starts if graph.roads[r].length >= 10.0] or list(network.starts)
    ends_ok = set(network.ends)
    longest = 0.0
    for _ in range(EGO_ROUTE_TRIES):
        start = weighted_roads(graph, starts, draw, 1)[0]
        reach = graph.distances(start, allowed, own.ego_route_max)
        longest = max(longest, max(reach.values()))
        ends = sorted(
            r
            for r, d in reach.items()
            if own.ego_route_min <= d <= own.ego_route_max and r != start and r in ends_ok
        )
        if not ends:
            continue
        direct = [r for r in ends if graph.straight_distance(start, r) >= 0.5 * reach[r]]
        end = draw.choice(direct or ends)  # rather a trip that goes somewhere than a loop
        edges = list(api.simulation.findRoute(start, end, EGO_TYPE).edges)
        if edges:
            return edges
    raise invalid_option(
        f"no ego trip of {own.ego_route_min:g}-{own.ego_route_max:g} m on this network (the "
        f"longest found: {longest:.0f} m): lower ego_route_min or raise ego_route_max"
    )


def map_config(net_file: Path) -> str:
    """The .sumocfg of a map's episode: the network, the episode's route file beside it, the
    settings forced on every scenario, and a map's own (humans stuck in a gridlock leave after
    `TELEPORT_AFTER_S`, trips that cannot start are dropped, a trip without a route too)."""
    return (
        "<configuration>\n"
        "    <input>\n"
        f'        <net-file value="{net_file}"/>\n'
        '        <route-files value="trips.rou.xml"/>\n'
        "    </input>\n"
        "    <time>\n"
        f'        <step-length value="{ROAD_STEP_LENGTH}"/>\n'
        "    </time>\n"
        "    <processing>\n"
        '        <collision.action value="warn"/>\n'
        '        <collision.mingap-factor value="0"/>\n'
        '        <collision.check-junctions value="true"/>\n'
        f'        <max-depart-delay value="{MAX_DEPART_DELAY_S:g}"/>\n'
        '        <lanechange.duration value="2"/>\n'
        '        <ignore-route-errors value="true"/>\n'
        "    </processing>\n"
        "    <report>\n"
        '        <no-step-log value="true"/>\n'
        '        <no-warnings value="true"/>\n'
        "    </report>\n"
        "</configuration>\n"
    )


def build_osm(osm_file: Path, cache_dir: Path, log: Any = None) -> Path:
    """The network netconvert builds from an OSM export (`OSM_OPTIONS`), built once into the
    cache (keyed by the export's content and the options); its path."""
    options = hashlib.sha256("\0".join(OSM_OPTIONS).encode()).hexdigest()[:8]
    folder = cache_dir / "maps" / f"{_stem(osm_file)}-{file_digest(osm_file)}-{options}"
    net = folder / "map.net.xml.gz"
    if net.is_file():
        return net
    tmp = folder.with_name(f"{folder.name}.tmp{os.getpid()}")
    tmp.mkdir(parents=True, exist_ok=True)
    typemap = Path(find_sumo_tool("data")) / "typemap" / "osmNetconvert.typ.xml"
    command = [
        find_sumo_tool("netconvert"),
        "--osm-files", str(osm_file.resolve()),
        *(["--type-files", str(typemap)] if typemap.is_file() else []),
        *OSM_OPTIONS,
        "--output-file", str(tmp / net.name),
        "--no-warnings", "true",
    ]  # fmt: skip
    if log is not None:
        log(f"building the network of {osm_file} with netconvert (once; cached in {folder})")
    try:
        result = subprocess.run(
            command, capture_output=True, text=True, timeout=OSM_TIMEOUT_S, check=False
        )
    except subprocess.TimeoutExpired as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        raise RuntimeError(
            f"netconvert took longer than {OSM_TIMEOUT_S:g} s on {osm_file}"
        ) from exc
    if result.returncode != 0 or not (tmp / net.name).is_file():
        shutil.rmtree(tmp, ignore_errors=True)
        detail = (result.stderr or result.stdout).strip().splitlines()
        raise RuntimeError(
            f"netconvert could not import {osm_file}: {detail[-1] if detail else result.returncode}"
        )
    (tmp / "netconvert.args").write_text("\n".join(command[1:]) + "\n")
    try:
        tmp.rename(folder)
    except OSError:  # another process built it meanwhile
        shutil.rmtree(tmp, ignore_errors=True)
    return net


def map_name(path: Path) -> str:
    """A map's scenario name: the file's name without its extensions."""
    return _stem(path)


def _stem(path: Path) -> str:
    name = path.name
    for suffix in (".gz", ".xml", ".net", ".osm"):
        name = name.removesuffix(suffix)
    return name or "map"
