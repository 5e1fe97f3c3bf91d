"""highway-env (Farama's highway simulator) behind the bridge: the same protocol, another simulator.

`sim-server --backend highway` serves ``cf`` (one lane) and ``cflc`` (three lanes) on a 2 km
straight road at 80 km/h, and the corridors ``merge`` (the ego enters from an on-ramp), ``exit``
(its route leaves by an off-ramp on the right) and ``lanedrop`` (three lanes become two), whose
geometry is drawn from the seed from the SUMO corridors' grids (`sumo.corridors`: the same seed
draws the same lengths and lanes on both servers). Every road is populated with highway-env's own
human drivers (`IDMVehicle`: IDM car following, MOBIL lane changing). highway-env's gym actions
cannot express the protocol's action, so the scene is built with highway-env's own API, as
``HighwayEnv._create_vehicles`` and ``MergeEnv._make_road`` do, and advanced with ``road.act()``
and ``road.step(dt)``, the two calls of ``AbstractEnv._simulate``, at 10 Hz: the SUMO server's
0.1 s and 1.0 s decision intervals are then whole numbers of steps. The client's ego keeps
highway-env's lateral controller (lane keeping and lane changes) and gets the commanded
acceleration. How each part of the protocol maps onto highway-env, and where it differs from
SUMO: docs/backends.md.

The road ahead (protocol 1.6, `Road` on every observation) is read off highway-env's road network
along the egos' route (`_Layout`): where each lane stops leading on, and which lanes of the ego's
road lead farthest. A lane that ends is also a standing obstacle for highway-env's humans (as in
``MergeEnv``), which they do not collide with. An ego whose front passes the end of its lane (an
acceleration lane it did not leave, a dropped lane, a lane past the exit it had to take) ends
there at once with ``lane_end``: highway-env would carry it on along a lane that does not exist.

Many egos (protocol 1.4, a reset naming ``egos`` > 1, at most `MAX_HIGHWAY_EGOS`): highway-env's
own multi-agent placement (``controlled_vehicles``: each controlled vehicle followed by its share
of the humans; on ``merge`` the egos one after another on the ramp), driven as the one ego is,
each alone (`_Driven`); ids ``ego.0``, ``ego.1``, ... in the order of highway-env's
``controlled_vehicles`` (rearmost first). An ego whose drive ends is reported once and removed
from the road. ``egos`` 1 is the one-ego episode under the id ``ego``.
"""

from __future__ import annotations

import itertools
import math
import random
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

import highway_env
import numpy as np
from highway_env.road.lane import CircularLane, LineType, SineLane, StraightLane
from highway_env.road.road import Road as HighwayRoad
from highway_env.road.road import RoadNetwork
from highway_env.utils import near_split
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import ControlledVehicle
from highway_env.vehicle.kinematics import Vehicle
from highway_env.vehicle.objects import Obstacle

from protocol.errors import ErrorCode
from protocol.messages import (
    ROAD_RANGE,
    AccelerationLimit,
    AppliedAction,
    Ego,
    EgoObservation,
    EndReason,
    Events,
    LeaderTrip,
    MultiObservation,
    Neighbour,
    Neighbours,
    Observation,
    OptionValue,
    Road,
    ScenarioInfo,
)
from sim_server.backends.base import Backend, Commands, ego_part
from sim_server.backends.options import (
    COMMON_OPTIONS,
    Bounds,
    EpisodeOptions,
    ParsedOptions,
    invalid_option,
)
from sim_server.backends.rules import (
    EndRule,
    LaneChangeUnderWay,
    ended,
    lane_change_refusal,
    limit_acceleration,
)
from sim_server.backends.sumo.corridors import (
    ACCELERATION_LANES,
    DECELERATION_LANES,
    DOWNSTREAM,
    DROP_DISTANCES,
    DROPPED_LANES,
    EXIT_DISTANCES,
    EXIT_LANES,
    MERGE_LANES,
    MOTORWAY_SPEED,
    RAMP_LENGTHS,
    RAMP_SPEED,
)
from sim_server.errors import BackendError

SIMULATION_FREQUENCY = 10
"""Simulation steps per second (highway-env's ``simulation_frequency``)."""
DT = 1.0 / SIMULATION_FREQUENCY
EGO_ID = "ego"
MAX_HIGHWAY_EGOS = 16
"""The most egos of one episode (``controlled_vehicles``); highway-env's cost is O(N²) per step
in the vehicles on the road."""
CEILING_HORIZON = 3600.0
"""Longest extra simulated time (s) spent waiting for the leader-at-entry to arrive."""
LANE_CHANGE_TOLERANCE = 0.1
"""A lane change is complete when the ego is within this lateral distance (m) of the target
lane's centre (highway-env's lateral controller converges exponentially, never exactly)."""
SIMULATOR_DRIVERS = ("simulator", "sumo")
"""Values of ``ego_driver`` that let highway-env's human model drive the ego."""

LANE_WIDTH = StraightLane.DEFAULT_WIDTH
"""highway-env's lane width (m)."""
RAMP_OFFSET = 6.5
"""Metres between the start of an on-ramp and the acceleration lane it leads into, sideways (its
``SineLane`` converges over the whole ramp; ``MergeEnv``'s converges by the same 6.5 m)."""
OFF_RAMP = 250.0
"""Length of the exit's off-ramp (m), as the SUMO corridor's."""
OFF_RAMP_RADIUS = 500.0
"""Radius of the off-ramp's arc (m): it bends away to the right, as ``ExitEnv``'s does."""
LANE_DROP_LANES = 3
"""Lanes of ``lanedrop`` before the drop."""
JOIN_TOLERANCE = 0.5
"""Metres within which a lane's end and a lane start of the next road on the route are one
point: the first leads into the second."""
START_ROOM = 100.0
"""Metres a human needs ahead in a lane that ends to be placed in it, and an ego to start in it
(on ``merge``, before the end of the acceleration lane)."""

_HONOURED = (
    "decision_interval",
    "max_episode_time",
    "warmup",
    "stop_speed",
    "stop_gap",
    "stop_patience",
    "lane_end_patience",
    "report_ceiling",
    "ego_driver",
    "egos",
)
"""The SUMO server's common options this backend honours: the same meaning, except that during
the ``warmup`` highway-env's own human model drives the ego (it is on the road from the start)."""

_REFERENCE_IDM = IDMVehicle(None, np.zeros(2))
"""IDM parameters for safety checks of a vehicle that is not itself an IDM vehicle (the ego)."""

LaneIndex = tuple[str, str, int]
"""highway-env's lane index: (from node, to node, lane id counted from the left)."""
RoadId = tuple[str, str]
"""A road of highway-env's network: its lanes share (from node, to node)."""


@dataclass(frozen=True, slots=True)
class SceneOptions(ParsedOptions):
    """How highway-env's ``create_random`` places the humans: `vehicles_behind` of them behind
    the ego, the rest ahead, one ``1 / vehicles_density`` spacing apart."""

    vehicles_count: int = 12
    """Human vehicles (highway-env's ``vehicles_count``)."""
    vehicles_behind: int = 2
    """Of which placed behind the ego, at most `vehicles_count`."""
    vehicles_density: float = 0.6
    """highway-env's ``vehicles_density``."""

    BOUNDS: ClassVar[Mapping[str, Bounds]] = {
        "vehicles_count": Bounds(0, 200, text="in 0..200"),
        "vehicles_density": Bounds(0.05, 10.0, text="within [0.05, 10]"),
    }

    def check(self) -> None:
        if not 0 <= self.vehicles_behind <= self.vehicles_count:
            raise invalid_option("option vehicles_behind must be in 0..vehicles_count")


@dataclass(frozen=True, slots=True)
class MergeOptions(ParsedOptions):
    """The on-ramp (the SUMO corridor's names): 0 draws a value per seed, anything else fixes
    it."""

    main_lanes: int = 0
    """Lanes of the motorway, 2 or 3 (0: drawn)."""
    acceleration_lane: float = 0.0
    """Length of the acceleration lane (m; 0: drawn from 150-300 m)."""
    ramp_length: float = 0.0
    """Length of the ramp before it (m; 0: drawn from 150-350 m)."""
    ramp_vehicles: int = 2
    """Humans on the ramp ahead of the ego, as many as fit on it (SUMO's ``ramp_flow`` instead:
    highway-env's traffic is placed at reset, it does not flow in)."""

    BOUNDS: ClassVar[Mapping[str, Bounds]] = {
        "main_lanes": Bounds(0, 3, text="0 (drawn), 2 or 3"),
        "acceleration_lane": Bounds(0.0, 2000.0, unit=" m"),
        "ramp_length": Bounds(0.0, 2000.0, unit=" m"),
        "ramp_vehicles": Bounds(0, 20),
    }

    def check(self) -> None:
        if self.main_lanes == 1:
            raise invalid_option("option main_lanes must be 0 (drawn), 2 or 3")
        if 0 < self.acceleration_lane < 20 or 0 < self.ramp_length < 20:
            raise invalid_option("options acceleration_lane and ramp_length must be 0 or >= 20 m")


@dataclass(frozen=True, slots=True)
class ExitOptions(ParsedOptions):
    """The exit (the SUMO corridor's names): 0 draws a value per seed, anything else fixes it."""

    main_lanes: int = 0
    """Lanes of the motorway, 2 to 4 (0: drawn)."""
    exit_distance: float = 0.0
    """Metres from the ego's front at reset (the frontmost ego's) to where the off-ramp leaves
    (0: drawn from 600-1200 m)."""
    deceleration_lane: float = 0.0
    """Length of the deceleration lane before it (m; 0: drawn, 100 or 200 m)."""
    ego_lane: int = -1
    """The ego's lane at its start, 0 the rightmost (-1: random; one beyond the motorway's
    lanes is its leftmost)."""

    BOUNDS: ClassVar[Mapping[str, Bounds]] = {
        "main_lanes": Bounds(0, 4, text="0 (drawn), 2, 3 or 4"),
        "exit_distance": Bounds(0.0, 10_000.0, unit=" m"),
        "deceleration_lane": Bounds(0.0, 1000.0, unit=" m"),
        "ego_lane": Bounds(-1, 3),
    }

    def check(self) -> None:
        if self.main_lanes == 1:
            raise invalid_option("option main_lanes must be 0 (drawn), 2, 3 or 4")
        if 0 < self.deceleration_lane < 20:
            raise invalid_option("option deceleration_lane must be 0 or >= 20 m")


@dataclass(frozen=True, slots=True)
class LaneDropOptions(ParsedOptions):
    """The lane drop (the SUMO corridor's names): 0 (or ``random``) draws a value per seed,
    anything else fixes it."""

    drop_distance: float = 0.0
    """Metres from the ego's front at reset (the frontmost ego's) to where the lane ends (0:
    drawn from 400-1000 m)."""
    dropped_lane: str = "random"
    """Which of the three lanes ends: ``left``, ``right`` or ``random`` (drawn)."""
    ego_lane: int = -1
    """The ego's lane at its start, 0 the rightmost (-1: random)."""

    BOUNDS: ClassVar[Mapping[str, Bounds]] = {
        "drop_distance": Bounds(0.0, 10_000.0, unit=" m"),
        "ego_lane": Bounds(-1, 2),
    }

    def check(self) -> None:
        if 0 < self.drop_distance < 100:
            raise invalid_option("option drop_distance must be 0 or >= 100 m")
        valid = ("random", *DROPPED_LANES)
        if self.dropped_lane not in valid:
            raise invalid_option(
                f"option dropped_lane must be one of {', '.join(valid)}, "
                f"got {self.dropped_lane[:64]!r}"
            )


def _longitudinal(lane: Any, position: Any) -> float:
    """`position`'s longitudinal coordinate on `lane` (m from its start)."""
    return float(lane.local_coordinates(position)[0])


@dataclass(frozen=True)
class _Layout:
    """A built road network and what the backend reads off it along the egos' route.

    Every road of the network lies on the route. A vehicle's route coordinate is `start` of its
    road plus its longitudinal coordinate on the road's `reference` lane (its longest): for an
    ego's front, the observation's ``position``. A lane leads into the lane of the next road that
    starts where it ends (`successor`). `reach` is the route coordinate where each lane stops
    leading on: the end of a lane of the last road that stops short of the road's end; for a
    lane that leads into none, the point where its road hands over to the next one (the end of
    the lanes that do lead on: an exit); else the reach of the lane it leads into. A lane that
    reaches the route's end has an infinite reach.
    """

    network: Any
    route: tuple[RoadId, ...]
    """The egos' roads, in order."""
    finals: frozenset[RoadId]
    """Roads whose end is an arrival (the humans leave the road there)."""
    reference: dict[RoadId, Any]
    start: dict[RoadId, float]
    reach: dict[LaneIndex, float]
    successor: dict[LaneIndex, LaneIndex]
    predecessor: dict[LaneIndex, LaneIndex]
    best: dict[RoadId, tuple[int, ...]]
    """The lanes of each road that lead farthest along the route."""
    dead_ends: frozenset[LaneIndex]
    """Lanes that come to an end before their road does (an obstacle marks each end)."""

    @classmethod
    def of(cls, network: Any, route: tuple[RoadId, ...], finals: frozenset[RoadId]) -> _Layout:
        """The layout of `network` along `route`; ValueError if a road does not lead into the
        next one."""
        lanes = {road: network.graph[road[0]][road[1]] for road in route}
        reference = {
            road: max(found, key=lambda lane: lane.length) for road, found in lanes.items()
        }
        successor, start = _joins(route, lanes, reference)
        reach, best, dead_ends = _reaches(route, lanes, reference, start, successor)
        predecessor = {after: before for before, after in successor.items()}
        return cls(
            network, route, finals, reference, start, reach, successor, predecessor, best,
            dead_ends,
        )  # fmt: skip

    def _coordinate(self, road: RoadId, point: Any) -> float:
        return self.start[road] + _longitudinal(self.reference[road], point)

    def end_of(self, road: RoadId) -> float:
        """Route coordinate of `road`'s end."""
        return self.start[road] + float(self.reference[road].length)

    @property
    def length(self) -> float:
        """The route's length (m): where the egos' drive ends (``end_of_road``)."""
        return self.end_of(self.route[-1])

    def along(self, vehicle: Any) -> float:
        """Route coordinate of `vehicle`'s front."""
        road = vehicle.lane_index[:2]
        return self._coordinate(road, vehicle.position) + vehicle.LENGTH / 2

    def arrived(self, vehicle: Any) -> bool:
        """`vehicle`'s front passed the end of a road where the traffic leaves."""
        road = vehicle.lane_index[:2]
        return road in self.finals and self.along(vehicle) >= self.end_of(road)

    def drives_route(self, vehicle: Any) -> bool:
        """Whether `vehicle`, driving on from its road, leaves where the route ends: the humans
        leave at the end of the first road of `finals` they reach (on ``exit``, the motorway's:
        they drive on past the exit)."""
        roads = self.route[self.route.index(vehicle.lane_index[:2]) :]
        return next((road for road in roads if road in self.finals), None) == self.route[-1]

    def at_route_end(self, ego: Any) -> bool:
        """The ego's front passed the end of its route."""
        return ego.lane_index[:2] == self.route[-1] and self.along(ego) >= self.length

    def past_lane_end(self, ego: Any) -> bool:
        """The ego's front passed the point where its lane stops leading on."""
        return self.along(ego) > self.reach.get(ego.lane_index, math.inf)

    def to_end(self, vehicle: Any) -> float:
        """Metres from `vehicle`'s front to where its lane stops leading on (inf: never)."""
        return self.reach.get(vehicle.lane_index, math.inf) - self.along(vehicle)

    def lanes_at(self, index: LaneIndex, position: Any) -> list[int]:
        """The lanes of `index`'s road at `position`, counted from the left: its own and those
        whose stretch covers it (an acceleration lane exists only along its stretch)."""
        _from, _to, own = index
        return [
            j
            for j, lane in enumerate(self.network.graph[_from][_to])
            if j == own or 0.0 <= _longitudinal(lane, position) <= lane.length
        ]

    def road_ahead(self, ego: Any, lanes: list[int]) -> Road:
        """The ego's `Road`, among the `lanes` of its road beside it (`lanes_at`).

        The lane to change to is the nearest of those that lead farthest; between lanes that lead
        equally far (the lanes before an exit's deceleration lane), the one nearest the lanes
        that lead farthest on the whole road (the rightmost, before an exit)."""
        _from, _to, own = ego.lane_index
        front = self.along(ego)

        def ahead(lane: int) -> float:
            left = self.reach.get((_from, _to, lane), math.inf) - front
            return ROAD_RANGE if left >= ROAD_RANGE else max(0.0, left)

        reaches = {j: self.reach.get((_from, _to, j), math.inf) for j in lanes}
        top = max(reaches.values())
        best = self.best.get((_from, _to), (own,))
        target = min(
            (j for j, reach in reaches.items() if reach >= top),
            key=lambda j: (min(abs(j - b) for b in best), abs(j - own)),
        )
        return Road(
            ahead(own),
            own - target,  # highway-env counts from the left: a lane to the left has a lower id
            ahead(own - 1) if own - 1 in lanes else 0.0,
            ahead(own + 1) if own + 1 in lanes else 0.0,
        )

    def leads_to_dead_end(self, index: LaneIndex) -> bool:
        """Whether lane `index`, or a lane it leads into, comes to an end."""
        while index not in self.dead_ends:
            following = self.successor.get(index)
            if following is None:
                return False
            index = following
        return True

    def plan(self, index: LaneIndex) -> list[tuple[str, str, int | None]]:
        """highway-env's ``route`` for a vehicle on lane `index`, to the route's end: on each road
        the lane it must reach, where its own does not lead farthest (highway-env's MOBIL then
        changes towards it whenever that is safe), else None."""
        plan: list[tuple[str, str, int | None]] = []
        lane: LaneIndex | None = index
        for road in self.route[self.route.index(index[:2]) :]:
            target = None
            best = self.best[road]
            if lane is not None and lane[2] not in best:
                entered = lane[2]
                target = min(best, key=lambda b: abs(b - entered))
            plan.append((*road, target))
            if lane is not None:
                lane = self.successor.get((*road, lane[2] if target is None else target))
        return plan


def _joins(
    route: tuple[RoadId, ...], lanes: dict[RoadId, list[Any]], reference: dict[RoadId, Any]
) -> tuple[dict[LaneIndex, LaneIndex], dict[RoadId, float]]:
    """Which lane leads into which along `route` (the next road's lane that starts where it
    ends), and the route coordinate of each road's start (0 for the first)."""
    successor: dict[LaneIndex, LaneIndex] = {}
    start = {route[0]: 0.0}
    for here, there in itertools.pairwise(route):
        for i, lane in enumerate(lanes[here]):
            end = lane.position(lane.length, 0.0)
            for j, following in enumerate(lanes[there]):
                if np.linalg.norm(following.position(0.0, 0.0) - end) < JOIN_TOLERANCE:
                    successor[(*here, i)] = (*there, j)
                    break
        joins = [i for i in range(len(lanes[here])) if (*here, i) in successor]
        if not joins:
            raise ValueError(f"no lane of road {here} leads into road {there}")
        lane = lanes[here][joins[0]]
        point = lane.position(lane.length, 0.0)
        start[there] = (
            start[here]
            + _longitudinal(reference[here], point)
            - _longitudinal(reference[there], point)
        )
    return successor, start


def _reaches(
    route: tuple[RoadId, ...],
    lanes: dict[RoadId, list[Any]],
    reference: dict[RoadId, Any],
    start: dict[RoadId, float],
    successor: dict[LaneIndex, LaneIndex],
) -> tuple[dict[LaneIndex, float], dict[RoadId, tuple[int, ...]], frozenset[LaneIndex]]:
    """`_Layout.reach`, `best` and `dead_ends`, from the route's last road back."""
    reach: dict[LaneIndex, float] = {}
    best: dict[RoadId, tuple[int, ...]] = {}
    dead_ends: set[LaneIndex] = set()
    for k in reversed(range(len(route))):
        road = route[k]
        road_end = start[road] + float(reference[road].length)
        ends = {
            (*road, i): start[road]
            + _longitudinal(reference[road], lane.position(lane.length, 0.0))
            for i, lane in enumerate(lanes[road])
        }
        dead_ends |= {
            index
            for index, end in ends.items()
            if index not in successor and end < road_end - JOIN_TOLERANCE
        }
        handover = max((end for index, end in ends.items() if index in successor), default=road_end)
        for index, end in ends.items():
            if index in successor:
                reach[index] = reach[successor[index]]
            elif k == len(route) - 1:
                reach[index] = math.inf if end >= road_end - JOIN_TOLERANCE else end
            else:
                reach[index] = min(end, handover)
        top = max(reach[index] for index in ends)
        best[road] = tuple(index[2] for index in ends if reach[index] >= top)
    return reach, best, frozenset(dead_ends)


def _straight_layout(lanes: int, length: float, speed_limit: float) -> _Layout:
    """highway-env's straight road (``straight_road_network``): every lane leads on."""
    network = RoadNetwork.straight_road_network(lanes, length=length, speed_limit=speed_limit)
    road = ("0", "1")
    return _Layout.of(network, (road,), frozenset({road}))


def _merge_layout(lanes: int, ramp: float, acceleration: float, ramp_start: float) -> _Layout:
    """``MergeEnv._make_road``'s road, the ego's way: the motorway (``a`` to ``b``, `lanes`
    lanes from x = 0) with an acceleration lane on its right (its last lane, from the ramp's end
    for `acceleration` m), and the ramp (``ramp`` to ``a``: a `SineLane` from `ramp_start`,
    converging by `RAMP_OFFSET`) that leads into it; the motorway goes on `DOWNSTREAM` m after."""
    merge = ramp_start + ramp
    network = RoadNetwork.straight_road_network(
        lanes, length=merge + acceleration + DOWNSTREAM, speed_limit=MOTORWAY_SPEED,
        nodes_str=("a", "b"),
    )  # fmt: skip
    y = lanes * LANE_WIDTH
    c, n = LineType.CONTINUOUS_LINE, LineType.NONE
    network.add_lane(
        "a", "b",
        StraightLane([merge, y], [merge + acceleration, y], line_types=(n, c), forbidden=True,
                     speed_limit=MOTORWAY_SPEED),
    )  # fmt: skip
    amplitude = RAMP_OFFSET / 2
    network.add_lane(
        "ramp", "a",
        SineLane([ramp_start, y + amplitude], [merge, y + amplitude], amplitude, np.pi / ramp,
                 np.pi / 2, line_types=(c, c), forbidden=True, speed_limit=RAMP_SPEED),
    )  # fmt: skip
    return _Layout.of(network, (("ramp", "a"), ("a", "b")), frozenset({("a", "b")}))


def _exit_layout(lanes: int, diverge: float, deceleration: float) -> _Layout:
    """``ExitEnv._create_road``'s road, the ego's way: the motorway (``a`` to ``b``, `lanes`
    lanes from x = 0 to `DOWNSTREAM` m after the diverge at x = `diverge`), a deceleration lane on
    its right (its last lane, `deceleration` m up to the diverge), and the off-ramp it leads into
    (``b`` to ``exit``: a `CircularLane` bending right, `OFF_RAMP` m), the egos' way out."""
    network = RoadNetwork.straight_road_network(
        lanes, length=diverge + DOWNSTREAM, speed_limit=MOTORWAY_SPEED, nodes_str=("a", "b")
    )
    y = lanes * LANE_WIDTH
    s, c = LineType.STRIPED, LineType.CONTINUOUS_LINE
    network.add_lane(
        "a", "b",
        StraightLane([diverge - deceleration, y], [diverge, y], line_types=(s, c),
                     speed_limit=MOTORWAY_SPEED),
    )  # fmt: skip
    bend = -np.pi / 2
    network.add_lane(
        "b", "exit",
        CircularLane([diverge, y + OFF_RAMP_RADIUS], OFF_RAMP_RADIUS, bend,
                     bend + OFF_RAMP / OFF_RAMP_RADIUS, clockwise=True, line_types=(c, c),
                     forbidden=True, speed_limit=RAMP_SPEED),
    )  # fmt: skip
    return _Layout.of(network, (("a", "b"), ("b", "exit")), frozenset({("a", "b"), ("b", "exit")}))


def _lane_drop_layout(dropped: int, drop: float) -> _Layout:
    """Three lanes (``a`` to ``b``, from x = 0) of which lane `dropped` (0 the left, 2 the right)
    ends at x = `drop`, the others `DOWNSTREAM` m later; highway-env has no lane-drop scene, so
    this is its straight road with one lane cut short."""
    network = RoadNetwork()
    last = LANE_DROP_LANES - 1
    for i in range(LANE_DROP_LANES):
        end = drop if i == dropped else drop + DOWNSTREAM
        lines = (
            LineType.CONTINUOUS_LINE if i == 0 else LineType.STRIPED,
            LineType.CONTINUOUS_LINE if i == last else LineType.NONE,
        )
        network.add_lane(
            "a", "b",
            StraightLane([0.0, i * LANE_WIDTH], [end, i * LANE_WIDTH], line_types=lines,
                         forbidden=i == dropped, speed_limit=MOTORWAY_SPEED),
        )  # fmt: skip
    return _Layout.of(network, (("a", "b"),), frozenset({("a", "b")}))


@dataclass
class _Scene:
    """A scenario's road with its vehicles placed, before the warm-up."""

    road: Any
    layout: _Layout
    ids: dict[Any, str]
    """Every vehicle's id: ``h0``, ``h1``... for the humans in spawn order, the egos' names."""
    egos: list[Any]
    """The egos' vehicles, in the order of their names."""


@dataclass(frozen=True)
class HighwayScenario:
    """A straight road with highway-env human traffic on every lane."""

    name: str
    description: str
    lanes: int
    length: float = 2000.0
    speed_limit: float = 80 / 3.6
    defaults: dict[str, OptionValue] = field(default_factory=dict)

    def info(self) -> ScenarioInfo:
        options: dict[str, OptionValue] = {name: COMMON_OPTIONS[name] for name in _HONOURED}
        options.update(warmup=5.0, **SceneOptions().as_options())
        options.update(self.defaults)
        return ScenarioInfo(self.name, self.description, options, DT)

    def build(
        self, seed: int, options: Mapping[str, OptionValue], names: tuple[str, ...]
    ) -> _Scene:
        """The road and its vehicles, placed by highway-env's ``create_random``: `vehicles_behind`
        humans, then each ego of `names` followed by its share of the other humans (highway-env's
        ``near_split``, as its ``_create_vehicles`` places ``controlled_vehicles``)."""
        scene = SceneOptions.parse(options)
        layout = _straight_layout(self.lanes, self.length, self.speed_limit)
        road = HighwayRoad(
            network=layout.network, np_random=np.random.default_rng(seed), record_history=False
        )
        spacing = 1.0 / scene.vehicles_density
        shares = near_split(scene.vehicles_count - scene.vehicles_behind, num_bins=len(names))
        plan: list[str | None] = [None] * scene.vehicles_behind
        for name, share in zip(names, shares, strict=True):
            plan += [name, *[None] * int(share)]
        ids: dict[Any, str] = {}
        egos: dict[str, Any] = {}
        for role in plan:
            vehicle = IDMVehicle.create_random(road, spacing=spacing)
            vehicle.randomize_behavior()
            road.vehicles.append(vehicle)
            if role is None:
                ids[vehicle] = f"h{len(ids) - len(egos)}"
            else:
                ids[vehicle], egos[role] = role, vehicle
        return _Scene(road, layout, ids, [egos[name] for name in names])


@dataclass(frozen=True, slots=True)
class Geometry:
    """A corridor as one seed draws it, in the options' names (m); what a kind lacks is 0."""

    main_lanes: int
    """Lanes of the motorway (``lanedrop``: before the drop)."""
    ramp_length: float = 0.0
    acceleration_lane: float = 0.0
    exit_distance: float = 0.0
    deceleration_lane: float = 0.0
    drop_distance: float = 0.0
    dropped_lane: str = ""
    """``lanedrop``: ``left`` or ``right``."""


@dataclass(frozen=True)
class CorridorScenario:
    """A motorway corridor with a lane end (`kind`: ``merge``, ``exit`` or ``lanedrop``), its
    geometry drawn from the seed as the SUMO corridors draw theirs (the same grids, the same
    order of draws, so the same seed and options give the same lengths and lanes)."""

    name: str
    description: str
    kind: str
    defaults: dict[str, OptionValue] = field(default_factory=dict)
    speed_limit: float = MOTORWAY_SPEED

    OPTIONS: ClassVar[dict[str, type[ParsedOptions]]] = {
        "merge": MergeOptions,
        "exit": ExitOptions,
        "lanedrop": LaneDropOptions,
    }

    def info(self) -> ScenarioInfo:
        options: dict[str, OptionValue] = {name: COMMON_OPTIONS[name] for name in _HONOURED}
        options.update(warmup=5.0, **SceneOptions().as_options())
        options.update(self.OPTIONS[self.kind]().as_options())
        options.update(self.defaults)
        return ScenarioInfo(self.name, self.description, options, DT)

    def geometry(self, seed: int, options: Mapping[str, OptionValue]) -> Geometry:
        """The geometry `seed` draws, with `options` fixing what they set: the SUMO corridors'
        draws (`sumo.corridors`), from the same grids in the same order."""
        own = self.OPTIONS[self.kind].parse(options)
        draw = random.Random(f"{self.kind}:{seed}")
        if isinstance(own, MergeOptions):
            lanes = own.main_lanes or draw.choice(MERGE_LANES)
            acceleration = own.acceleration_lane or draw.choice(ACCELERATION_LANES)
            ramp = own.ramp_length or draw.choice(RAMP_LENGTHS)
            return Geometry(lanes, ramp_length=ramp, acceleration_lane=acceleration)
        if isinstance(own, ExitOptions):
            lanes = own.main_lanes or draw.choice(EXIT_LANES)
            distance = own.exit_distance or draw.choice(EXIT_DISTANCES)
            deceleration = own.deceleration_lane or draw.choice(DECELERATION_LANES)
            if distance < deceleration + 100.0:  # as the SUMO corridor
                raise invalid_option(
                    "option exit_distance must leave at least 100 m before the deceleration lane"
                )
            return Geometry(lanes, exit_distance=distance, deceleration_lane=deceleration)
        assert isinstance(own, LaneDropOptions)
        distance = own.drop_distance or draw.choice(DROP_DISTANCES)
        dropped = own.dropped_lane if own.dropped_lane != "random" else draw.choice(DROPPED_LANES)
        return Geometry(LANE_DROP_LANES, drop_distance=distance, dropped_lane=dropped)

    def build(
        self, seed: int, options: Mapping[str, OptionValue], names: tuple[str, ...]
    ) -> _Scene:
        """The corridor `seed` draws (`geometry`), and its vehicles:
        humans one after another on the motorway as ``create_random`` spaces them,
        `vehicles_behind` of them behind the egos' start; on ``merge`` the egos one after another
        on the ramp (then ``ramp_vehicles`` humans), elsewhere each ego followed by its share of
        the humans, as on ``cf``. The egos keep their lane during the warm-up (lane changes are
        the client's)."""
        scene = SceneOptions.parse(options)
        own = self.OPTIONS[self.kind].parse(options)
        geometry = self.geometry(seed, options)
        rng = np.random.default_rng(seed)
        if isinstance(own, MergeOptions):
            return _merge_scene(geometry, own.ramp_vehicles, scene, rng, names)
        assert isinstance(own, ExitOptions | LaneDropOptions)
        scene_of = _exit_scene if isinstance(own, ExitOptions) else _lane_drop_scene
        return scene_of(geometry, own.ego_lane, scene, rng, names)


Scenario = HighwayScenario | CorridorScenario


class _Column:
    """Places vehicles one after another as highway-env's ``create_random`` does: a speed drawn
    from 70-80 % of the speed limit, then ``(12 m + speed) * exp(-5/40 * lanes) / density`` (times
    a factor drawn from [0.9, 1.1]) ahead of the previous vehicle, the first 3 such offsets from
    the start (or at `start`)."""

    def __init__(
        self, rng: Any, density: float, lanes: int, speed_limit: float, start: float | None = None
    ) -> None:
        self._rng, self._spacing, self._lanes, self._limit = rng, 1.0 / density, lanes, speed_limit
        self._x, self._placed = start, start is not None

    def next(self) -> tuple[float, float]:
        """The next vehicle's centre (m along the road) and speed (m/s)."""
        speed = float(self._rng.uniform(0.7 * self._limit, 0.8 * self._limit))
        offset = self._spacing * (12.0 + speed) * math.exp(-5.0 / 40.0 * self._lanes)
        if self._x is None:
            self._x = 3.0 * offset
        if not self._placed:  # a given start is the first vehicle's place
            self._x += offset * float(self._rng.uniform(0.9, 1.1))
        self._placed = False
        return self._x, speed


class _Populating:
    """Vehicles put on a built road one by one, the lanes that end marked by an obstacle."""

    def __init__(self, layout: _Layout, rng: Any) -> None:
        self.layout = layout
        self.road = HighwayRoad(network=layout.network, np_random=rng, record_history=False)
        self.ids: dict[Any, str] = {}
        self.egos: dict[str, Any] = {}
        for index in sorted(layout.dead_ends):
            lane = layout.network.get_lane(index)
            end = Obstacle(self.road, lane.position(lane.length, 0.0), lane.heading_at(lane.length))
            end.collidable = False  # IDM stops before it; the ego's lane_end is the rule's
            self.road.objects.append(end)

    def add(
        self, index: LaneIndex, s: float, speed: float, name: str | None = None, wish: float = 0.0
    ) -> None:
        """An `IDMVehicle` at `s` on lane `index`; with a `name`, an ego (highway-env's human model
        drives it through the warm-up, in its lane, along the egos' route); a human on a lane that
        ends gets the route that leads it off that lane. `wish`: its desired speed, if not
        `speed`."""
        vehicle = IDMVehicle.make_on_lane(self.road, index, s, speed)
        vehicle.randomize_behavior()
        if wish:
            vehicle.target_speed = wish
        if name is not None:
            vehicle.route = self.layout.plan(index)
            vehicle.enable_lane_change = False
            self.ids[vehicle], self.egos[name] = name, vehicle
        else:
            if self.layout.leads_to_dead_end(index):
                vehicle.route = self.layout.plan(index)
            self.ids[vehicle] = f"h{len(self.ids) - len(self.egos)}"
        self.road.vehicles.append(vehicle)

    def human(self, road: RoadId, lanes: range, x: float, speed: float) -> None:
        """A human at `x` on a random one of `lanes` that goes on far enough there (`START_ROOM`
        in a lane that ends); none if no lane does (beyond the road's end)."""
        fits = []
        for j in lanes:
            lane = self.layout.network.get_lane((*road, j))
            room = START_ROOM if (*road, j) in self.layout.dead_ends else Vehicle.LENGTH / 2
            if x + room <= lane.length:
                fits.append(j)
        if fits:
            lane_id = fits[int(self.road.np_random.integers(len(fits)))]
            self.add((*road, lane_id), x, speed)

    def scene(self, names: tuple[str, ...]) -> _Scene:
        return _Scene(self.road, self.layout, self.ids, [self.egos[name] for name in names])


_MAIN: RoadId = ("a", "b")
"""The corridors' motorway."""


def _platoon(
    rng: Any, scene: SceneOptions, lanes: int, names: tuple[str, ...]
) -> list[tuple[str | None, float, float]]:
    """(ego name or None for a human, centre, speed) along the motorway, as on ``cf``:
    `vehicles_behind` humans, then each ego followed by its share of the others."""
    column = _Column(rng, scene.vehicles_density, lanes, MOTORWAY_SPEED)
    slots: list[tuple[str | None, float, float]] = [
        (None, *column.next()) for _ in range(scene.vehicles_behind)
    ]
    shares = near_split(scene.vehicles_count - scene.vehicles_behind, num_bins=len(names))
    for name, share in zip(names, shares, strict=True):
        slots.append((name, *column.next()))
        slots += [(None, *column.next()) for _ in range(int(share))]
    return slots


def _ego_lane(rng: Any, ego_lane: int, lanes: int) -> int:
    """highway-env's lane id of an ego's start lane: `ego_lane` counted from the right (-1:
    random, one beyond the lanes the leftmost)."""
    if ego_lane < 0:
        return int(rng.integers(lanes))
    return lanes - 1 - min(ego_lane, lanes - 1)


def _merge_scene(
    geometry: Geometry,
    ramp_vehicles: int,
    scene: SceneOptions,
    rng: Any,
    names: tuple[str, ...],
) -> _Scene:
    """The ramp starts beside the egos' place in the motorway's traffic; the egos, then up to
    `ramp_vehicles` humans, one after another on the ramp (and on to its acceleration lane)."""
    lanes, ramp = geometry.main_lanes, geometry.ramp_length
    acceleration = geometry.acceleration_lane
    main = _Column(rng, scene.vehicles_density, lanes, MOTORWAY_SPEED)
    behind = [main.next() for _ in range(scene.vehicles_behind)]
    anchor, _ = main.next()
    half = Vehicle.LENGTH / 2
    column = _Column(rng, scene.vehicles_density, 1, RAMP_SPEED, start=half)
    egos = [column.next() for _ in names]
    if egos[-1][0] + half > ramp + acceleration - START_ROOM:
        raise BackendError(
            ErrorCode.INVALID_OPTION,
            f"{len(names)} egos do not fit on this merge's ramp and acceleration lane "
            f"({ramp:g} + {acceleration:g} m); fewer egos or a higher vehicles_density",
        )
    on_ramp = []
    for _ in range(ramp_vehicles):
        x, speed = column.next()
        if x + half > ramp:
            break
        on_ramp.append((x, speed))
    ahead = [main.next() for _ in range(scene.vehicles_count - scene.vehicles_behind)]
    layout = _merge_layout(lanes, ramp, acceleration, anchor - half)
    populating = _Populating(layout, rng)

    def along_ramp(x: float) -> tuple[LaneIndex, float]:
        return (("ramp", "a", 0), x) if x < ramp else ((*_MAIN, lanes), x - ramp)

    wish = MOTORWAY_SPEED / RAMP_SPEED  # the same share of the motorway's limit, once on it
    for x, speed in behind:
        populating.human(_MAIN, range(lanes), x, speed)
    for name, (x, speed) in zip(names, egos, strict=True):
        populating.add(*along_ramp(x), speed, name, wish=speed * wish)
    for x, speed in on_ramp:
        populating.add(*along_ramp(x), speed, wish=speed * wish)
    for x, speed in ahead:
        populating.human(_MAIN, range(lanes), x, speed)
    return populating.scene(names)


def _exit_scene(
    geometry: Geometry, ego_lane: int, scene: SceneOptions, rng: Any, names: tuple[str, ...]
) -> _Scene:
    """The off-ramp leaves ``exit_distance`` m after the frontmost ego's front."""
    lanes = geometry.main_lanes
    slots = _platoon(rng, scene, lanes, names)
    diverge = _anchor(slots) + geometry.exit_distance
    layout = _exit_layout(lanes, diverge, geometry.deceleration_lane)
    return _populate(layout, rng, slots, lanes, ego_lane, names)


def _lane_drop_scene(
    geometry: Geometry, ego_lane: int, scene: SceneOptions, rng: Any, names: tuple[str, ...]
) -> _Scene:
    """The lane ends ``drop_distance`` m after the frontmost ego's front."""
    slots = _platoon(rng, scene, LANE_DROP_LANES, names)
    dropped = 0 if geometry.dropped_lane == "left" else LANE_DROP_LANES - 1
    layout = _lane_drop_layout(dropped, _anchor(slots) + geometry.drop_distance)
    return _populate(layout, rng, slots, LANE_DROP_LANES, ego_lane, names)


def _anchor(slots: list[tuple[str | None, float, float]]) -> float:
    """Where the frontmost ego's front starts (m along the motorway): every ego has at least
    the drawn distance to the exit or the drop."""
    return max(x for name, x, _ in slots if name is not None) + Vehicle.LENGTH / 2


def _populate(
    layout: _Layout,
    rng: Any,
    slots: list[tuple[str | None, float, float]],
    lanes: int,
    ego_lane: int,
    names: tuple[str, ...],
) -> _Scene:
    """The `_platoon`'s vehicles on the motorway's first `lanes` lanes: each human on a random
    one, each ego on `ego_lane` (`_ego_lane`)."""
    populating = _Populating(layout, rng)
    for name, x, speed in slots:
        if name is None:
            populating.human(_MAIN, range(lanes), x, speed)
        else:
            populating.add((*_MAIN, _ego_lane(rng, ego_lane, lanes)), x, speed, name)
    return populating.scene(names)


_CORRIDOR_TRAFFIC: dict[str, OptionValue] = {
    "vehicles_count": 16,
    "vehicles_behind": 4,
    "vehicles_density": 0.5,
}
"""The corridors' humans: ~100-160 m apart in each lane (~470-730 veh/h/lane), sparse enough that
highway-env's MOBIL, with its 2 m/s² safety rule and IDM's 1.5 s time gap, finds gaps to merge
into; at ``vehicles_density`` 0.7 humans often stand at the end of the acceleration lane."""

SCENARIOS: dict[str, Scenario] = {
    s.name: s
    for s in (
        HighwayScenario(
            "cf",
            "highway-env car following: 2 km single lane, 80 km/h, IDM human traffic ahead",
            lanes=1,
        ),
        HighwayScenario(
            "cflc",
            "highway-env car following and lane changing: 2 km, 3 lanes, 80 km/h, IDM/MOBIL "
            "human traffic",
            lanes=3,
            defaults={"vehicles_count": 20, "vehicles_behind": 4, "vehicles_density": 0.7},
        ),
        CorridorScenario(
            "merge",
            "highway-env on-ramp: the ego enters from a ramp and must merge from its "
            "acceleration lane onto a motorway of 2-3 lanes (100 km/h, IDM/MOBIL human traffic); "
            "geometry drawn per seed",
            "merge",
            defaults=_CORRIDOR_TRAFFIC,
        ),
        CorridorScenario(
            "exit",
            "highway-env exit: the ego's route leaves a motorway of 2-4 lanes by an off-ramp on "
            "the right, 600-1200 m ahead after a deceleration lane; it starts in any lane; "
            "drawn per seed",
            "exit",
            defaults=_CORRIDOR_TRAFFIC,
        ),
        CorridorScenario(
            "lanedrop",
            "highway-env lane drop: three motorway lanes become two, the left or the right one "
            "ending 400-1000 m ahead; the ego starts in any lane; drawn per seed",
            "lanedrop",
            defaults=_CORRIDOR_TRAFFIC,
        ),
    )
}


class _ClientVehicle(ControlledVehicle):  # type: ignore[misc]
    """The client's ego: highway-env's lateral controller, the client's acceleration."""

    command: float = 0.0

    def act(self, action: Any = None) -> None:
        self.follow_road()
        steering = self.steering_control(self.target_lane_index)
        steering = float(np.clip(steering, -self.MAX_STEERING_ANGLE, self.MAX_STEERING_ANGLE))
        Vehicle.act(self, {"steering": steering, "acceleration": self.command})


@dataclass
class _Driven:
    """One ego of a multi-ego episode and its own book-keeping (a one-ego episode keeps its
    ego's in `_Episode`)."""

    id: str
    vehicle: Any
    end: EndRule
    lane_change: LaneChangeUnderWay | None = None
    over: bool = False
    """Its drive has ended (reported once, then off the road)."""


@dataclass
class _Turn:
    """One ego's part of a decision of a multi-ego episode."""

    driven: _Driven
    request: float
    lane_change: int
    refused: str
    started: bool
    applied_total: float = 0.0
    limited_by: str = ""
    why: str = ""
    """What limited the acceleration on the current simulation step."""
    steps: int = 0
    """Simulation steps driven in this decision."""
    collision_with: str = ""
    end_of_road: bool = False
    lane_end: bool = False
    """Its front passed the end of its lane (`_Layout.past_lane_end`): it ends with
    ``lane_end``."""
    completed: bool = False
    aborted: bool = False
    last: Observation | None = None
    """Observed at the simulation step where its drive ended inside the decision."""

    @property
    def stopped_inside(self) -> bool:
        return bool(self.collision_with) or self.end_of_road or self.lane_end

    def result(self) -> tuple[AppliedAction, Events]:
        action = AppliedAction(
            requested_acceleration=self.request,
            requested_lane_change=self.lane_change,
            acceleration=self.applied_total / self.steps,
            lane_change=0 if self.refused else self.lane_change,
            acceleration_limited_by=self.limited_by,
            lane_change_refused=self.refused,
        )
        events = Events(
            collision=bool(self.collision_with),
            collision_with=self.collision_with,
            end_of_road=self.end_of_road,
            lane_change_started=self.started,
            lane_change_completed=self.completed,
            lane_change_refused=bool(self.refused),
            lane_change_aborted=self.aborted,
        )
        return action, events


@dataclass
class _Episode:
    """The running scene and its book-keeping."""

    scenario: Scenario
    road: Any
    layout: _Layout
    ego: Any
    options: EpisodeOptions
    substeps: int
    ids: dict[Any, str]
    spawn_front: dict[Any, float]
    steps: int = 0
    leader: Any = None
    leader_arrival: float | None = None
    leader_end: float = 0.0
    """Route coordinate of the end of the road where the leader-at-entry arrived."""
    stranded: dict[Any, float] = field(default_factory=dict)
    """Humans standing at the end of a lane that ends, and since when (`_stranded`)."""
    lane_change: LaneChangeUnderWay | None = None
    collided: Any = None
    done: bool = False
    fleet: list[_Driven] = field(default_factory=list)
    """The egos of a multi-ego episode, in highway-env's ``controlled_vehicles`` order (then
    `ego` is None); empty in a one-ego episode."""
    end: EndRule = field(init=False)
    """Set at the hand-over: the episode's time runs from there."""

    @property
    def time(self) -> float:
        return self.steps / SIMULATION_FREQUENCY

    def egos(self) -> list[Any]:
        """The ego vehicles on the road: the one ego, or the fleet's still driving."""
        if not self.fleet:
            return [self.ego]
        return [d.vehicle for d in self.fleet if not d.over]


class HighwayBackend(Backend):
    """highway-env scenes advanced with ``road.act()`` / ``road.step(dt)``; see the module doc."""

    name = "highway"
    max_egos = MAX_HIGHWAY_EGOS

    def __init__(self) -> None:
        self._episode: _Episode | None = None
        self._absent = Neighbour(False, self.sensor_range, 0.0, 0.0, "")

    @property
    def version(self) -> str:
        return str(highway_env.__version__)

    def scenarios(self) -> tuple[ScenarioInfo, ...]:
        return tuple(s.info() for s in SCENARIOS.values())

    # ----------------------------------------------------------------------- reset

    def reset(self, scenario: str, seed: int, options: dict[str, OptionValue]) -> Observation:
        chosen = SCENARIOS.get(scenario)
        if chosen is None:
            raise BackendError(ErrorCode.UNKNOWN_SCENARIO, f"unknown scenario {scenario[:64]!r}")
        episode_options = EpisodeOptions.parse(options, SIMULATOR_DRIVERS)
        substeps = episode_options.steps_per_decision(DT)
        self._episode = None
        episode = self._build(chosen, seed, options, episode_options, substeps)
        self._start(episode)
        leader, _ = self._around(episode, episode.ego, episode.ego.lane_index, own=True)
        if leader is not None and episode.layout.drives_route(leader):  # else it bounds nothing
            episode.leader = leader
        self._episode = episode
        return self._observe(episode, 0, Events(), AppliedAction(0.0, 0, 0.0, 0))

    def _build(
        self,
        scenario: Scenario,
        seed: int,
        options: Mapping[str, OptionValue],
        episode_options: EpisodeOptions,
        substeps: int,
        names: tuple[str, ...] = (EGO_ID,),
    ) -> _Episode:
        """The scenario's road and vehicles (`Scenario.build`), egos named `names`; a human
        placed beyond the end of its road never enters it, an ego placed there or past the end of
        its lane is refused."""
        scene = scenario.build(seed, options, names)
        road, layout = scene.road, scene.layout
        fleet: list[_Driven] = [] if names == (EGO_ID,) else [
            _Driven(name, vehicle, EndRule(episode_options, 0.0))
            for name, vehicle in zip(names, scene.egos, strict=True)
        ]  # fmt: skip
        episode = _Episode(
            scenario=scenario,
            road=road,
            layout=layout,
            ego=None if fleet else scene.egos[0],
            options=episode_options,
            substeps=substeps,
            ids=scene.ids,
            spawn_front={},
            fleet=fleet,
        )
        egos = dict(zip(scene.egos, names, strict=True))
        for vehicle in list(road.vehicles):
            front = layout.along(vehicle)
            beyond = front >= layout.end_of(vehicle.lane_index[:2])
            if vehicle in egos and (beyond or layout.past_lane_end(vehicle)):
                what = "the ego" if not fleet else egos[vehicle]
                raise BackendError(
                    ErrorCode.INVALID_OPTION,
                    f"vehicles_behind and vehicles_density place {what} beyond the end of "
                    "the road; fewer vehicles behind it or a higher density"
                    + ("" if not fleet else ", or fewer egos"),
                )
            if beyond:  # placed beyond the end: never on the road
                road.vehicles.remove(vehicle)
            episode.spawn_front[vehicle] = front
        return episode

    def _start(self, episode: _Episode) -> None:
        """The warm-up, then the hand-over to the client (or highway-env's human model drives on,
        changing lanes from then on); the episode's time runs from there."""
        self._warm_up(episode)
        if episode.options.simulator_drives:
            for ego in episode.egos():
                ego.enable_lane_change = True
        else:
            self._hand_over(episode)
        episode.end = EndRule(episode.options, entry_time=episode.time)
        for driven in episode.fleet:
            driven.end = EndRule(episode.options, entry_time=episode.time)

    def _warm_up(self, episode: _Episode) -> None:
        """highway-env's human model drives the ego for ``warmup`` seconds."""
        warmup = episode.options.warmup
        layout = episode.layout
        names = {d.vehicle: d.id for d in episode.fleet}
        for _ in range(math.ceil(warmup * SIMULATION_FREQUENCY - 1e-9)):
            self._advance(episode)
            for ego in episode.egos():
                if ego.crashed:
                    what = names.get(ego, "the ego")
                    raise BackendError(
                        ErrorCode.INSERTION_FAILED,
                        f"{what} crashed during the warm-up (driven by highway-env); try "
                        "another seed",
                    )
        for ego in episode.egos():
            what = names.get(ego, "the ego")
            reached = ""
            if layout.past_lane_end(ego):
                reached = "drove past the end of its lane"
            elif layout.along(ego) >= layout.length:
                reached = "reached the end of the road"
            if reached:
                raise BackendError(
                    ErrorCode.INVALID_OPTION,
                    f"warmup {warmup} s: {what} {reached} before the client took over",
                )

    @classmethod
    def _hand_over(cls, episode: _Episode) -> None:
        """Replace the ego's human model by the client's control, in the same list slot."""
        if not episode.fleet:
            episode.ego = cls._take_over(episode, episode.ego)
        for driven in episode.fleet:
            driven.vehicle = cls._take_over(episode, driven.vehicle)

    @staticmethod
    def _take_over(episode: _Episode, human: Any) -> Any:
        """The client's vehicle in `human`'s place (list slot, id, spawn position)."""
        ego = _ClientVehicle.create_from(human)
        ego.target_lane_index = human.lane_index  # a lane change the human began is not ours
        ego.target_speed = episode.scenario.speed_limit  # for the IDM safety check only
        ego.action = dict(human.action)
        vehicles = episode.road.vehicles
        vehicles[vehicles.index(human)] = ego
        episode.ids[ego] = episode.ids.pop(human)
        episode.spawn_front[ego] = episode.spawn_front.pop(human)
        return ego

    # ----------------------------------------------------------------------- step

    def step(self, seq: int, acceleration: float, lane_change: int) -> Observation:
        episode = self._episode
        if episode is None or episode.done or episode.fleet:
            raise BackendError(ErrorCode.OUT_OF_ORDER, "no running episode: send reset first")
        refused = (
            self._lane_change_refusal(episode, episode.ego, episode.lane_change, lane_change)
            if lane_change
            else ""
        )
        started = bool(lane_change) and not refused
        if started:
            episode.lane_change = self._start_lane_change(episode, episode.ego, lane_change)
        action, events, lane_end = self._drive(episode, acceleration, lane_change, refused, started)
        obs = self._observe(episode, seq, events, action)
        reason = EndReason.LANE_END if lane_end else episode.end.check(obs)
        if reason is None:
            return obs
        episode.done = True
        obs = ended(obs, reason)
        if episode.options.report_ceiling:
            obs = replace(obs, ceiling=self._leader_trip(episode))
        return obs

    def _drive(
        self, episode: _Episode, request: float, lane_change: int, refused: str, started: bool
    ) -> tuple[AppliedAction, Events, bool]:
        """Run the decision's simulation steps, the request limited anew on each (bounds, the
        speed limit of the ego's lane, standstill); stop early at a crash, the end of the road or
        the end of the ego's lane (the flag returned: the episode then ends with ``lane_end``)."""
        ego, drives = episode.ego, episode.options.simulator_drives
        low, high = self.action_schema.acceleration_min, self.action_schema.acceleration_max
        applied_total, limited_by = 0.0, ""
        collision_with, outcome, completed, aborted = "", "", False, False
        done = 0
        for _ in range(episode.substeps):
            why: str = AccelerationLimit.SIMULATOR
            if not drives:
                limit = float(ego.lane.speed_limit)
                ego.command, why = limit_acceleration(
                    request, float(ego.speed), limit, low, high, DT
                )
            self._advance(episode)
            if not drives and ego.speed < 0.0:
                ego.speed = 0.0  # rounding of -v/dt * dt; the protocol's speed is >= 0
            applied_total += float(ego.action["acceleration"])
            limited_by = limited_by or why
            done += 1
            outcome = self._outcome(episode, ego)
            if outcome == EndReason.COLLISION:
                episode.collided = self._collided_with(episode, ego)
                collision_with = episode.ids.get(episode.collided, "unknown")
            if outcome:
                break
            if episode.lane_change is not None:
                completed, aborted = self._lane_change_progress(episode, ego, episode.lane_change)
                if completed or aborted:
                    episode.lane_change = None
        action = AppliedAction(
            requested_acceleration=request,
            requested_lane_change=lane_change,
            acceleration=applied_total / done,
            lane_change=0 if refused else lane_change,
            acceleration_limited_by=limited_by,
            lane_change_refused=refused,
        )
        events = Events(
            collision=bool(collision_with),
            collision_with=collision_with,
            end_of_road=outcome == EndReason.END_OF_ROAD,
            lane_change_started=started,
            lane_change_completed=completed,
            lane_change_refused=bool(refused),
            lane_change_aborted=aborted,
        )
        return action, events, outcome == EndReason.LANE_END

    @staticmethod
    def _outcome(episode: _Episode, ego: Any) -> str:
        """What ends `ego`'s drive after a simulation step, as an `EndReason`: a crash, its front
        past the end of its route (``end_of_road``) or past the end of its lane (``lane_end``:
        highway-env would carry it on along a lane that does not exist); "" if none."""
        layout = episode.layout
        if ego.crashed:
            return EndReason.COLLISION
        if layout.at_route_end(ego):
            return EndReason.END_OF_ROAD
        if layout.past_lane_end(ego):
            return EndReason.LANE_END
        return ""

    def _advance(self, episode: _Episode) -> None:
        """One simulation step: highway-env's ``road.act()`` and ``road.step(dt)``, arrivals."""
        road = episode.road
        road.act()
        road.step(DT)
        episode.steps += 1
        layout = episode.layout
        egos = episode.egos()
        arrived = [
            v for v in road.vehicles if all(v is not ego for ego in egos) and layout.arrived(v)
        ]
        for vehicle in arrived:
            road.vehicles.remove(vehicle)
            if vehicle is episode.leader:
                episode.leader_arrival = episode.time
                episode.leader_end = layout.end_of(vehicle.lane_index[:2])
        if layout.dead_ends:
            self._clear_lane_ends(episode, egos)

    def _clear_lane_ends(self, episode: _Episode, egos: list[Any]) -> None:
        """A human that has stood at the end of a lane that ends for ``lane_end_patience``
        seconds leaves the road (as an ego's drive ends there with ``lane_end``): highway-env's
        MOBIL never changes lanes below 1 m/s, so it would block that lane for good."""
        stranded, now = episode.stranded, episode.time
        patience = episode.options.lane_end_patience
        for vehicle in list(episode.road.vehicles):
            if any(vehicle is ego for ego in egos) or not self._stranded(episode, vehicle):
                stranded.pop(vehicle, None)
            elif now - stranded.setdefault(vehicle, now) >= patience - 1e-9:
                episode.road.vehicles.remove(vehicle)
                del stranded[vehicle]

    def _lane_change_refusal(
        self, episode: _Episode, ego: Any, under_way: LaneChangeUnderWay | None, direction: int
    ) -> str:
        _from, _to, index = ego.lane_index

        def ego_lane() -> tuple[int, int]:
            lanes = episode.layout.lanes_at(ego.lane_index, ego.position)
            return sum(j > index for j in lanes), len(lanes)  # highway-env counts from the left

        return lane_change_refusal(
            direction,
            simulator_drives=episode.options.simulator_drives,
            under_way=under_way,
            ego_lane=ego_lane,
            gap_ok=lambda towards: self._safe(episode, ego, (_from, _to, index - towards)),
        )

    @staticmethod
    def _start_lane_change(episode: _Episode, ego: Any, direction: int) -> LaneChangeUnderWay:
        """Steer `ego` one lane towards `direction` (not refused)."""
        _from, _to, index = ego.lane_index
        target = index - direction  # protocol +1 (left) is highway-env index - 1
        ego.target_lane_index = (_from, _to, target)
        return LaneChangeUnderWay(target, direction, episode.time)

    @classmethod
    def _safe(cls, episode: _Episode, ego: Any, lane_index: LaneIndex) -> bool:
        """MOBIL's safety criterion for `ego` moving to `lane_index` (both directions)."""
        front, rear = cls._around(episode, ego, lane_index)
        limit = IDMVehicle.LANE_CHANGE_MAX_BRAKING_IMPOSED
        if rear is not None:
            model = rear if isinstance(rear, IDMVehicle) else _REFERENCE_IDM
            if model.acceleration(ego_vehicle=rear, front_vehicle=ego) < -limit:
                return False
        return (
            front is None
            or _REFERENCE_IDM.acceleration(ego_vehicle=ego, front_vehicle=front) >= -limit
        )

    @staticmethod
    def _lane_change_progress(
        episode: _Episode, ego: Any, change: LaneChangeUnderWay
    ) -> tuple[bool, bool]:
        """(completed, aborted) of `ego`'s lane change under way; either ends it."""
        target = ego.target_lane_index  # the change's, or the lane it leads into on the route
        if ego.lane_index == target:
            _, lateral = episode.road.network.get_lane(target).local_coordinates(ego.position)
            if abs(lateral) < LANE_CHANGE_TOLERANCE:
                return True, False
        if change.expired(episode.time):
            return False, True
        return False, False

    @staticmethod
    def _collided_with(episode: _Episode, ego: Any) -> Any:
        """highway-env flags both vehicles of a crash: the nearest crashed one is the other."""
        crashed = [v for v in episode.road.vehicles if v is not ego and v.crashed]
        if not crashed:
            return None
        return min(crashed, key=lambda v: float(np.linalg.norm(v.position - ego.position)))

    def _leader_trip(self, episode: _Episode) -> LeaderTrip | None:
        """Run on without the ego until the leader-at-entry arrives; its (virtual) trip."""
        leader = episode.leader
        if leader is None:
            return None
        road = episode.road
        if episode.leader_arrival is None:
            if episode.ego in road.vehicles:
                road.vehicles.remove(episode.ego)
            if episode.collided is not None:  # SUMO's collision action "warn": it drives on
                episode.collided.crashed, episode.collided.impact = False, None
            # IDM looks ahead only: on one lane the vehicles behind cannot influence the leader.
            # On more lanes one could overtake and cut in; dropping them is an approximation
            # (docs/backends.md, "Ceiling")
            layout = episode.layout
            mine = layout.along(leader)
            road.vehicles = [v for v in road.vehicles if layout.along(v) >= mine]
            end = episode.steps + round(CEILING_HORIZON * SIMULATION_FREQUENCY)
            while episode.leader_arrival is None and episode.steps < end:
                if leader.crashed or self._stranded(episode, leader):
                    break  # highway-env stops it for good: it never arrives
                self._advance(episode)
        arrival = episode.leader_arrival
        name = episode.ids[leader]
        if arrival is None:
            return LeaderTrip(name, 0.0, None, None)
        average = (episode.leader_end - episode.spawn_front[leader]) / arrival
        return LeaderTrip(name, arrival - episode.layout.length / average, arrival, average)

    @staticmethod
    def _stranded(episode: _Episode, human: Any) -> bool:
        """`human` stands at the end of a lane that ends: MOBIL changes lanes only at 1 m/s or
        faster, so it stays there for good."""
        layout = episode.layout
        return (
            human.speed < 1.0
            and layout.leads_to_dead_end(human.lane_index)
            and layout.to_end(human) < 2 * IDMVehicle.DISTANCE_WANTED
        )

    # ----------------------------------------------------------------------- observation

    @staticmethod
    def _around(
        episode: _Episode, ego: Any, index: LaneIndex, own: bool = False
    ) -> tuple[Any, Any]:
        """highway-env's ``neighbour_vehicles`` of `ego` on lane `index` (its leader, its
        follower), without the obstacles that mark the lane ends (the road ahead reports those);
        on its `own` lane also across the joins of its route, which highway-env does not look
        across: the leader on the lane it leads into, the follower on the lane it came from."""
        road, layout = episode.road, episode.layout
        objects, road.objects = road.objects, []
        try:
            front, rear = road.neighbour_vehicles(ego, index)
            if own and front is None and index in layout.successor:
                front, _ = road.neighbour_vehicles(ego, layout.successor[index])
            if own and rear is None and index in layout.predecessor:
                _, rear = road.neighbour_vehicles(ego, layout.predecessor[index])
        finally:
            road.objects = objects
        return front, rear

    def _observe(
        self, episode: _Episode, seq: int, events: Events, action: AppliedAction
    ) -> Observation:
        return self._observe_ego(episode, episode.ego, episode.lane_change, seq, events, action)

    def _observe_ego(
        self,
        episode: _Episode,
        ego: Any,
        change: LaneChangeUnderWay | None,
        seq: int,
        events: Events,
        action: AppliedAction,
    ) -> Observation:
        """`ego`'s observation: its own state, its six neighbours (other egos included) and the
        road ahead, among the lanes of its road beside it (`_Layout.lanes_at`)."""
        layout = episode.layout
        _from, _to, index = ego.lane_index
        lane = layout.network.get_lane(ego.lane_index)
        s, lat = lane.local_coordinates(ego.position)
        lanes = layout.lanes_at(ego.lane_index, ego.position)
        slots: dict[str, Neighbour] = {}
        for name, offset in (("left_", -1), ("", 0), ("right_", 1)):
            other = index + offset
            if other not in lanes:
                slots[f"{name}leader"] = slots[f"{name}follower"] = self._absent
                continue
            front, rear = self._around(episode, ego, (_from, _to, other), own=not offset)
            slots[f"{name}leader"] = self._neighbour(episode, ego, lane, s, lat, front, True)
            slots[f"{name}follower"] = self._neighbour(episode, ego, lane, s, lat, rear, False)
        return Observation(
            seq=seq,
            time=episode.time,
            ego=Ego(
                speed=float(ego.speed),
                acceleration=float(ego.action["acceleration"]),
                lane=sum(j > index for j in lanes),  # highway-env counts from the left
                lane_count=len(lanes),
                position=min(layout.along(ego), layout.length),
                speed_limit=float(lane.speed_limit),
                changing_lane=0 if change is None else change.direction,
            ),
            neighbours=Neighbours(**slots),
            events=events,
            action=action,
            road=layout.road_ahead(ego, lanes),
        )

    def _neighbour(
        self,
        episode: _Episode,
        ego: Any,
        lane: Any,
        s: float,
        lat: float,
        other: Any,
        ahead: bool,
    ) -> Neighbour:
        if other is None:
            return self._absent
        other_s, other_lat = lane.local_coordinates(other.position)
        half_lengths = (other.LENGTH + ego.LENGTH) / 2
        gap = (other_s - s if ahead else s - other_s) - half_lengths
        if gap > self.sensor_range:
            return self._absent
        lateral = lat - other_lat  # highway-env's lateral axis points right
        return Neighbour(True, float(gap), float(lateral), float(other.speed), episode.ids[other])

    # ----------------------------------------------------------------------- many egos

    def reset_many(
        self, scenario: str, seed: int, options: dict[str, OptionValue], egos: int
    ) -> MultiObservation:
        """``egos`` 1: the one-ego episode under the id ``ego`` (without the ceiling's run-on: a
        multi observation has no ceiling); more: ``ego.0``... placed as highway-env places its
        ``controlled_vehicles`` (`_build`), handed over together after the warm-up."""
        if egos == 1 or egos > self.max_egos:
            quiet = {**options, "report_ceiling": False}
            return super().reset_many(scenario, seed, quiet, egos)  # or its refusal
        chosen = SCENARIOS.get(scenario)
        if chosen is None:
            raise BackendError(ErrorCode.UNKNOWN_SCENARIO, f"unknown scenario {scenario[:64]!r}")
        episode_options = EpisodeOptions.parse(options, SIMULATOR_DRIVERS)
        substeps = episode_options.steps_per_decision(DT)
        names = tuple(f"ego.{k}" for k in range(egos))
        self._episode = None
        episode = self._build(chosen, seed, options, episode_options, substeps, names)
        self._start(episode)
        self._episode = episode
        still = AppliedAction(0.0, 0, 0.0, 0)
        firsts = [
            self._observe_ego(episode, d.vehicle, None, 0, Events(), still) for d in episode.fleet
        ]
        mine = tuple(ego_part(d.id, obs) for d, obs in zip(episode.fleet, firsts, strict=True))
        return MultiObservation(0, episode.time, mine)

    def step_many(self, seq: int, commands: Commands) -> MultiObservation:
        episode = self._episode
        if episode is not None and not episode.fleet:
            return super().step_many(seq, commands)  # a one-ego episode (egos 1)
        if episode is None or episode.done:
            raise BackendError(ErrorCode.OUT_OF_ORDER, "no running episode: send reset first")
        turns = [self._turn(episode, d, *commands[d.id]) for d in episode.fleet if not d.over]
        self._drive_many(episode, seq, turns)
        ends: list[tuple[int, EndReason]] = []
        egos: list[EgoObservation] = []
        for turn in turns:
            action, events = turn.result()
            driven = turn.driven
            obs = turn.last or self._observe_ego(
                episode, driven.vehicle, driven.lane_change, seq, events, action
            )
            reason = EndReason.LANE_END if turn.lane_end else driven.end.check(obs)
            if reason is not None:
                obs = ended(obs, reason)
                driven.over = True
                ends.append((turn.steps, reason))  # in time, then in the egos' order
                if driven.vehicle in episode.road.vehicles:
                    episode.road.vehicles.remove(driven.vehicle)
            egos.append(ego_part(driven.id, obs))
        ends.sort(key=lambda end: end[0])  # stable: within a step, the egos' order
        return self._frame(episode, seq, tuple(egos), ends[-1][1] if ends else "")

    def _turn(self, episode: _Episode, driven: _Driven, request: float, lane_change: int) -> _Turn:
        """`driven`'s command checked and its lane change begun (or refused)."""
        refused = (
            self._lane_change_refusal(episode, driven.vehicle, driven.lane_change, lane_change)
            if lane_change
            else ""
        )
        started = bool(lane_change) and not refused
        if started:
            driven.lane_change = self._start_lane_change(episode, driven.vehicle, lane_change)
        return _Turn(driven, request, lane_change, refused, started)

    def _drive_many(self, episode: _Episode, seq: int, turns: list[_Turn]) -> None:
        """Run the decision's simulation steps for every ego at once, each request limited anew
        on each step; an ego that crashes or reaches the end of the road is observed at that step
        and taken off the road, the others drive on."""
        drives = episode.options.simulator_drives
        low, high = self.action_schema.acceleration_min, self.action_schema.acceleration_max
        for _ in range(episode.substeps):
            active = [t for t in turns if not t.stopped_inside]
            if not active:
                break
            for turn in active:
                ego = turn.driven.vehicle
                turn.why = AccelerationLimit.SIMULATOR
                if not drives:
                    limit = float(ego.lane.speed_limit)
                    ego.command, turn.why = limit_acceleration(
                        turn.request, float(ego.speed), limit, low, high, DT
                    )
            self._advance(episode)
            for turn in active:
                ego = turn.driven.vehicle
                if not drives and ego.speed < 0.0:
                    ego.speed = 0.0  # as for one ego
                turn.applied_total += float(ego.action["acceleration"])
                turn.limited_by = turn.limited_by or turn.why
                turn.steps += 1
                self._judge_step(episode, turn)
            stopped = [t for t in active if t.stopped_inside]
            for turn in stopped:  # observed before any leaves: two egos that collide see each other
                action, events = turn.result()
                driven = turn.driven
                turn.last = self._observe_ego(
                    episode, driven.vehicle, driven.lane_change, seq, events, action
                )
            for turn in stopped:
                episode.road.vehicles.remove(turn.driven.vehicle)

    def _judge_step(self, episode: _Episode, turn: _Turn) -> None:
        """After a simulation step: `turn`'s crash, end of road, end of its lane or lane-change
        progress."""
        driven = turn.driven
        ego = driven.vehicle
        outcome = self._outcome(episode, ego)
        if outcome == EndReason.COLLISION:
            turn.collision_with = episode.ids.get(self._collided_with(episode, ego), "unknown")
        elif outcome:
            turn.end_of_road = outcome == EndReason.END_OF_ROAD
            turn.lane_end = outcome == EndReason.LANE_END
        elif driven.lane_change is not None:
            completed, aborted = self._lane_change_progress(episode, ego, driven.lane_change)
            turn.completed, turn.aborted = turn.completed or completed, turn.aborted or aborted
            if completed or aborted:
                driven.lane_change = None

    @staticmethod
    def _frame(
        episode: _Episode, seq: int, egos: tuple[EgoObservation, ...], last_end: str
    ) -> MultiObservation:
        """The decision's frame: truncated at the time limit, terminated once no ego is left
        (with `last_end`, the reason of the last end)."""
        truncated = any(e.truncated for e in egos)
        terminated = not truncated and all(d.over for d in episode.fleet)
        reason = ""
        if truncated:
            reason = EndReason.TIME_LIMIT
        elif terminated:
            reason = last_end
        episode.done = truncated or terminated
        return MultiObservation(seq, episode.time, egos, terminated, truncated, reason)

    # ----------------------------------------------------------------------- lifecycle

    def close(self) -> None:
        self._episode = None
