"""The egos' route through a built highway-env road network, and the road ahead read off it.

`Layout` measures every vehicle along the route (its route coordinate: the observation's
``position`` for an ego's front), finds which lane leads into which across the joins of the
route's roads, and where each lane stops leading on (`Layout.reach`): from these come the
protocol's `Road` (protocol 1.6), the lanes beside an ego, the arrivals of the humans, the ego's
``lane_end`` and the route highway-env's MOBIL steers a vehicle along (`Layout.plan`).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from protocol.messages import ROAD_RANGE, Road

JOIN_TOLERANCE = 0.5
"""Metres within which a lane's end and a lane start of the next road on the route are one
point: the first leads into the second."""

LaneIndex = tuple[str, str, int]
"""highway-env's lane index: (from node, to node, lane id counted from the left)."""
RoadId = tuple[str, str]
"""A road of highway-env's network: its lanes share (from node, to node)."""


def _longitudinal(lane: Any, position: Any) -> float:
    """`position`'s longitudinal coordinate on `lane` (m from its start)."""
    return float(lane.local_coordinates(position)[0])


@dataclass(frozen=True)
class Layout:
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
    def of(cls, network: Any, route: tuple[RoadId, ...], finals: frozenset[RoadId]) -> Layout:
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
    """`Layout.reach`, `best` and `dead_ends`, from the route's last road back."""
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
