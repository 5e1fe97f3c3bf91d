"""`JunctionFoes` against a stub of SUMO's lane API: a route's next lane that SUMO does not
link directly to the ego's (a very short edge between them, on imported networks) has no
foes, instead of SUMO's "No connection from lane" ending the episode in an error; a vehicle
inside the junction on a lane that names the ego's as its foe is in the ego's way, though the
ego's lane does not name it back (SUMO's relation is not symmetric on joined clusters)."""

from __future__ import annotations

from dataclasses import dataclass, field

from sim_server.backends.sumo.junctions import JunctionFoes


class NoConnection(Exception):
    """What libsumo raises for getFoes on lanes it does not link."""


@dataclass
class Lanes:
    links: dict[str, list[tuple[object, ...]]] = field(default_factory=dict)
    asked: list[tuple[str, str]] = field(default_factory=list)
    internal_foes: dict[str, list[str]] = field(default_factory=dict)
    vehicles: dict[str, list[str]] = field(default_factory=dict)

    def getEdgeID(self, lane: str) -> str:
        return lane.rsplit("_", 1)[0]

    def getInternalFoes(self, lane: str) -> list[str]:
        return self.internal_foes.get(lane, [])

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


class Vehicles:
    def getSpeed(self, vehicle: str) -> float:
        return 0.0


@dataclass
class Api:
    lane: Lanes = field(default_factory=Lanes)
    vehicle: object = field(default_factory=Vehicles)
    edge: Edges = field(default_factory=Edges)
    junction: Junctions = field(default_factory=Junctions)


def test_lanes_sumo_does_not_link_have_no_foes() -> None:
    api = Api()
    api.lane.links = {"a_0": [("b_0", ":j_0_0", "1", "1", "", "G", "s", 10.0)]}
    foes = JunctionFoes(api)
    assert foes.of("a_0", "c_0", 30.0) == ()  # not linked: no question SUMO would refuse
    assert foes.of("a_0", "b_0", 30.0) == ()  # linked, no foes on it
    assert api.lane.asked == [("a_0", "b_0")]


def test_a_vehicle_standing_on_a_lane_that_names_the_egos_as_foe_is_in_its_way() -> None:
    api = Api()
    api.lane.links = {
        "a_0": [("b_0", ":j_0_0", "1", "1", ":j_0_0", "G", "s", 10.0)],
        "c_0": [("d_0", ":j_1_0", "0", "1", ":j_1_0", "g", "l", 10.0)],
        ":j_0_0": [("b_0", "", "1", "1", "", "G", "s", 0.0)],
        ":j_1_0": [("d_0", "", "1", "1", "", "G", "l", 0.0)],
    }
    api.lane.internal_foes = {":j_1_0": [":j_0_0"]}  # the turn names the straight lane only
    api.lane.vehicles = {":j_1_0": ["turning"]}  # standing inside, across the ego's way
    (foe,) = JunctionFoes(api).inside("a_0", ":j_0_0", 12.0)
    assert foe.distance == 0.0 and foe.speed == 0.0 and foe.ego_exit_distance == 12.0
    api.lane.vehicles = {}
    assert JunctionFoes(api).inside("a_0", ":j_0_0", 12.0) == ()
