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

import itertools
import math
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
STANDING_SPEED = 2.0
"""m/s: slower than this, a vehicle inside a junction stands in the way of those it is on."""
STOPPED_SPEED = 0.5
"""m/s: slower than this, a vehicle inside a junction short of the ego's way waits there (for
the ego, as often as not: counting it as coming, the ego on São Paulo's export waited for a
car that waited for it until `jam_patience` ended the trip)."""
WAITING_CAR = 5.0
"""m: the length of the car assumed standing at a waiting point."""
CLEARANCE = 2.0
"""m the ego stops short of a vehicle standing on its way inside a junction."""
EGO_WIDTH = 1.8
"""m: the ego's width (SUMO's passenger car)."""
FOE_WIDTH = 2.6
"""m: the widest vehicle assumed on a crossing junction lane (a truck, 2.55 m)."""
CONFLICT_STEP = 0.5
"""m between the points of a junction lane tested against the ego's way."""
MAX_CONFLICT_STEPS = 1_000
"""Bound on the points tested per junction lane."""
DRIVING_UP_SPEED = 3.0
"""m/s: a vehicle at least this fast towards a junction drives up to it (one standing in a
queue, or creeping up to it, starts slowly)."""
OUTLINE_STEP = 0.5
"""m between the points of a vehicle's outline tested against the ego's way (a little more
where a side is not a whole number of steps long: 0.54 m on a 4.9 m car)."""
LATERAL_MARGIN = 0.3
"""m beyond half the ego's width within which a point of another vehicle's body counts as on
the ego's way."""
MAX_JUNCTION_LANES = 10_000
"""Bound on the lanes looked at to list one junction's inner lanes."""


class JunctionFoes:
    """The foes of a connection, from SUMO's right of way (the foe lanes of each connection
    asked once per network)."""

    def __init__(self, api: Any) -> None:
        self._api = api
        self._lanes: dict[tuple[str, str], tuple[str, ...]] = {}
        self._crossing: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {}
        self._shapes: dict[str, tuple[tuple[float, float], ...]] = {}
        self._waits: dict[str, bool] = {}
        self._lengths: dict[str, float] = {}
        self._foes_of: dict[str, tuple[str, ...]] = {}
        self._inside_lanes: dict[str, tuple[str, ...]] = {}
        self._conflicts: dict[tuple[str, str], tuple[float, float] | None] = {}
        self._onward_lanes: dict[str, tuple[str, ...]] = {}
        self._approach_lanes: dict[str, tuple[str, ...]] = {}

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
        the way), or that names `via` as its foe without `via` naming it back and ends at a
        waiting point on the ego's way (`_crossing_lanes`): each from where it is to where
        the ways meet (`_conflict`), until its rear is through, unless it stopped short of
        them (`_crossing_foes`); and those on the other lanes that name `via` whose body is
        on the ego's way now (`_named_foes`)."""
        lanes = self._crossing.get(via)
        if lanes is None:
            lanes = self._crossing[via] = self._crossing_lanes(from_lane, via)
        crossing, named_by = lanes
        found: list[Foe] = []
        for lane in crossing:
            found += self._crossing_foes(lane, via, ego_exit)
        for lane in named_by:
            found += self._named_foes(lane, via, ego_exit)
        return tuple(found)

    def driving_up(self, from_lane: str, via: str, within: float) -> bool:
        """Whether a vehicle drives (`DRIVING_UP_SPEED` at least) towards the junction on a
        lane whose junction lane crosses `via` (taken from `from_lane`) and would be there
        within `within` seconds at its speed now: one that SUMO lets start at its green
        without waiting for a car inside (`SumoBackend._stranded`)."""
        lanes = self._crossing.get(via)
        if lanes is None:
            lanes = self._crossing[via] = self._crossing_lanes(from_lane, via)
        lane_api, vehicle = self._api.lane, self._api.vehicle
        junction = self._api.edge.getToJunction(lane_api.getEdgeID(from_lane))
        for crossing in lanes[0]:
            for approach in self._approaches(junction, crossing):
                length = self._length(approach)
                for other in lane_api.getLastStepVehicleIDs(approach):
                    speed = vehicle.getSpeed(other)
                    to_junction = length - vehicle.getLanePosition(other)
                    if speed >= DRIVING_UP_SPEED and to_junction <= speed * within:
                        return True
        return False

    def _approaches(self, junction: str, lane: str) -> tuple[str, ...]:
        """The lanes whose connection goes through `junction`'s junction lane `lane`: of its
        incoming roads, and its own junction lanes up to a waiting point (libsumo lists its
        internal edges among its incoming ones): a car there drives up to `lane` too."""
        approaches = self._approach_lanes.get(lane)
        if approaches is None:
            lane_api = self._api.lane
            approaches = self._approach_lanes[lane] = tuple(
                approach
                for edge in self._api.junction.getIncomingEdges(junction)
                for approach in (
                    f"{edge}_{index}" for index in range(self._api.edge.getLaneNumber(edge))
                )
                if any(link[4] == lane for link in lane_api.getLinks(approach))
            )
        return approaches

    def _crossing_foes(self, lane: str, via: str, ego_exit: float) -> list[Foe]:
        """The foes on junction lane `lane`, which crosses or merges with `via` (`inside`)."""
        lane_api, vehicle = self._api.lane, self._api.vehicle
        span = self._conflict(lane, via)
        found: list[Foe] = []
        if span is not None:  # those whose front has driven on, their rear still across
            lane_length = self._length(lane)
            for onward in self._onward(lane):
                for other in lane_api.getLastStepVehicleIDs(onward):
                    rear = lane_length + vehicle.getLanePosition(other) - vehicle.getLength(other)
                    if rear <= span[1]:
                        speed = vehicle.getSpeed(other)
                        found.append(Foe(0.0, span[1] - rear, speed, ego_exit))
        for other in lane_api.getLastStepVehicleIDs(lane):
            speed = vehicle.getSpeed(other)
            if span is None:  # named a foe, but its way does not meet the ego's
                if self._on_the_way(other, via):
                    found.append(Foe(0.0, CROSSING_LENGTH, speed, ego_exit))
                continue
            front = vehicle.getLanePosition(other)
            rear = front - vehicle.getLength(other)
            if rear > span[1]:
                continue  # through: its rear has left the ego's way
            distance = max(span[0] - front, 0.0)
            if distance > 0.0 and speed < STOPPED_SPEED:
                if not self._on_the_way(other, via):
                    continue  # stopped short of the ego's way: it waits, often for the ego
                distance = 0.0  # short of it by its lane, but its body is across the way
            found.append(Foe(distance, span[1] - rear, speed, ego_exit))
        return found

    def _named_foes(self, lane: str, via: str, ego_exit: float) -> list[Foe]:
        """The foes on junction lane `lane`, which names `via` as its foe without being named
        back (`inside`): those whose body is on the ego's way, by their lane's conflict span
        or by where their body lies (a truck starting a U-turn stood across it: São Paulo)."""
        lane_api, vehicle = self._api.lane, self._api.vehicle
        span = self._conflict(lane, via)
        found: list[Foe] = []
        for other in lane_api.getLastStepVehicleIDs(lane):
            front = vehicle.getLanePosition(other)
            rear = front - vehicle.getLength(other)
            across = span is not None and span[0] <= front and rear <= span[1]
            if across or self._on_the_way(other, via):
                found.append(Foe(0.0, CROSSING_LENGTH, vehicle.getSpeed(other), ego_exit))
        return found

    def standing_ahead(self, from_lane: str, lane: str, position: float) -> float:
        """On the junction lane `lane` (entered from `from_lane`), `position` m along it: m
        to the nearest point where another lane's vehicle, standing (slower than
        `STANDING_SPEED`), has its body on the ego's way ahead
        (`_on_the_way`), less `CLEARANCE`; `math.inf` where none is. A junction of a joined
        cluster may be 35 m long, and a car that stopped at a waiting point placed on the
        ego's way after the ego entered is met inside it (DRT)."""
        lanes = self._crossing.get(lane)
        if lanes is None:
            lanes = self._crossing[lane] = self._crossing_lanes(from_lane, lane)
        lane_api, vehicle = self._api.lane, self._api.vehicle
        nearest = math.inf
        for other_lane in lanes[0] + lanes[1]:
            for other in lane_api.getLastStepVehicleIDs(other_lane):
                if vehicle.getSpeed(other) >= STANDING_SPEED:
                    continue  # crossing: it clears the way (right of way judged before)
                along = self._along_the_way(other, lane)
                if along is not None and along > position:
                    nearest = min(nearest, along - position - CLEARANCE)
        return max(nearest, 0.0)

    def _crossing_lanes(self, from_lane: str, via: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
        """The junction lanes that cross or merge with `via` (its own internal foes), and
        the lanes of its junction that name `via` among theirs though `via` does not name
        them. SUMO's relation is not symmetric: a left turn's lane up to its waiting point
        names the oncoming straight lane it waits for, which does not name it back, since a
        car standing at the waiting point is clear of it; on netconvert's joined clusters
        that waiting point may lie on the straight lane's way, and a car standing there is
        in the way all the same (DRT, SUMO's game network: the ego drove into one in 3 of
        100 trips, SUMO's own driver in 2)."""
        lane_api = self._api.lane
        crossing = set(self._internal_foes(via))
        edge = lane_api.getEdgeID(from_lane)
        junction = self._api.edge.getToJunction(edge)
        named_by = {
            lane
            for lane in self._junction_lanes(junction)
            if lane != via and lane not in crossing and via in self._internal_foes(lane)
        }
        misplaced = {lane for lane in named_by if self._waits_on(lane, via)}
        crossing |= misplaced
        return tuple(sorted(crossing)), tuple(sorted(named_by - misplaced))

    def _waits_on(self, lane: str, via: str) -> bool:
        """Whether junction lane `lane` ends at a waiting point (`waits_inside`) where a car
        standing (its front at the end, its middle `WAITING_CAR` / 2 behind) is on the way
        of `via`: a waiting point netconvert placed on the way it waits for."""
        if not self.waits_inside(lane):
            return False
        shape, way = self._shape(lane), self._shape(via)
        length = _length_of(shape)
        for back in (0.0, 0.5 * WAITING_CAR):
            point = _point_at(shape, max(length - back, 0.0))
            if _projection(point, way)[0] < EGO_WIDTH:
                return True
        return False

    def _conflict(self, lane: str, via: str) -> tuple[float, float] | None:
        """(first, last) m along junction lane `lane` where a vehicle on it (up to
        `FOE_WIDTH` wide) would touch the ego on junction lane `via`; None where the two ways
        do not meet. SUMO names as foes of a turn's lane up to its waiting point the oncoming
        lanes it waits for there, whose ways meet only the lane after the waiting point: a car
        on those does not close the way into the junction (Greenville: IDM + MOBIL stood
        before a left turn for three cycles while each green's oncoming cars drove by)."""
        key = (lane, via)
        if key in self._conflicts:
            return self._conflicts[key]
        shape, way = self._shape(lane), self._shape(via)
        length = _length_of(shape)
        reach = 0.5 * (FOE_WIDTH + EGO_WIDTH)
        steps = min(max(int(length / CONFLICT_STEP) + 1, 2), MAX_CONFLICT_STEPS)
        step = length / (steps - 1)
        touching = [
            k * step
            for k in range(steps)
            if _projection(_point_at(shape, k * step), way)[0] < reach
        ]
        span = None
        if touching:  # widened by a step (the sampling's error), in the lane's own metres
            scale = self._length(lane) / length if length > 0.0 else 1.0
            first, last = max(touching[0] - step, 0.0), min(touching[-1] + step, length)
            span = (first * scale, last * scale)
        self._conflicts[key] = span
        return span

    def _onward(self, lane: str) -> tuple[str, ...]:
        """The lanes junction lane `lane` leads to (SUMO lists a vehicle on the lane its front
        is on: one whose front has left `lane` is found on these)."""
        onward = self._onward_lanes.get(lane)
        if onward is None:
            onward = self._onward_lanes[lane] = tuple(
                str(link[0]) for link in self._api.lane.getLinks(lane)
            )
        return onward

    def _on_the_way(self, other: str, via: str) -> bool:
        """Whether vehicle `other`'s body lies on the ego's way along the junction lane `via`
        (`_along_the_way`)."""
        return self._along_the_way(other, via) is not None

    def _along_the_way(self, other: str, via: str) -> float | None:
        """m along the junction lane `via` to the first point of vehicle `other`'s body (its
        outline, about `OUTLINE_STEP` apart) that lies within half the ego's width and
        `LATERAL_MARGIN` of its centre line; None where none does. The outline, not the
        centre line widened by both half widths: a car standing across the ego's way at a
        right angle, its front 1.6 m from the ego's centre line, is 0.7 m clear of the ego, and
        the ego stood behind it while it waited for the ego (São Paulo, a jam)."""
        vehicle = self._api.vehicle
        x, y = vehicle.getPosition(other)
        heading = math.radians(vehicle.getAngle(other))
        length, width = vehicle.getLength(other), vehicle.getWidth(other)
        reach = 0.5 * EGO_WIDTH + LATERAL_MARGIN
        shape = self._shape(via)
        found: float | None = None
        for point in _outline(x, y, heading, length, width):
            distance, along = _projection(point, shape)
            if distance < reach and (found is None or along < found):
                found = along
        return found

    def _shape(self, lane: str) -> tuple[tuple[float, float], ...]:
        shape = self._shapes.get(lane)
        if shape is None:
            shape = self._shapes[lane] = tuple(
                (float(x), float(y)) for x, y in self._api.lane.getShape(lane)
            )
        return shape

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


def _outline(
    x: float, y: float, heading: float, length: float, width: float
) -> list[tuple[float, float]]:
    """Points about `OUTLINE_STEP` apart around a vehicle's rectangle, its front centre at
    (`x`, `y`), heading `heading` (radians, SUMO's: clockwise from north)."""
    ahead_x, ahead_y = math.sin(heading), math.cos(heading)
    left_x, left_y = -ahead_y, ahead_x
    along = max(int(length / OUTLINE_STEP), 1)
    across = max(int(width / OUTLINE_STEP), 1)
    points: list[tuple[float, float]] = []
    for k in range(along + 1):
        back = length * k / along
        for side in (-0.5, 0.5):
            points.append((x - back * ahead_x + side * width * left_x,
                           y - back * ahead_y + side * width * left_y))  # fmt: skip
    for k in range(1, across):
        side = k / across - 0.5
        for back in (0.0, length):
            points.append((x - back * ahead_x + side * width * left_x,
                           y - back * ahead_y + side * width * left_y))  # fmt: skip
    return points


def _projection(
    point: tuple[float, float], shape: tuple[tuple[float, float], ...]
) -> tuple[float, float]:
    """(m from `point` to the polyline `shape`, m along `shape` to its nearest point)."""
    px, py = point
    best, best_along, walked = math.inf, 0.0, 0.0
    if len(shape) == 1:
        return math.hypot(px - shape[0][0], py - shape[0][1]), 0.0
    for (x1, y1), (x2, y2) in itertools.pairwise(shape):
        dx, dy = x2 - x1, y2 - y1
        squared = dx * dx + dy * dy
        along = ((px - x1) * dx + (py - y1) * dy) / squared if squared else 0.0
        t = max(0.0, min(1.0, along))
        distance = math.hypot(px - x1 - t * dx, py - y1 - t * dy)
        segment = math.sqrt(squared)
        if distance < best:
            best, best_along = distance, walked + t * segment
        walked += segment
    return best, best_along


def _length_of(shape: tuple[tuple[float, float], ...]) -> float:
    return sum(math.hypot(x2 - x1, y2 - y1) for (x1, y1), (x2, y2) in itertools.pairwise(shape))


def _point_at(shape: tuple[tuple[float, float], ...], along: float) -> tuple[float, float]:
    """The point `along` m along the polyline `shape` (its last point beyond its end)."""
    walked = 0.0
    for (x1, y1), (x2, y2) in itertools.pairwise(shape):
        segment = math.hypot(x2 - x1, y2 - y1)
        if segment > 0.0 and walked + segment >= along:
            t = (along - walked) / segment
            return (x1 + t * (x2 - x1), y1 + t * (y2 - y1))
        walked += segment
    return shape[-1]
