"""The roads, built with highway-env's own API: the straight road of ``cf`` and ``cflc``, and the
corridors ``merge``, ``exit`` and ``lanedrop`` as one seed draws them (`Geometry`).

Each is highway-env's network with the egos' route through it (`road.Layout`): the straight road
as ``RoadNetwork.straight_road_network``; the on-ramp as ``MergeEnv._make_road`` and the exit as
``ExitEnv._create_road`` build theirs; the lane drop, which highway-env has no scene for, as its
straight road with one lane cut short. The lengths of the SUMO corridors are used where both
have one (`sumo.corridors`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from highway_env.road.lane import CircularLane, LineType, SineLane, StraightLane
from highway_env.road.road import RoadNetwork

from sim_server.backends.highway.road import Layout
from sim_server.backends.sumo.corridors import DOWNSTREAM, MOTORWAY_SPEED, RAMP_SPEED

LANE_WIDTH = StraightLane.DEFAULT_WIDTH
"""highway-env's lane width (m)."""
RAMP_OFFSET = 6.5
"""Metres between the start of an on-ramp and the acceleration lane it leads into, sideways (its
``SineLane`` converges over the whole ramp; ``MergeEnv``'s converges by the same 6.5 m)."""
OFF_RAMP = 250.0
"""Length of the exit's off-ramp (m), as the SUMO corridor's."""
OFF_RAMP_RADIUS = 500.0
"""Radius of the off-ramp's arc (m): it bends away to the right, as ``ExitEnv``'s does."""
LANE_DROP_LANES = 3
"""Lanes of ``lanedrop`` before the drop."""


@dataclass(frozen=True, slots=True)
class Geometry:
    """A corridor as one seed draws it, in the options' names (m); what a kind lacks is 0."""

    main_lanes: int
    """Lanes of the motorway (``lanedrop``: before the drop)."""
    ramp_length: float = 0.0
    acceleration_lane: float = 0.0
    exit_distance: float = 0.0
    deceleration_lane: float = 0.0
    drop_distance: float = 0.0
    dropped_lane: str = ""
    """``lanedrop``: ``left`` or ``right``."""


def straight_layout(lanes: int, length: float, speed_limit: float) -> Layout:
    """highway-env's straight road (``straight_road_network``): every lane leads on."""
    network = RoadNetwork.straight_road_network(lanes, length=length, speed_limit=speed_limit)
    road = ("0", "1")
    return Layout.of(network, (road,), frozenset({road}))


def merge_layout(lanes: int, ramp: float, acceleration: float, ramp_start: float) -> Layout:
    """``MergeEnv._make_road``'s road, the ego's way: the motorway (``a`` to ``b``, `lanes`
    lanes from x = 0) with an acceleration lane on its right (its last lane, from the ramp's end
    for `acceleration` m), and the ramp (``ramp`` to ``a``: a `SineLane` from `ramp_start`,
    converging by `RAMP_OFFSET`) that leads into it; the motorway goes on `DOWNSTREAM` m after."""
    merge = ramp_start + ramp
    network = RoadNetwork.straight_road_network(
        lanes, length=merge + acceleration + DOWNSTREAM, speed_limit=MOTORWAY_SPEED,
        nodes_str=("a", "b"),
    )  # fmt: skip
    y = lanes * LANE_WIDTH
    c, n = LineType.CONTINUOUS_LINE, LineType.NONE
    network.add_lane(
        "a", "b",
        StraightLane([merge, y], [merge + acceleration, y], line_types=(n, c), forbidden=True,
                     speed_limit=MOTORWAY_SPEED),
    )  # fmt: skip
    amplitude = RAMP_OFFSET / 2
    network.add_lane(
        "ramp", "a",
        SineLane([ramp_start, y + amplitude], [merge, y + amplitude], amplitude, np.pi / ramp,
                 np.pi / 2, line_types=(c, c), forbidden=True, speed_limit=RAMP_SPEED),
    )  # fmt: skip
    return Layout.of(network, (("ramp", "a"), ("a", "b")), frozenset({("a", "b")}))


def exit_layout(lanes: int, diverge: float, deceleration: float) -> Layout:
    """``ExitEnv._create_road``'s road, the ego's way: the motorway (``a`` to ``b``, `lanes`
    lanes from x = 0 to `DOWNSTREAM` m after the diverge at x = `diverge`), a deceleration lane on
    its right (its last lane, `deceleration` m up to the diverge), and the off-ramp it leads into
    (``b`` to ``exit``: a `CircularLane` bending right, `OFF_RAMP` m), the egos' way out."""
    network = RoadNetwork.straight_road_network(
        lanes, length=diverge + DOWNSTREAM, speed_limit=MOTORWAY_SPEED, nodes_str=("a", "b")
    )
    y = lanes * LANE_WIDTH
    s, c = LineType.STRIPED, LineType.CONTINUOUS_LINE
    network.add_lane(
        "a", "b",
        StraightLane([diverge - deceleration, y], [diverge, y], line_types=(s, c),
                     speed_limit=MOTORWAY_SPEED),
    )  # fmt: skip
    bend = -np.pi / 2
    network.add_lane(
        "b", "exit",
        CircularLane([diverge, y + OFF_RAMP_RADIUS], OFF_RAMP_RADIUS, bend,
                     bend + OFF_RAMP / OFF_RAMP_RADIUS, clockwise=True, line_types=(c, c),
                     forbidden=True, speed_limit=RAMP_SPEED),
    )  # fmt: skip
    return Layout.of(network, (("a", "b"), ("b", "exit")), frozenset({("a", "b"), ("b", "exit")}))


def lane_drop_layout(dropped: int, drop: float) -> Layout:
    """Three lanes (``a`` to ``b``, from x = 0) of which lane `dropped` (0 the left, 2 the right)
    ends at x = `drop`, the others `DOWNSTREAM` m later; highway-env has no lane-drop scene, so
    this is its straight road with one lane cut short."""
    network = RoadNetwork()
    last = LANE_DROP_LANES - 1
    for i in range(LANE_DROP_LANES):
        end = drop if i == dropped else drop + DOWNSTREAM
        lines = (
            LineType.CONTINUOUS_LINE if i == 0 else LineType.STRIPED,
            LineType.CONTINUOUS_LINE if i == last else LineType.NONE,
        )
        network.add_lane(
            "a", "b",
            StraightLane([0.0, i * LANE_WIDTH], [end, i * LANE_WIDTH], line_types=lines,
                         forbidden=i == dropped, speed_limit=MOTORWAY_SPEED),
        )  # fmt: skip
    return Layout.of(network, (("a", "b"),), frozenset({("a", "b")}))
