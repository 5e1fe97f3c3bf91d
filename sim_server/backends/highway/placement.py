"""The corridors' vehicles, placed on a built road as highway-env's ``create_random`` places them.

`Column` spaces vehicles one after another as ``create_random`` does; `Populating` puts them on
the road (the egos with highway-env's human model for the warm-up, the humans on a lane that ends
with the route that leads them off it) and marks each lane end with an obstacle. On ``merge`` the
egos start one after another on the ramp, on ``exit`` and ``lanedrop`` each ego is followed by its
share of the humans (`_platoon`, as on ``cf``).
"""

from __future__ import annotations

import math
from typing import Any

from highway_env.road.road import Road as HighwayRoad
from highway_env.utils import near_split
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.kinematics import Vehicle
from highway_env.vehicle.objects import Obstacle

from protocol.errors import ErrorCode
from sim_server.backends.highway.networks import (
    LANE_DROP_LANES,
    Geometry,
    exit_layout,
    lane_drop_layout,
    merge_layout,
)
from sim_server.backends.highway.road import LaneIndex, Layout, RoadId
from sim_server.backends.highway.scene import Scene, SceneOptions
from sim_server.backends.sumo.corridors import MOTORWAY_SPEED, RAMP_SPEED
from sim_server.errors import BackendError

START_ROOM = 100.0
"""Metres a human needs ahead in a lane that ends to be placed in it, and an ego to start in it
(on ``merge``, before the end of the acceleration lane)."""


class Column:
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


class Populating:
    """Vehicles put on a built road one by one, the lanes that end marked by an obstacle."""

    def __init__(self, layout: Layout, rng: Any) -> None:
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

    def scene(self, names: tuple[str, ...]) -> Scene:
        return Scene(self.road, self.layout, self.ids, [self.egos[name] for name in names])


MAIN: RoadId = ("a", "b")
"""The corridors' motorway."""


def _platoon(
    rng: Any, scene: SceneOptions, lanes: int, names: tuple[str, ...]
) -> list[tuple[str | None, float, float]]:
    """(ego name or None for a human, centre, speed) along the motorway, as on ``cf``:
    `vehicles_behind` humans, then each ego followed by its share of the others."""
    column = Column(rng, scene.vehicles_density, lanes, MOTORWAY_SPEED)
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


def merge_scene(
    geometry: Geometry,
    ramp_vehicles: int,
    scene: SceneOptions,
    rng: Any,
    names: tuple[str, ...],
) -> Scene:
    """The ramp starts beside the egos' place in the motorway's traffic; the egos, then up to
    `ramp_vehicles` humans, one after another on the ramp (and on to its acceleration lane)."""
    lanes, ramp = geometry.main_lanes, geometry.ramp_length
    acceleration = geometry.acceleration_lane
    main = Column(rng, scene.vehicles_density, lanes, MOTORWAY_SPEED)
    behind = [main.next() for _ in range(scene.vehicles_behind)]
    anchor, _ = main.next()
    half = Vehicle.LENGTH / 2
    column = Column(rng, scene.vehicles_density, 1, RAMP_SPEED, start=half)
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
    layout = merge_layout(lanes, ramp, acceleration, anchor - half)
    populating = Populating(layout, rng)

    def along_ramp(x: float) -> tuple[LaneIndex, float]:
        return (("ramp", "a", 0), x) if x < ramp else ((*MAIN, lanes), x - ramp)

    wish = MOTORWAY_SPEED / RAMP_SPEED  # the same share of the motorway's limit, once on it
    for x, speed in behind:
        populating.human(MAIN, range(lanes), x, speed)
    for name, (x, speed) in zip(names, egos, strict=True):
        populating.add(*along_ramp(x), speed, name, wish=speed * wish)
    for x, speed in on_ramp:
        populating.add(*along_ramp(x), speed, wish=speed * wish)
    for x, speed in ahead:
        populating.human(MAIN, range(lanes), x, speed)
    return populating.scene(names)


def exit_scene(
    geometry: Geometry, ego_lane: int, scene: SceneOptions, rng: Any, names: tuple[str, ...]
) -> Scene:
    """The off-ramp leaves ``exit_distance`` m after the frontmost ego's front."""
    lanes = geometry.main_lanes
    slots = _platoon(rng, scene, lanes, names)
    diverge = _anchor(slots) + geometry.exit_distance
    layout = exit_layout(lanes, diverge, geometry.deceleration_lane)
    return _populate(layout, rng, slots, lanes, ego_lane, names)


def lane_drop_scene(
    geometry: Geometry, ego_lane: int, scene: SceneOptions, rng: Any, names: tuple[str, ...]
) -> Scene:
    """The lane ends ``drop_distance`` m after the frontmost ego's front."""
    slots = _platoon(rng, scene, LANE_DROP_LANES, names)
    dropped = 0 if geometry.dropped_lane == "left" else LANE_DROP_LANES - 1
    layout = lane_drop_layout(dropped, _anchor(slots) + geometry.drop_distance)
    return _populate(layout, rng, slots, LANE_DROP_LANES, ego_lane, names)


def _anchor(slots: list[tuple[str | None, float, float]]) -> float:
    """Where the frontmost ego's front starts (m along the motorway): every ego has at least
    the drawn distance to the exit or the drop."""
    return max(x for name, x, _ in slots if name is not None) + Vehicle.LENGTH / 2


def _populate(
    layout: Layout,
    rng: Any,
    slots: list[tuple[str | None, float, float]],
    lanes: int,
    ego_lane: int,
    names: tuple[str, ...],
) -> Scene:
    """The `_platoon`'s vehicles on the motorway's first `lanes` lanes: each human on a random
    one, each ego on `ego_lane` (`_ego_lane`)."""
    populating = Populating(layout, rng)
    for name, x, speed in slots:
        if name is None:
            populating.human(MAIN, range(lanes), x, speed)
        else:
            populating.add((*MAIN, _ego_lane(rng, ego_lane, lanes)), x, speed, name)
    return populating.scene(names)
