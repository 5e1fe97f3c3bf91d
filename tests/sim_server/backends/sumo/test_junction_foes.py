"""`JunctionFoes` against a stub of SUMO's lane API: a route's next lane that SUMO does not
link directly to the ego's (a very short edge between them, on imported networks) has no
foes, instead of SUMO's "No connection from lane" ending the episode in an error; a vehicle
inside the junction on a lane that names the ego's as its foe is in the ego's way, though the
ego's lane does not name it back (SUMO's relation is not symmetric on joined clusters); one
on a crossing lane is a foe until its rear has left the ego's way, and one on a lane that SUMO
names but whose way does not meet the ego's is none."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import pytest

from sim_server.backends.sumo.junctions import CLEARANCE, EGO_WIDTH, FOE_WIDTH, JunctionFoes


class NoConnection(Exception):
    """What libsumo raises for getFoes on lanes it does not link."""


@dataclass
class Lanes:
    links: dict[str, list[tuple[object, ...]]] = field(default_factory=dict)
    asked: list[tuple[str, str]] = field(default_factory=list)
    internal_foes: dict[str, list[str]] = field(default_factory=dict)
    vehicles: dict[str, list[str]] = field(default_factory=dict)
    shapes: dict[str, list[tuple[float, float]]] = field(default_factory=dict)

    def getEdgeID(self, lane: str) -> str:
        return lane.rsplit("_", 1)[0]

    def getInternalFoes(self, lane: str) -> list[str]:
        return self.internal_foes.get(lane, [])

    def getShape(self, lane: str) -> list[tuple[float, float]]:
        # by default every junction lane runs along x, through the origin
        return self.shapes.get(lane, [(0.0, 0.0), (20.0, 0.0)])

    def getLength(self, lane: str) -> float:
        (x1, y1), (x2, y2) = self.getShape(lane)[0], self.getShape(lane)[-1]
        return math.hypot(x2 - x1, y2 - y1)  # the stub's shapes are straight

    def getLinks(self, lane: str) -> list[tuple[object, ...]]:
        return self.links.get(lane, [])

    def getFoes(self, from_lane: str, to_lane: str) -> list[str]:
        self.asked.append((from_lane, to_lane))
        if not any(link[0] == to_lane for link in self.links.get(from_lane, [])):
            raise NoConnection(f"No connection from lane '{from_lane}' to lane '{to_lane}'")
        return []

    def getLastStepVehicleIDs(self, lane: str) -> list[str]:
        return self.vehicles.get(lane, [])


class Edges:
    def getToJunction(self, edge: str) -> str:
        return "j"

    def getLaneNumber(self, edge: str) -> int:
        return 1


class Junctions:
    def getIncomingEdges(self, junction: str) -> list[str]:
        return ["a", "c"]


@dataclass
class Vehicles:
    positions: dict[str, tuple[float, float]] = field(default_factory=dict)
    angles: dict[str, float] = field(default_factory=dict)
    lane_positions: dict[str, float] = field(default_factory=dict)
    speeds: dict[str, float] = field(default_factory=dict)
    lengths: dict[str, float] = field(default_factory=dict)

    def getLanePosition(self, vehicle: str) -> float:
        return self.lane_positions[vehicle]

    def getSpeed(self, vehicle: str) -> float:
        return self.speeds.get(vehicle, 0.0)

    def getPosition(self, vehicle: str) -> tuple[float, float]:
        return self.positions[vehicle]

    def getAngle(self, vehicle: str) -> float:
        return self.angles.get(vehicle, 0.0)  # 0: heading north (+y), 90: east (+x)

    def getLength(self, vehicle: str) -> float:
        return self.lengths.get(vehicle, 5.0)

    def getWidth(self, vehicle: str) -> float:
        return 1.8


@dataclass
class Api:
    lane: Lanes = field(default_factory=Lanes)
    vehicle: Vehicles = field(default_factory=Vehicles)
    edge: Edges = field(default_factory=Edges)
    junction: Junctions = field(default_factory=Junctions)


def junction_links(
    ego_length: float, other_length: float, turning: bool = False
) -> dict[str, list[tuple[object, ...]]]:
    """SUMO's links of a junction "j": the ego's straight connection a_0 -> b_0 by junction
    lane :j_0_0 (`ego_length` m), and another, c_0 -> d_0 by :j_1_0 (`other_length` m; a left
    turn on a permissive green if `turning`, else straight with priority)."""
    state, direction = ("g", "l") if turning else ("G", "s")
    return {
        "a_0": [("b_0", ":j_0_0", "1", "1", ":j_0_0", "G", "s", ego_length)],
        "c_0": [("d_0", ":j_1_0", "0", "1", ":j_1_0", state, direction, other_length)],
        ":j_0_0": [("b_0", "", "1", "1", "", "G", "s", 0.0)],
        ":j_1_0": [("d_0", "", "1", "1", "", "G", direction, 0.0)],
    }


def test_lanes_sumo_does_not_link_have_no_foes() -> None:
    api = Api()
    api.lane.links = {"a_0": [("b_0", ":j_0_0", "1", "1", "", "G", "s", 10.0)]}
    foes = JunctionFoes(api)
    assert foes.of("a_0", "c_0", 30.0) == ()  # not linked: no question SUMO would refuse
    assert foes.of("a_0", "b_0", 30.0) == ()  # linked, no foes on it
    assert api.lane.asked == [("a_0", "b_0")]


def test_a_vehicle_standing_on_a_lane_that_names_the_egos_as_foe_is_in_its_way_if_on_it() -> None:
    """The turn's lane names the ego's straight lane as its foe, not the other way round (a
    left turn up to its waiting point, SUMO's design): a car standing there is in the ego's
    way only where its body is on the ego's way (a waiting point misplaced on a joined
    cluster), not where it waits clear of it."""
    api = Api()
    api.lane.links = junction_links(10.0, 10.0, turning=True)
    api.lane.internal_foes = {":j_1_0": [":j_0_0"]}  # the turn names the straight lane only
    api.lane.shapes = {":j_1_0": [(8.0, -10.0), (8.0, -3.0)]}  # by its lane, short of the way
    api.lane.vehicles = {":j_1_0": ["turning"]}
    api.vehicle.lane_positions = {"turning": 7.0}  # at its end (where the body is: below)
    api.vehicle.positions = {"turning": (8.0, 1.5)}  # its front 1.5 m from the ego's way
    (foe,) = JunctionFoes(api).inside("a_0", ":j_0_0", 12.0)
    assert foe.distance == 0.0 and foe.speed == 0.0 and foe.ego_exit_distance == 12.0
    api.vehicle.positions = {"turning": (8.0, 3.5)}  # its front past, its middle across it
    assert len(JunctionFoes(api).inside("a_0", ":j_0_0", 12.0)) == 1
    api.vehicle.positions = {"turning": (8.0, 2.7)}  # waiting clear of it (2.7 m: SUMO's own)
    api.vehicle.angles = {"turning": 90.0}  # beside it, heading the same way
    assert JunctionFoes(api).inside("a_0", ":j_0_0", 12.0) == ()
    api.vehicle.positions = {"turning": (8.0, 1.5)}
    assert len(JunctionFoes(api).inside("a_0", ":j_0_0", 12.0)) == 1
    # by its lane it stands across the way (a truck starting a U-turn on São Paulo's export,
    # its body judged clear by three points of it): in the way
    api.lane.shapes = {":j_1_0": [(8.0, -10.0), (8.0, 10.0)]}
    api.vehicle.lane_positions = {"turning": 10.5}
    api.vehicle.positions = {"turning": (8.0, 30.0)}
    assert len(JunctionFoes(api).inside("a_0", ":j_0_0", 12.0)) == 1
    api.lane.vehicles = {}
    assert JunctionFoes(api).inside("a_0", ":j_0_0", 12.0) == ()


def test_inside_a_junction_the_ego_stops_short_of_a_vehicle_standing_on_its_way() -> None:
    api = Api()
    api.lane.links = junction_links(20.0, 10.0, turning=True)
    api.lane.internal_foes = {":j_1_0": [":j_0_0"]}
    api.lane.vehicles = {":j_1_0": ["turning"]}
    api.vehicle.positions = {"turning": (14.0, 1.5)}  # heading north, its rear across the way
    ahead = JunctionFoes(api).standing_ahead("a_0", ":j_0_0", 4.0)
    assert ahead == pytest.approx(14.0 - 0.5 * 1.8 - 4.0 - CLEARANCE)  # to its side
    assert JunctionFoes(api).standing_ahead("a_0", ":j_0_0", 15.0) == math.inf  # passed it
    api.vehicle.positions = {"turning": (14.0, 9.0)}  # clear of the way
    assert JunctionFoes(api).standing_ahead("a_0", ":j_0_0", 4.0) == math.inf


def test_a_vehicle_whose_outline_is_clear_of_the_egos_way_does_not_stand_on_it() -> None:
    """A car standing at a right angle to the ego's way, its front 1.6 m from the ego's centre
    line: its outline is 0.7 m clear of the ego (within both half widths of the line by its
    centre, not by its body; São Paulo: the ego stood behind it, it waited for the ego)."""
    api = Api()
    api.lane.links = junction_links(20.0, 10.0, turning=True)
    api.lane.internal_foes = {":j_1_0": [":j_0_0"]}
    api.lane.vehicles = {":j_1_0": ["turning"]}
    api.vehicle.positions = {"turning": (14.0, 1.6)}
    api.vehicle.angles = {"turning": 180.0}  # heading south, its front 1.6 m short of the way
    assert JunctionFoes(api).standing_ahead("a_0", ":j_0_0", 4.0) == math.inf
    api.vehicle.positions = {"turning": (14.0, 0.8)}  # 0.8 m: its front corners on the way
    assert JunctionFoes(api).standing_ahead("a_0", ":j_0_0", 4.0) == pytest.approx(
        14.0 - 0.9 - 4.0 - CLEARANCE
    )


def test_a_crossing_vehicle_is_a_foe_until_its_rear_has_left_the_egos_way() -> None:
    """A lane the ego's names as its foe crosses it (here at right angles, 10 m along it): a
    car on it is a foe from where it is to the crossing, until its rear is through, not while
    it stands short of it (it waits, often for the ego: São Paulo, a trip jammed so); a lane
    SUMO names whose way never meets the ego's (the oncoming lanes of a turn's lane up to
    its waiting point, which meet only the lane after it) holds no foe unless a car's body
    is on the ego's way (Greenville: IDM + MOBIL stood before such a turn for three cycles)."""
    api = Api()
    api.lane.links = junction_links(20.0, 20.0)
    api.lane.shapes = {":j_1_0": [(10.0, -10.0), (10.0, 10.0)]}  # northwards across x = 10
    api.lane.internal_foes = {":j_0_0": [":j_1_0"], ":j_1_0": [":j_0_0"]}
    api.lane.vehicles = {":j_1_0": ["crossing"]}
    api.vehicle.positions = {"crossing": (10.0, -5.0)}
    api.vehicle.speeds = {"crossing": 5.0}
    api.vehicle.lane_positions = {"crossing": 5.0}  # its front 5 m along, 2.8 m before the way
    (foe,) = JunctionFoes(api).inside("a_0", ":j_0_0", 12.0)
    reach = 0.5 * (FOE_WIDTH + EGO_WIDTH)
    assert foe.distance == pytest.approx(10.0 - reach - 5.0, abs=0.6)
    assert foe.exit_distance == pytest.approx(10.0 + reach, abs=0.6)  # its rear at 0 m
    api.vehicle.speeds = {"crossing": 0.0}  # stopped short of the way: it waits
    assert JunctionFoes(api).inside("a_0", ":j_0_0", 12.0) == ()
    api.vehicle.positions = {"crossing": (10.0, 1.0)}
    api.vehicle.lane_positions = {"crossing": 11.0}  # on the way, stopped or not
    (foe,) = JunctionFoes(api).inside("a_0", ":j_0_0", 12.0)
    assert foe.distance == 0.0 and foe.exit_distance > 0.0 and foe.speed == 0.0
    api.vehicle.positions = {"crossing": (10.0, 8.0)}
    api.vehicle.lane_positions = {"crossing": 18.0}  # its rear at 13 m: through
    assert JunctionFoes(api).inside("a_0", ":j_0_0", 12.0) == ()
    api.lane.shapes = {":j_1_0": [(30.0, -10.0), (30.0, 10.0)]}  # named, but 10 m beyond the way
    api.vehicle.positions = {"crossing": (30.0, 0.0)}
    api.vehicle.lane_positions = {"crossing": 10.0}
    assert JunctionFoes(api).inside("a_0", ":j_0_0", 12.0) == ()


def test_a_crossing_vehicle_whose_front_has_driven_on_is_a_foe_while_its_rear_is_across() -> None:
    """SUMO lists a vehicle on the lane its front is on: a truck whose front has left the
    crossing lane (which ends right after the ego's way) still has its rear across it."""
    api = Api()
    api.lane.links = junction_links(20.0, 13.0)
    api.lane.shapes = {":j_1_0": [(10.0, -10.0), (10.0, 3.0)]}  # ends 3 m past the ego's way
    api.lane.internal_foes = {":j_0_0": [":j_1_0"], ":j_1_0": [":j_0_0"]}
    api.lane.vehicles = {"d_0": ["truck"]}
    api.vehicle.lengths = {"truck": 12.0}
    api.vehicle.lane_positions = {"truck": 2.0}  # its rear 13 + 2 - 12 = 3 m along :j_1_0
    (foe,) = JunctionFoes(api).inside("a_0", ":j_0_0", 12.0)
    assert foe.distance == 0.0 and foe.exit_distance > 0.0
    api.vehicle.lane_positions = {"truck": 12.5}  # its rear 0.5 m along d_0: through
    assert JunctionFoes(api).inside("a_0", ":j_0_0", 12.0) == ()
