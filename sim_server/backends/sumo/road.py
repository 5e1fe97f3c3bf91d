"""The road ahead of an ego, from what SUMO's own lane-change model plans with.

`vehicle.getBestLanes` gives, for every lane of the ego's edge, how far a vehicle can drive from
the start of that lane and stay on its route (``length``), the signed number of lanes to cross to
the best lane (``offset``, positive to the left), and the lanes it leads into without a change
(``nextLanes``). SUMO counts a lane as going on where its continuation can still reach the route
by changing lanes further down the road; the road ahead takes the shorter of that and the lanes
it leads into, so that the distances are those within which a change must have happened: the end
of an acceleration lane (seen from its ramp too), a lane drop, a lane that does not lead to the
exit. The lanes that go on farthest lead to the end of the route (or beyond SUMO's look-ahead of
at least 3 km): they are reported at `ROAD_RANGE`.

On a junction (an internal lane) SUMO reports only the lane the ego leads into: the road there is
the one of the lane it came from, carried on by the distance driven (`carried`).

The stop line (`stop_line`, protocol 1.7) is SUMO's own right of way at the next junction:
`vehicle.getNextLinks` gives, for each junction along the ego's route, its link's state (a
light's colour, major or minor road) and whether it is open to the ego now (SUMO's
`MSLink::opened`, given the foes that approach with priority: what its own drivers give way by).

Source: SUMO docs, TraCI "Vehicle Value Retrieval" (best lanes, 0xb2; next links, 0x33);
src/microsim/MSVehicle.cpp (`updateBestLanes`), src/libsumo/Vehicle.cpp (`getNextLinks`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from protocol.messages import ROAD_RANGE, Road

LONGEST_TOLERANCE = 1.0
"""Metres within which a lane counts as going on as far as the longest of its edge (the lanes of
one edge share its length; their junction lanes may differ a little)."""

_LENGTH, _OFFSET, _NEXT = 1, 3, 5
"""Positions in a best-lanes entry: (lane id, length, occupation, offset, allows continuation,
next lanes)."""

_OPEN, _STATE = 2, 5
"""Positions in a next-links entry: (lane, has priority, is open, has foe, via lane, state,
direction, length)."""
CLOSED_STATES = frozenset("ru")
"""Link states that close the way whatever the foes: red, red-yellow."""
YELLOW = "y"
YELLOW_DECELERATION = 3.0
"""m/s²: a yellow light closes the way to an ego that can stop before it braking no harder
(a firm, normal braking); one that cannot drives on, as drivers do."""


def road_ahead(
    best_lanes: Any, lane_id: str, lane_position: float, length_of: Callable[[str], float]
) -> Road | None:
    """The `Road` of an ego at `lane_position` on `lane_id`, from its `best_lanes` (and
    `length_of` a lane); None on a junction's internal lane, for which SUMO reports only the
    lane it leads into (`carried`)."""
    entries = {entry[0]: entry for entry in best_lanes}
    mine = entries.get(lane_id)
    if mine is None:
        return None
    longest = max(entry[_LENGTH] for entry in best_lanes) - LONGEST_TOLERANCE

    def end(entry: Any) -> float:
        # SUMO's length lets changes further down the road count: on a ramp's single lane, the
        # whole route. The lanes it leads into without a change may end sooner.
        following = sum(length_of(lane) for lane in entry[_NEXT])
        length = min(entry[_LENGTH], following) if following else entry[_LENGTH]
        if length >= longest:
            return ROAD_RANGE
        return min(ROAD_RANGE, max(0.0, length - lane_position))

    edge, _, index = lane_id.rpartition("_")
    lane = int(index)
    left = entries.get(f"{edge}_{lane + 1}")
    right = entries.get(f"{edge}_{lane - 1}") if lane > 0 else None
    return Road(
        end(mine),
        int(mine[_OFFSET]),
        end(left) if left is not None else 0.0,
        end(right) if right is not None else 0.0,
    )


def carried(previous: Road | None, driven: float, lane: int, lane_count: int) -> Road:
    """The road on a junction: the one of the lane the ego came from, `driven` metres on, as
    far as the junction's lanes allow (`lane` of `lane_count`)."""
    if previous is None:
        return Road(ROAD_RANGE, 0, 0.0, 0.0)

    def on(distance: float) -> float:
        return distance if distance >= ROAD_RANGE else max(0.0, distance - driven)

    change = min(max(previous.lanes_to_change, -lane), lane_count - 1 - lane)
    return Road(
        on(previous.lane_end),
        change,
        on(previous.left_lane_end) if lane < lane_count - 1 else 0.0,
        on(previous.right_lane_end) if lane > 0 else 0.0,
    )


def stop_line(next_links: Any, to_junction: float, speed: float) -> float:
    """Metres to where the ego must stop now: the end of its lane (`to_junction` m ahead) when
    the link to the next junction on its route (the first of `next_links`) is closed to it, else
    `ROAD_RANGE`. Closed: red or red-yellow, yellow where stopping needs no more than
    `YELLOW_DECELERATION`, or not open by SUMO's right of way (foes with priority approach, a
    stop sign not yet stopped at). No links (a lane that ends, the end of the route): none."""
    if not next_links or to_junction >= ROAD_RANGE:
        return ROAD_RANGE
    link = next_links[0]
    state = link[_STATE]
    room = max(to_junction, 0.0)
    if state == YELLOW:
        closed = speed * speed <= 2.0 * YELLOW_DECELERATION * room
    else:
        closed = state in CLOSED_STATES or not link[_OPEN]
    return room if closed else ROAD_RANGE
