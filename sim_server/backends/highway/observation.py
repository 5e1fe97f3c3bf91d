"""An ego's observation on highway-env: its own state, its six neighbours and the road ahead.

The neighbours are highway-env's ``neighbour_vehicles`` on the ego's lane and the lanes beside it
(`simulation.around`), other egos included, measured along the ego's lane and reported within the
sensor range; the lanes beside it are those of its road whose stretch covers it
(`Layout.lanes_at`), and the road ahead is read off the route (`Layout.road_ahead`).
"""

from __future__ import annotations

from typing import Any

from protocol.messages import (
    AppliedAction,
    Ego,
    Events,
    Neighbour,
    Neighbours,
    Observation,
)
from sim_server.backends.highway.egos import Episode
from sim_server.backends.highway.simulation import around
from sim_server.backends.rules import LaneChangeUnderWay


class Observer:
    """Observes egos with the backend's `sensor_range`."""

    def __init__(self, sensor_range: float) -> None:
        self.sensor_range = sensor_range
        self.absent = Neighbour(False, sensor_range, 0.0, 0.0, "")

    def observe(
        self,
        episode: Episode,
        ego: Any,
        change: LaneChangeUnderWay | None,
        seq: int,
        events: Events,
        action: AppliedAction,
    ) -> Observation:
        """`ego`'s observation: its own state, its six neighbours (other egos included) and the
        road ahead, among the lanes of its road beside it (`Layout.lanes_at`)."""
        layout = episode.layout
        _from, _to, index = ego.lane_index
        lane = layout.network.get_lane(ego.lane_index)
        s, lat = lane.local_coordinates(ego.position)
        lanes = layout.lanes_at(ego.lane_index, ego.position)
        slots: dict[str, Neighbour] = {}
        for name, offset in (("left_", -1), ("", 0), ("right_", 1)):
            other = index + offset
            if other not in lanes:
                slots[f"{name}leader"] = slots[f"{name}follower"] = self.absent
                continue
            front, rear = around(episode, ego, (_from, _to, other), own=not offset)
            slots[f"{name}leader"] = self._neighbour(episode, ego, lane, s, lat, front, True)
            slots[f"{name}follower"] = self._neighbour(episode, ego, lane, s, lat, rear, False)
        return Observation(
            seq=seq,
            time=episode.time,
            ego=Ego(
                speed=float(ego.speed),
                acceleration=float(ego.action["acceleration"]),
                lane=sum(j > index for j in lanes),  # highway-env counts from the left
                lane_count=len(lanes),
                position=min(layout.along(ego), layout.length),
                speed_limit=float(lane.speed_limit),
                changing_lane=0 if change is None else change.direction,
            ),
            neighbours=Neighbours(**slots),
            events=events,
            action=action,
            road=layout.road_ahead(ego, lanes),
        )

    def _neighbour(
        self,
        episode: Episode,
        ego: Any,
        lane: Any,
        s: float,
        lat: float,
        other: Any,
        ahead: bool,
    ) -> Neighbour:
        if other is None:
            return self.absent
        other_s, other_lat = lane.local_coordinates(other.position)
        half_lengths = (other.LENGTH + ego.LENGTH) / 2
        gap = (other_s - s if ahead else s - other_s) - half_lengths
        if gap > self.sensor_range:
            return self.absent
        lateral = lat - other_lat  # highway-env's lateral axis points right
        return Neighbour(True, float(gap), float(lateral), float(other.speed), episode.ids[other])
