"""Built-in motorway corridors with a lane end: an on-ramp, an exit and a lane drop.

* ``merge``    - the ego enters from an on-ramp and must leave its acceleration lane for a
  motorway of two or three lanes before the lane ends.
* ``exit``     - the ego's route leaves the motorway by an off-ramp on the right, after a
  deceleration lane; it starts in any lane of two to four.
* ``lanedrop`` - three lanes become two: the left or the right lane ends.

The geometry is drawn from the episode's seed (ramp and acceleration-lane lengths, the distance
to the exit or the drop, the lanes), so that a policy learns to read the road (`Road` on the
wire) rather than one road by heart; each option of the geometry fixes it instead when set. The
draws come from short grids, so that a handful of networks serve every seed: each is built once
by netconvert into the scenario cache (`scenarios.write_scenario`), like ``cf``.
"""

from __future__ import annotations

import random
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

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
from sim_server.backends.sumo.humans import human_type
from sim_server.backends.sumo.scenarios import (
    EGO_ROUTE,
    EGO_TYPE_LINE,
    HUMAN_TYPE,
    MEASURE_OPTIONS,
    ROAD_STEP_LENGTH,
    ScenarioFiles,
    write_scenario,
)

MOTORWAY_SPEEDS = (80 / 3.6, 100 / 3.6, 120 / 3.6)
"""The motorway speed limits a seed draws from with ``motorway_speed`` 0 (m/s)."""
MOTORWAY_SPEED = MOTORWAY_SPEEDS[1]
"""The motorway's speed limit unless an option says otherwise (m/s): 100 km/h."""
MIN_MOTORWAY_SPEED = 5.0
"""m/s: the slowest motorway option `motorway_speed` sets."""
RAMP_SPEED = 80 / 3.6
"""Their ramps' speed limit (m/s)."""
DOWNSTREAM = 500.0
"""Metres of motorway after the merge, the drop or the exit: where the ego's route goes on."""
RAMP_ANGLE = 0.15
"""Slope of an on-ramp or off-ramp against the motorway (rad, about 9 degrees)."""

MERGE_LANES = (2, 3)
ACCELERATION_LANES = (150.0, 200.0, 250.0, 300.0)
RAMP_LENGTHS = (150.0, 250.0, 350.0)
EXIT_LANES = (2, 3, 4)
EXIT_DISTANCES = (600.0, 800.0, 1000.0, 1200.0)
DECELERATION_LANES = (100.0, 200.0)
DROP_DISTANCES = (400.0, 600.0, 800.0, 1000.0)
DROPPED_LANES = ("left", "right")
"""The grids the geometry is drawn from, uniformly and independently, per seed."""

_EGO_START = ("ramp", "main")
_DROPPED = ("random", *DROPPED_LANES)


@dataclass(frozen=True, slots=True)
class MergeOptions(ParsedOptions):
    """The on-ramp: 0 (or ``random``) draws a value per seed, anything else fixes it."""

    main_lanes: int = 0
    """Lanes of the motorway, 2 or 3 (0: drawn)."""
    acceleration_lane: float = 0.0
    """Length of the acceleration lane (m; 0: drawn from 150-300 m)."""
    ramp_length: float = 0.0
    """Length of the ramp before it (m; 0: drawn from 150-350 m)."""
    ramp_flow: float = 300.0
    """Vehicles per hour entering from the ramp (the motorway's is ``flow`` per lane)."""
    motorway_speed: float = MOTORWAY_SPEED
    """The motorway's speed limit (m/s; 100 km/h; 0: drawn, 80, 100 or 120 km/h; the ramps'
    is 80)."""
    ego_start: str = "ramp"
    """Where the ego enters: ``ramp`` (it must merge) or ``main`` (the merging traffic comes in
    beside it)."""

    BOUNDS: ClassVar[Mapping[str, Bounds]] = {
        "main_lanes": Bounds(0, 3, text="0 (drawn), 2 or 3"),
        "acceleration_lane": Bounds(0.0, 2000.0, unit=" m"),
        "ramp_length": Bounds(0.0, 2000.0, unit=" m"),
        "ramp_flow": Bounds(0.0, 3600.0, unit=" veh/h"),
        "motorway_speed": Bounds(0.0, 70.0, unit=" m/s"),
    }

    def check(self) -> None:
        if self.main_lanes == 1:
            raise invalid_option("option main_lanes must be 0 (drawn), 2 or 3")
        if 0 < self.acceleration_lane < 20 or 0 < self.ramp_length < 20:
            raise invalid_option("options acceleration_lane and ramp_length must be 0 or >= 20 m")
        _one_of("ego_start", self.ego_start, _EGO_START)
        _speed_limit(self.motorway_speed)


@dataclass(frozen=True, slots=True)
class ExitOptions(ParsedOptions):
    """The exit: 0 draws a value per seed, anything else fixes it."""

    main_lanes: int = 0
    """Lanes of the motorway, 2 to 4 (0: drawn)."""
    exit_distance: float = 0.0
    """Metres from the ego's start to where the off-ramp leaves (0: drawn from 600-1200 m)."""
    deceleration_lane: float = 0.0
    """Length of the deceleration lane before it (m; 0: drawn, 100 or 200 m)."""
    motorway_speed: float = MOTORWAY_SPEED
    """The motorway's speed limit (m/s; 100 km/h; 0: drawn, 80, 100 or 120 km/h; the ramps'
    is 80)."""
    exit_share: float = 0.2
    """Share of the human traffic that takes the exit."""
    ego_lane: int = -1
    """The ego's lane at its start, 0 the rightmost (-1: random; one beyond the motorway's
    lanes is its leftmost)."""

    BOUNDS: ClassVar[Mapping[str, Bounds]] = {
        "main_lanes": Bounds(0, 4, text="0 (drawn), 2, 3 or 4"),
        "exit_distance": Bounds(0.0, 10_000.0, unit=" m"),
        "deceleration_lane": Bounds(0.0, 1000.0, unit=" m"),
        "exit_share": Bounds(0.0, 1.0, text="within [0, 1]"),
        "motorway_speed": Bounds(0.0, 70.0, unit=" m/s"),
        "ego_lane": Bounds(-1, 3),
    }

    def check(self) -> None:
        if self.main_lanes == 1:
            raise invalid_option("option main_lanes must be 0 (drawn), 2, 3 or 4")
        if 0 < self.deceleration_lane < 20:
            raise invalid_option("option deceleration_lane must be 0 or >= 20 m")
        _speed_limit(self.motorway_speed)
        deceleration = self.deceleration_lane or max(DECELERATION_LANES)  # the longest drawn
        if self.exit_distance and self.exit_distance < deceleration + 100:
            raise invalid_option(
                "option exit_distance must leave at least 100 m before the deceleration lane "
                f"({deceleration:g} m here: exit_distance >= {deceleration + 100:g})"
            )


@dataclass(frozen=True, slots=True)
class LaneDropOptions(ParsedOptions):
    """The lane drop: 0 (or ``random``) draws a value per seed, anything else fixes it."""

    drop_distance: float = 0.0
    """Metres from the ego's start to where the lane ends (0: drawn from 400-1000 m)."""
    dropped_lane: str = "random"
    """Which of the three lanes ends: ``left``, ``right`` or ``random`` (drawn)."""
    motorway_speed: float = MOTORWAY_SPEED
    """The motorway's speed limit (m/s; 100 km/h; 0: drawn, 80, 100 or 120 km/h)."""
    ego_lane: int = -1
    """The ego's lane at its start, 0 the rightmost (-1: random)."""

    BOUNDS: ClassVar[Mapping[str, Bounds]] = {
        "drop_distance": Bounds(0.0, 10_000.0, unit=" m"),
        "motorway_speed": Bounds(0.0, 70.0, unit=" m/s"),
        "ego_lane": Bounds(-1, 2),
    }

    def check(self) -> None:
        if 0 < self.drop_distance < 100:
            raise invalid_option("option drop_distance must be 0 or >= 100 m")
        _one_of("dropped_lane", self.dropped_lane, _DROPPED)
        _speed_limit(self.motorway_speed)


def _speed_limit(value: float) -> None:
    if 0 < value < MIN_MOTORWAY_SPEED:
        raise invalid_option(
            f"option motorway_speed must be 0 (drawn) or >= {MIN_MOTORWAY_SPEED:g} m/s"
        )


def _one_of(name: str, value: str, valid: tuple[str, ...]) -> None:
    if value not in valid:
        raise invalid_option(f"option {name} must be one of {', '.join(valid)}, got {value[:64]!r}")


CorridorOptions = MergeOptions | ExitOptions | LaneDropOptions


@dataclass(frozen=True)
class Network:
    """One drawn geometry as netconvert's plain files, the routes, and the ego's start."""

    nodes: list[tuple[str, float, float]]
    edges: list[tuple[str, str, str, int, float, float]]
    """(id, from, to, lanes, speed limit, length): the length as drawn, which SUMO keeps
    whatever the junctions' shapes take off an edge's drawing."""
    connections: list[tuple[str, str, int, int]]
    """(from edge, to edge, from lane, to lane): every lane-to-lane link, no other."""
    routes: dict[str, str]
    """Route id -> its edges; `EGO_ROUTE` is the ego's."""
    flows: list[tuple[str, str, float, str]]
    """(route, departLane, veh/h, id suffix) of the human traffic."""
    depart_lane: str = "random"
    """The ego's departLane."""


@dataclass(frozen=True)
class CorridorScenario:
    """A built-in corridor: `kind` is ``merge``, ``exit`` or ``lanedrop``."""

    name: str
    description: str
    kind: str
    defaults: dict[str, OptionValue] = field(default_factory=dict)

    OPTIONS: ClassVar[dict[str, type[ParsedOptions]]] = {
        "merge": MergeOptions,
        "exit": ExitOptions,
        "lanedrop": LaneDropOptions,
    }

    def info(self) -> ScenarioInfo:
        own = self.OPTIONS[self.kind]().as_options()
        options = {
            **COMMON_OPTIONS,
            "warmup": 60.0,
            **SHARE_OPTIONS,
            **TRAFFIC_OPTIONS,
            "flow": 1000.0,
            **own,
            **MEASURE_OPTIONS,
            **self.defaults,
        }
        return ScenarioInfo(self.name, self.description, options, ROAD_STEP_LENGTH)

    def files(
        self, options: Mapping[str, OptionValue], seed: int, cache_dir: Path
    ) -> ScenarioFiles:
        """Write (or reuse) the files of the geometry `seed` draws; the ego's route and lane."""
        traffic = TrafficOptions.parse(options)
        network = self.network(self.OPTIONS[self.kind].parse(options), traffic, seed)
        config = write_scenario(self.name, network_texts(network, traffic), cache_dir)
        return ScenarioFiles(config, EGO_ROUTE, network.depart_lane)

    def network(self, own: ParsedOptions, traffic: TrafficOptions, seed: int) -> Network:
        """The geometry `seed` draws, with `own` options fixing what they set."""
        draw = random.Random(f"{self.kind}:{seed}")
        if isinstance(own, MergeOptions):
            return merge_network(own, traffic, draw)
        if isinstance(own, ExitOptions):
            return exit_network(own, traffic, draw)
        assert isinstance(own, LaneDropOptions)
        return lane_drop_network(own, traffic, draw)

    def build(self, options: Mapping[str, OptionValue], cache_dir: Path) -> Path:
        """Write (or reuse) the files of seed 0's geometry; the path of its .sumocfg (for the
        image's prebuilt cache: other seeds build theirs on first use)."""
        return self.files(options, 0, cache_dir).config


def merge_network(own: MergeOptions, traffic: TrafficOptions, draw: random.Random) -> Network:
    """main_up (N lanes) and the ramp (1) meet at ``merge`` (N + 1: lane 0 the acceleration
    lane, which ends), then main_down (N)."""
    lanes = own.main_lanes or draw.choice(MERGE_LANES)
    accel = own.acceleration_lane or draw.choice(ACCELERATION_LANES)
    ramp = own.ramp_length or draw.choice(RAMP_LENGTHS)
    speed = own.motorway_speed or draw.choice(MOTORWAY_SPEEDS)
    upstream = ramp + 150.0
    merge_x = upstream
    nodes = [
        ("up", 0.0, 0.0),
        ("ramp_start", merge_x - ramp, -ramp * RAMP_ANGLE),
        ("merge_start", merge_x, 0.0),
        ("merge_end", merge_x + accel, 0.0),
        ("down", merge_x + accel + DOWNSTREAM, 0.0),
    ]
    edges = [
        ("main_up", "up", "merge_start", lanes, speed, upstream),
        ("ramp", "ramp_start", "merge_start", 1, RAMP_SPEED, ramp),
        ("merge", "merge_start", "merge_end", lanes + 1, speed, accel),
        ("main_down", "merge_end", "down", lanes, speed, DOWNSTREAM),
    ]
    connections = [
        ("ramp", "merge", 0, 0),
        *(("main_up", "merge", i, i + 1) for i in range(lanes)),
        *(("merge", "main_down", i + 1, i) for i in range(lanes)),
    ]
    main = "main_up merge main_down"
    from_ramp = "ramp merge main_down"
    routes = {"main": main, "from_ramp": from_ramp}
    routes[EGO_ROUTE] = from_ramp if own.ego_start == "ramp" else main
    flows = [("main", str(i), traffic.flow, f"main{i}") for i in range(lanes)]
    flows.append(("from_ramp", "0", own.ramp_flow, "ramp"))
    return Network(nodes, edges, connections, routes, flows)


def exit_network(own: ExitOptions, traffic: TrafficOptions, draw: random.Random) -> Network:
    """main (N lanes), then ``decel`` (N + 1: lane 0 the deceleration lane), which splits into
    the off-ramp (from lane 0 only) and main_down (N)."""
    lanes = own.main_lanes or draw.choice(EXIT_LANES)
    distance = own.exit_distance or draw.choice(EXIT_DISTANCES)
    decel = own.deceleration_lane or draw.choice(DECELERATION_LANES)
    speed = own.motorway_speed or draw.choice(MOTORWAY_SPEEDS)
    main_length = distance - decel
    diverge = distance
    off = 250.0
    nodes = [
        ("start", 0.0, 0.0),
        ("decel_start", main_length, 0.0),
        ("diverge", diverge, 0.0),
        ("end", diverge + DOWNSTREAM, 0.0),
        ("exit_end", diverge + off, -off * RAMP_ANGLE),
    ]
    edges = [
        ("main", "start", "decel_start", lanes, speed, main_length),
        ("decel", "decel_start", "diverge", lanes + 1, speed, decel),
        ("main_down", "diverge", "end", lanes, speed, DOWNSTREAM),
        ("off_ramp", "diverge", "exit_end", 1, RAMP_SPEED, off),
    ]
    connections = [
        *(("main", "decel", i, i + 1) for i in range(lanes)),
        ("decel", "off_ramp", 0, 0),
        *(("decel", "main_down", i + 1, i) for i in range(lanes)),
    ]
    routes = {"through": "main decel main_down", EGO_ROUTE: "main decel off_ramp"}
    flows = []
    for i in range(lanes):
        flows.append(("through", str(i), traffic.flow * (1 - own.exit_share), f"through{i}"))
        flows.append((EGO_ROUTE, str(i), traffic.flow * own.exit_share, f"exit{i}"))
    depart = "random" if own.ego_lane < 0 else str(min(own.ego_lane, lanes - 1))
    return Network(nodes, edges, connections, routes, flows, depart)


def lane_drop_network(
    own: LaneDropOptions, traffic: TrafficOptions, draw: random.Random
) -> Network:
    """``up`` (3 lanes), whose left or right lane ends, then ``down`` (2)."""
    distance = own.drop_distance or draw.choice(DROP_DISTANCES)
    dropped = own.dropped_lane if own.dropped_lane != "random" else draw.choice(DROPPED_LANES)
    speed = own.motorway_speed or draw.choice(MOTORWAY_SPEEDS)
    nodes = [("start", 0.0, 0.0), ("drop", distance, 0.0), ("end", distance + DOWNSTREAM, 0.0)]
    edges = [
        ("up", "start", "drop", 3, speed, distance),
        ("down", "drop", "end", 2, speed, DOWNSTREAM),
    ]
    first = 0 if dropped == "left" else 1  # the lanes of ``up`` that go on
    connections = [("up", "down", first + i, i) for i in range(2)]
    routes = {EGO_ROUTE: "up down"}
    flows = [(EGO_ROUTE, str(i), traffic.flow, f"lane{i}") for i in range(3)]
    depart = "random" if own.ego_lane < 0 else str(own.ego_lane)
    return Network(nodes, edges, connections, routes, flows, depart)


def network_texts(network: Network, traffic: TrafficOptions) -> dict[str, str]:
    """netconvert's plain files (nodes, edges, connections), the routes and the .sumocfg."""
    nodes = "".join(f'    <node id="{n}" x="{x:.2f}" y="{y:.2f}"/>\n' for n, x, y in network.nodes)
    edges = "".join(
        f'    <edge id="{e}" from="{a}" to="{b}" numLanes="{lanes}" speed="{speed:.4f}" '
        f'length="{length:.2f}"/>\n'
        for e, a, b, lanes, speed, length in network.edges
    )
    connections = "".join(
        f'    <connection from="{a}" to="{b}" fromLane="{i}" toLane="{j}"/>\n'
        for a, b, i, j in network.connections
    )
    routes = "".join(
        f'    <route id="{route}" edges="{edges}"/>\n' for route, edges in network.routes.items()
    )
    mean, dev = traffic.speed_factor_mean, traffic.speed_factor_dev
    flows = "".join(
        f'    <flow id="human_{name}" type="{HUMAN_TYPE}" route="{route}" begin="0" '
        f'end="86400" period="exp({rate / 3600:.6f})" departLane="{lane}" departPos="base" '
        'departSpeed="max"/>\n'
        for route, lane, rate, name in network.flows
        if rate > 0
    )
    return {
        "road.nod.xml": f"<nodes>\n{nodes}</nodes>\n",
        "road.edg.xml": f"<edges>\n{edges}</edges>\n",
        "road.con.xml": f"<connections>\n{connections}</connections>\n",
        "routes.rou.xml": (
            "<routes>\n"
            f"{human_type(HUMAN_TYPE, traffic.human_model, traffic.sigma, mean, dev)}"
            f"{EGO_TYPE_LINE}"
            f"{routes}{flows}"
            "</routes>\n"
        ),
    }


CORRIDORS: dict[str, CorridorScenario] = {
    s.name: s
    for s in (
        CorridorScenario(
            "merge",
            "on-ramp: the ego enters from a ramp and must merge from its acceleration lane onto "
            "a motorway of 2-3 lanes (80-120 km/h, 1000 veh/h/lane); geometry drawn per seed",
            "merge",
        ),
        CorridorScenario(
            "exit",
            "exit: the ego's route leaves a motorway of 2-4 lanes by an off-ramp on the right, "
            "600-1200 m ahead after a deceleration lane; it starts in any lane; drawn per seed",
            "exit",
        ),
        CorridorScenario(
            "lanedrop",
            "lane drop: three motorway lanes (800 veh/h/lane) become two, the left or the right "
            "one ending 400-1000 m ahead; the ego starts in any lane; drawn per seed",
            "lanedrop",
            defaults={"flow": 800.0},
        ),
    )
}
