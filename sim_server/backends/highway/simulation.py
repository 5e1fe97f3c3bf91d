"""One simulation step of a highway episode and what it decides.

highway-env's gym ``step`` is not used: a step is ``road.act()`` and ``road.step(dt)``, the two
calls of ``AbstractEnv._simulate`` (`advance`), then the humans that arrived at the end of their
road leave it, and so does a human that has stood at the end of a lane that ends for
``lane_end_patience`` seconds. After a step, `outcome` says what ends an ego's drive.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from highway_env.vehicle.behavior import IDMVehicle

from protocol.messages import EndReason
from sim_server.backends.highway.egos import Episode
from sim_server.backends.highway.road import LaneIndex
from sim_server.backends.highway.scene import DT


def advance(episode: Episode) -> None:
    """One simulation step: highway-env's ``road.act()`` and ``road.step(dt)``, arrivals."""
    road = episode.road
    road.act()
    road.step(DT)
    episode.steps += 1
    layout = episode.layout
    egos = episode.egos()
    arrived = [v for v in road.vehicles if all(v is not ego for ego in egos) and layout.arrived(v)]
    for vehicle in arrived:
        road.vehicles.remove(vehicle)
        if vehicle is episode.leader:
            episode.leader_arrival = episode.time
            episode.leader_end = layout.end_of(vehicle.lane_index[:2])
    if layout.dead_ends:
        _clear_lane_ends(episode, egos)


def _clear_lane_ends(episode: Episode, egos: list[Any]) -> None:
    """A human that has stood at the end of a lane that ends for ``lane_end_patience`` seconds
    leaves the road (as an ego's drive ends there with ``lane_end``): highway-env's MOBIL never
    changes lanes below 1 m/s, so it would block that lane for good."""
    stranded_since, now = episode.stranded, episode.time
    patience = episode.options.lane_end_patience
    for vehicle in list(episode.road.vehicles):
        if any(vehicle is ego for ego in egos) or not stranded(episode, vehicle):
            stranded_since.pop(vehicle, None)
        elif now - stranded_since.setdefault(vehicle, now) >= patience - 1e-9:
            episode.road.vehicles.remove(vehicle)
            del stranded_since[vehicle]


def stranded(episode: Episode, human: Any) -> bool:
    """`human` stands at the end of a lane that ends: MOBIL changes lanes only at 1 m/s or
    faster, so it stays there for good."""
    layout = episode.layout
    return (
        human.speed < 1.0
        and layout.leads_to_dead_end(human.lane_index)
        and layout.to_end(human) < 2 * IDMVehicle.DISTANCE_WANTED
    )


def outcome(episode: Episode, ego: Any) -> str:
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


def collided_with(episode: Episode, ego: Any) -> Any:
    """highway-env flags both vehicles of a crash: the nearest crashed one is the other."""
    crashed = [v for v in episode.road.vehicles if v is not ego and v.crashed]
    if not crashed:
        return None
    return min(crashed, key=lambda v: float(np.linalg.norm(v.position - ego.position)))


def around(episode: Episode, ego: Any, index: LaneIndex, own: bool = False) -> tuple[Any, Any]:
    """highway-env's ``neighbour_vehicles`` of `ego` on lane `index` (its leader, its follower),
    without the obstacles that mark the lane ends (the road ahead reports those); on its `own`
    lane also across the joins of its route, which highway-env does not look across: the leader
    on the lane it leads into, the follower on the lane it came from."""
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
