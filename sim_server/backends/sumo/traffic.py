"""Every vehicle of the simulation but the egos, as the columns of `protocol.messages.Traffic`.

What a calibration needs of the scenario's own drivers: each vehicle's odometer, speed,
acceleration and its leader with the net gap to it. SUMO's leader distance excludes the
follower's minGap; it is added back, as for the ego's neighbours.
"""

from __future__ import annotations

import math
from collections.abc import Container
from typing import Any

from protocol.messages import Traffic

MAX_VEHICLES = 1024
"""The protocol's longest array: beyond it, the vehicles nearest the start of the list."""


def observe_traffic(
    api: Any, egos: Container[str], sensor_range: float, min_gaps: dict[str, float]
) -> Traffic:
    """The state of every vehicle but the `egos` (their ids: one, or every ego of a multi-ego
    episode); `min_gaps` caches each vehicle's minGap."""
    vehicle = api.vehicle
    ids = [v for v in vehicle.getIDList() if v not in egos][:MAX_VEHICLES]
    speeds = [vehicle.getSpeed(v) for v in ids]
    speed_of = dict(zip(ids, speeds, strict=True))
    leaders, gaps, leader_speeds = [], [], []
    for v in ids:
        found = vehicle.getLeader(v, sensor_range)
        gap = math.inf
        if found and found[0]:
            other, distance = found
            min_gap = min_gaps.get(v)
            if min_gap is None:
                min_gap = min_gaps[v] = vehicle.getMinGap(v)
            gap = distance + min_gap
        if gap <= sensor_range:
            known = speed_of.get(other)
            leaders.append(other)
            gaps.append(gap)
            leader_speeds.append(vehicle.getSpeed(other) if known is None else known)
        else:
            leaders.append("")
            gaps.append(sensor_range)
            leader_speeds.append(0.0)
    return Traffic(
        id=tuple(ids),
        vehicle_type=tuple(vehicle.getTypeID(v) for v in ids),
        lane=tuple(vehicle.getLaneIndex(v) for v in ids),
        position=tuple(vehicle.getDistance(v) for v in ids),
        speed=tuple(speeds),
        acceleration=tuple(vehicle.getAcceleration(v) for v in ids),
        leader=tuple(leaders),
        gap=tuple(gaps),
        leader_speed=tuple(leader_speeds),
    )
