"""Who has priority over the ego's way through its next junction: the foes it must give way to.

SUMO knows, for a connection from one lane to another, the incoming lanes whose own connections
have priority over it (`lane.getFoes`: the junction's right of way; at a traffic light, the
lanes whose links are green with priority while the ego's is a permissive green). The vehicles
on those lanes that are coming (their lane's links not red) and near, and those already inside
the junction on a conflicting internal lane, are the foes `road.stop_line` weighs: whether the
ego can leave the conflict area before one of them arrives. A vehicle turning left across
oncoming traffic is looked at twice: before the junction, and at the waiting point inside it
(SUMO's internal junction), where it stands while the oncoming stream passes.

Source: SUMO docs, TraCI "Lane Value Retrieval" (foes 0x37, links 0x33); "Networks/SUMO Road
Networks" (internal junctions, right of way).
"""

from __future__ import annotations

from typing import Any

from sim_server.backends.sumo.road import Foe

FOE_HORIZON = 150.0
"""m before the junction within which a vehicle with priority is looked at."""
CROSSING_LENGTH = 20.0
"""m a foe drives through the conflict area (about a junction's size)."""
NOT_COMING = frozenset("ru")
"""Link states of a foe lane whose vehicles do not enter now: red, red-yellow."""
BLOCKING_LOOK = 30.0
"""m before the junction from which a vehicle standing or driving inside it, across the ego's
way, closes the way even to an ego with priority (it must not drive into a blocked junction)."""
BLOCKING_TIME = 2.0
"""s: also from as far as the ego drives in this time."""
MAX_JUNCTION_LANES = 10_000
"""Bound on the lanes looked at to list one junction's inner lanes."""


class JunctionFoes:
    """The foes of a connection, from SUMO's right of way (the foe lanes of each connection
    asked once per network)."""

    def __init__(self, api: Any) -> None:
        self._api = api
        self._lanes: dict[tuple[str, str], tuple[str, ...]] = {}
        self._crossing: dict[str, tuple[str, ...]] = {}
        self._waits: dict[str, bool] = {}
        self._lengths: dict[str, float] = {}
        self._foes_of: dict[str, tuple[str, ...]] = {}
        self._inside_lanes: dict[str, tuple[str, ...]] = {}

    def of(self, from_lane: str, to_lane: str, ego_exit: float) -> tuple[Foe, ...]:
        """The foes of the connection `from_lane` -> `to_lane`; `ego_exit` is the ego's
        distance to where it has left the conflict area."""
        lane_api, vehicle = self._api.lane, self._api.vehicle
        key = (from_lane, to_lane)
        lanes = self._lanes.get(key)
        if lanes is None:
            # Only a connection has foes: SUMO raises for lanes it does not link directly (a
            # route's next lane beyond a very short edge, on imported networks).
            linked = any(link[0] == to_lane for link in lane_api.getLinks(from_lane))
            foes = lane_api.getFoes(from_lane, to_lane) if linked else ()
            lanes = self._lanes[key] = tuple(sorted(set(foes)))
        found: list[Foe] = []
        for lane in lanes:
            vehicles = lane_api.getLastStepVehicleIDs(lane)
            if not vehicles:
                continue
            if lane.startswith(":"):  # inside the junction now, in the way
                found += [
                    Foe(0.0, CROSSING_LENGTH, vehicle.getSpeed(v), ego_exit) for v in vehicles
                ]
                continue
            states = {link[5] for link in lane_api.getLinks(lane)}
            if states and states <= NOT_COMING:
                continue
            length = self._length(lane)
            for other in vehicles:
                distance = length - vehicle.getLanePosition(other)
                if distance <= FOE_HORIZON:
                    speed = vehicle.getSpeed(other)
                    found.append(Foe(distance, distance + CROSSING_LENGTH, speed, ego_exit))
        return tuple(found)

    def waits_inside(self, via: str) -> bool:
        """Whether the junction lane `via` ends at a waiting point inside the junction (SUMO's
        internal junction: a turn across oncoming traffic, which the ego may drive up to and
        wait at, as SUMO's drivers do, the oncoming stream judged there)."""
        known = self._waits.get(via)
        if known is None:
            known = self._waits[via] = any(
                str(link[4]).startswith(":") for link in self._api.lane.getLinks(via)
            )
        return known

    def inside(self, from_lane: str, via: str, ego_exit: float) -> tuple[Foe, ...]:
        """The vehicles inside the junction now on a lane that crosses or merges with the
        ego's junction lane `via` (taken from `from_lane`; whoever has priority: they are in
        the way)."""
        lane_api, vehicle = self._api.lane, self._api.vehicle
        crossing = self._crossing.get(via)
        if crossing is None:
            crossing = self._crossing[via] = self._crossing_lanes(from_lane, via)
        found: list[Foe] = []
        for lane in crossing:
            for other in lane_api.getLastStepVehicleIDs(lane):
                found.append(Foe(0.0, CROSSING_LENGTH, vehicle.getSpeed(other), ego_exit))
        return tuple(found)

    def _crossing_lanes(self, from_lane: str, via: str) -> tuple[str, ...]:
        """The junction lanes that cross or merge with `via`: its own internal foes and the
        lanes of its junction that name `via` among theirs. SUMO's relation is not always
        symmetric (on netconvert's joined clusters a turn's lane may name a straight lane
        that does not name it back), and a vehicle standing on such a lane, waiting inside
        the junction for the straight stream, is in the way all the same (DRT, SUMO's game
        network: the ego drove into one in 3 of 100 trips, SUMO's own driver in 2)."""
        lane_api = self._api.lane
        crossing = set(self._internal_foes(via))
        edge = lane_api.getEdgeID(from_lane)
        junction = self._api.edge.getToJunction(edge)
        for lane in self._junction_lanes(junction):
            if lane != via and via in self._internal_foes(lane):
                crossing.add(lane)
        return tuple(sorted(crossing))

    def _internal_foes(self, lane: str) -> tuple[str, ...]:
        foes = self._foes_of.get(lane)
        if foes is None:
            foes = self._foes_of[lane] = tuple(self._api.lane.getInternalFoes(lane))
        return foes

    def _junction_lanes(self, junction: str) -> tuple[str, ...]:
        """Every lane inside `junction`: the junction lanes of its incoming lanes' links,
        and those after a waiting point inside it (bounded: a junction's lanes lead out)."""
        lanes = self._inside_lanes.get(junction)
        if lanes is not None:
            return lanes
        lane_api, edge_api = self._api.lane, self._api.edge
        found: list[str] = []
        pending = [
            f"{edge}_{index}"
            for edge in self._api.junction.getIncomingEdges(junction)
            for index in range(edge_api.getLaneNumber(edge))
        ]
        seen: set[str] = set()
        for _ in range(MAX_JUNCTION_LANES):
            if not pending:
                break
            lane = pending.pop()
            for link in lane_api.getLinks(lane):
                inner = str(link[4])
                if inner.startswith(":") and inner not in seen:
                    seen.add(inner)
                    found.append(inner)
                    pending.append(inner)
        lanes = self._inside_lanes[junction] = tuple(found)
        return lanes

    def _length(self, lane: str) -> float:
        length = self._lengths.get(lane)
        if length is None:
            length = self._lengths[lane] = self._api.lane.getLength(lane)
        return length
