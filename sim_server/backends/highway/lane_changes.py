"""An ego's lane changes on highway-env: refused or begun, then completed or aborted.

A requested change is judged by the common rules (`rules.lane_change_refusal`), its gap by
MOBIL's safety criterion in both directions (`_safe`); a change begun steers highway-env's
lateral controller to the next lane (`start_lane_change`), and is complete once the ego is within
`LANE_CHANGE_TOLERANCE` of that lane's centre (`lane_change_progress`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from highway_env.vehicle.behavior import IDMVehicle

from sim_server.backends.highway.egos import Episode
from sim_server.backends.highway.road import LaneIndex
from sim_server.backends.highway.simulation import around
from sim_server.backends.rules import LaneChangeUnderWay, lane_change_refusal

LANE_CHANGE_TOLERANCE = 0.1
"""A lane change is complete when the ego is within this lateral distance (m) of the target
lane's centre (highway-env's lateral controller converges exponentially, never exactly)."""

_REFERENCE_IDM = IDMVehicle(None, np.zeros(2))
"""IDM parameters for safety checks of a vehicle that is not itself an IDM vehicle (the ego)."""


def refusal(
    episode: Episode, ego: Any, under_way: LaneChangeUnderWay | None, direction: int
) -> str:
    """Why `ego`'s change towards `direction` is refused ("" if it is not)."""
    _from, _to, index = ego.lane_index

    def ego_lane() -> tuple[int, int]:
        lanes = episode.layout.lanes_at(ego.lane_index, ego.position)
        return sum(j > index for j in lanes), len(lanes)  # highway-env counts from the left

    return lane_change_refusal(
        direction,
        simulator_drives=episode.options.simulator_drives,
        under_way=under_way,
        ego_lane=ego_lane,
        gap_ok=lambda towards: _safe(episode, ego, (_from, _to, index - towards)),
    )


def start_lane_change(episode: Episode, ego: Any, direction: int) -> LaneChangeUnderWay:
    """Steer `ego` one lane towards `direction` (not refused)."""
    _from, _to, index = ego.lane_index
    target = index - direction  # protocol +1 (left) is highway-env index - 1
    ego.target_lane_index = (_from, _to, target)
    return LaneChangeUnderWay(target, direction, episode.time)


def _safe(episode: Episode, ego: Any, lane_index: LaneIndex) -> bool:
    """MOBIL's safety criterion for `ego` moving to `lane_index` (both directions)."""
    front, rear = around(episode, ego, lane_index)
    limit = IDMVehicle.LANE_CHANGE_MAX_BRAKING_IMPOSED
    if rear is not None:
        model = rear if isinstance(rear, IDMVehicle) else _REFERENCE_IDM
        if model.acceleration(ego_vehicle=rear, front_vehicle=ego) < -limit:
            return False
    return (
        front is None or _REFERENCE_IDM.acceleration(ego_vehicle=ego, front_vehicle=front) >= -limit
    )


def lane_change_progress(
    episode: Episode, ego: Any, change: LaneChangeUnderWay
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
