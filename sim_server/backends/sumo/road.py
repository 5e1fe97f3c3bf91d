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

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from protocol.messages import ROAD_RANGE, Road

LONGEST_TOLERANCE = 1.0
"""Metres within which a lane counts as going on as far as the longest of its edge (the lanes of
one edge share its length; their junction lanes may differ a little)."""

_LENGTH, _OFFSET, _NEXT = 1, 3, 5
"""Positions in a best-lanes entry: (lane id, length, occupation, offset, allows continuation,
next lanes)."""

_PRIORITY, _OPEN, _VIA, _STATE = 1, 2, 4, 5
"""Positions in a next-links entry: (lane, has priority, is open, has foe, via lane, state,
direction, length)."""
MINOR_TIME_GAP = 1.0
"""s: how long before a foe with priority reaches the conflict point the ego must have left it
(SUMO's default ``jmTimegapMinor``)."""
CLEARING_ACCELERATION = 1.5
"""m/s²: the acceleration the ego is assumed to leave the junction with (IDM's a): SUMO's own
check of a link assumes the lanes' speed, which a standing ego is far from."""
VEHICLE_LENGTH = 5.0
"""m: the ego's length assumed in clearing a conflict point."""
FOE_DECELERATION = 4.0
"""m/s²: the hardest braking the ego's entry may impose on a foe with priority (MOBIL's
b_safe)."""
STANDSTILL_GAP = 2.0
"""m: the gap a foe keeps behind the ego at the least (IDM's s0)."""
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


@dataclass(frozen=True, slots=True)
class Foe:
    """A vehicle with priority at the ego's next junction (`vehicle.getJunctionFoes`)."""

    distance: float
    """m from its front to the conflict point (negative once it has reached it)."""
    exit_distance: float
    """m from its front to where it has left the conflict area (negative: left)."""
    speed: float
    ego_exit_distance: float
    """m from the ego's front to where the ego's front leaves the conflict area."""


def stop_line(
    next_links: Any,
    to_junction: float,
    speed: float,
    speed_limit: float,
    foes: Sequence[Foe] = (),
    yellow_left: float = math.inf,
    limit_before: float = math.inf,
) -> float:
    """Metres to where the ego must stop now: the end of its lane (`to_junction` m ahead) when
    the link to the next junction on its route (the first of `next_links`) is closed to it, else
    `ROAD_RANGE`. Closed: red or red-yellow; yellow where stopping needs no more than
    `YELLOW_DECELERATION`, or where the ego at its speed would not reach the line within the
    `yellow_left` seconds before it turns red (no faster than `limit_before`, the lowest speed
    limit on its way to the line: then it must stop, braking harder); not open by
    SUMO's right of way (foes with priority approach, a stop sign not yet stopped at), or too
    close a foe (`foes`) for the ego to leave the conflict point from its speed at
    `CLEARING_ACCELERATION` (`too_close`). No links (a lane that ends, the end of the route):
    none."""
    if not next_links or to_junction >= ROAD_RANGE:
        return ROAD_RANGE
    link = next_links[0]
    state = link[_STATE]
    room = max(to_junction, 0.0)
    if state == YELLOW:
        can_stop = speed * speed <= 2.0 * YELLOW_DECELERATION * room
        closed = can_stop or room > min(speed, limit_before) * yellow_left
    else:
        closed = state in CLOSED_STATES or not link[_OPEN] or too_close(foes, speed, speed_limit)
    return room if closed else ROAD_RANGE


def yields_at(next_links: Any) -> str:
    """The junction lane of the next link when the ego must give way there (a minor link SUMO
    judges open now: its foes are worth a closer look), else ""."""
    if not next_links:
        return ""
    link = next_links[0]
    return "" if link[_PRIORITY] or not link[_OPEN] else str(link[_VIA])


def too_close(foes: Sequence[Foe], speed: float, speed_limit: float) -> bool:
    """A foe would come too close once the ego has left the conflict point (its rear there): the
    foe then closes in until, braking at `FOE_DECELERATION` while the ego accelerates at
    `CLEARING_ACCELERATION`, it is down to the ego's speed, and must still keep the ego's
    `MINOR_TIME_GAP` and `STANDSTILL_GAP` (it follows the ego after a merge)."""
    for foe in foes:
        if foe.exit_distance <= 0.0:
            continue  # gone through
        if foe.distance <= 0.0:
            return True  # in the conflict area now
        to_clear = max(foe.ego_exit_distance + VEHICLE_LENGTH, 0.0)
        clears = time_to_cover(to_clear, speed, speed_limit)
        leaving = min(speed_limit, math.sqrt(speed * speed + 2 * CLEARING_ACCELERATION * to_clear))
        left = foe.distance - foe.speed * clears  # the foe's front from the point by then
        closing = max(foe.speed - leaving, 0.0)
        closes_in = closing * closing / (2 * (FOE_DECELERATION + CLEARING_ACCELERATION))
        if left < closes_in + leaving * MINOR_TIME_GAP + STANDSTILL_GAP:
            return True
    return False


def time_to_cover(distance: float, speed: float, limit: float) -> float:
    """Seconds to drive `distance` m from `speed`, accelerating at `CLEARING_ACCELERATION` up
    to `limit`."""
    a = CLEARING_ACCELERATION
    speed = max(speed, 0.0)
    if speed >= limit:
        return distance / max(speed, 0.1)
    to_limit = (limit - speed) / a
    on_the_way = speed * to_limit + 0.5 * a * to_limit * to_limit
    if on_the_way >= distance:
        return (math.sqrt(speed * speed + 2.0 * a * distance) - speed) / a
    return to_limit + (distance - on_the_way) / limit
