"""`JunctionFoes` against a stub of SUMO's lane API: a route's next lane that SUMO does not
link directly to the ego's (a very short edge between them, on imported networks) has no
foes, instead of SUMO's "No connection from lane" ending the episode in an error."""

from __future__ import annotations

from dataclasses import dataclass, field

from sim_server.backends.sumo.junctions import JunctionFoes


class NoConnection(Exception):
    """What libsumo raises for getFoes on lanes it does not link."""


@dataclass
class Lanes:
    links: dict[str, list[tuple[str, ...]]] = field(default_factory=dict)
    asked: list[tuple[str, str]] = field(default_factory=list)

    def getLinks(self, lane: str) -> list[tuple[str, ...]]:
        return self.links.get(lane, [])

    def getFoes(self, from_lane: str, to_lane: str) -> list[str]:
        self.asked.append((from_lane, to_lane))
        if not any(link[0] == to_lane for link in self.links.get(from_lane, [])):
            raise NoConnection(f"No connection from lane '{from_lane}' to lane '{to_lane}'")
        return []

    def getLastStepVehicleIDs(self, lane: str) -> list[str]:
        return []


@dataclass
class Api:
    lane: Lanes = field(default_factory=Lanes)
    vehicle: object = None


def test_lanes_sumo_does_not_link_have_no_foes() -> None:
    api = Api()
    api.lane.links = {"a_0": [("b_0", ":j_0_0", "1", "1", "", "G", "s", 10.0)]}
    foes = JunctionFoes(api)
    assert foes.of("a_0", "c_0", 30.0) == ()  # not linked: no question SUMO would refuse
    assert foes.of("a_0", "b_0", 30.0) == ()  # linked, no foes on it
    assert api.lane.asked == [("a_0", "b_0")]
