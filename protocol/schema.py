"""The flat observation vector: every field's name, unit, meaning and order.

The server announces `OBSERVATION_FIELDS` in its `Welcome` (to a client older than 1.6, the
fields of its version: `fields_for`); a client turns each named `Observation` into a vector in
exactly that order with `Flattener`. Absent neighbours contribute ``present = 0``, ``gap = sensor
range``, ``lateral = 0`` and ``speed = 0``; an observation without `road` (an older server's) the
open road: every lane leads on (`road_ahead`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from operator import attrgetter

from protocol.messages import FieldSpec, Observation, SignalState, road_ahead
from protocol.version import ROAD_VERSION, SIGNAL_VERSION, STOP_LINE_VERSION

NEIGHBOUR_SLOTS: tuple[str, ...] = (
    "left_leader",
    "left_follower",
    "leader",
    "follower",
    "right_leader",
    "right_follower",
)
"""The six neighbours of the paper's Fig. 11, in vector order."""

_SLOT_MEANING = {
    "left_leader": "nearest vehicle ahead in the lane to the left",
    "left_follower": "nearest vehicle behind in the lane to the left",
    "leader": "nearest vehicle ahead in the ego's lane",
    "follower": "nearest vehicle behind in the ego's lane",
    "right_leader": "nearest vehicle ahead in the lane to the right",
    "right_follower": "nearest vehicle behind in the lane to the right",
}

Getter = Callable[[Observation], float]


def _neighbour_fields() -> list[tuple[FieldSpec, Getter]]:
    fields: list[tuple[FieldSpec, Getter]] = []
    for slot in NEIGHBOUR_SLOTS:
        meaning = _SLOT_MEANING[slot]
        specs = (
            FieldSpec(f"{slot}_present", "1", f"1 if there is a {meaning} within sensor range"),
            FieldSpec(f"{slot}_gap", "m", f"net bumper-to-bumper gap to the {meaning}"),
            FieldSpec(f"{slot}_lateral", "m", f"lateral offset of the {meaning} (left +)"),
            FieldSpec(f"{slot}_speed", "m/s", f"speed of the {meaning}"),
        )
        for spec, part in zip(specs, ("present", "gap", "lateral", "speed"), strict=True):
            fields.append((spec, attrgetter(f"neighbours.{slot}.{part}")))
    return fields


def _leader_speed_diff(obs: Observation) -> float:
    leader = obs.neighbours.leader
    return obs.ego.speed - leader.speed if leader.present else 0.0


_ROAD_FIELDS: list[tuple[FieldSpec, Getter]] = [
    (
        FieldSpec("lane_end", "m", "distance the ego can drive on in its lane along its route"),
        lambda o: road_ahead(o).lane_end,
    ),
    (
        FieldSpec(
            "lanes_to_change", "1", "lanes to cross to a lane that leads on (left +, right -)"
        ),
        lambda o: road_ahead(o).lanes_to_change,
    ),
    (
        FieldSpec("left_lane_end", "m", "lane_end of the lane to the left (0: no lane)"),
        lambda o: road_ahead(o).left_lane_end,
    ),
    (
        FieldSpec("right_lane_end", "m", "lane_end of the lane to the right (0: no lane)"),
        lambda o: road_ahead(o).right_lane_end,
    ),
]
"""The road ahead (since 1.6), after the 32 fields of 1.0."""

_STOP_LINE_FIELDS: list[tuple[FieldSpec, Getter]] = [
    (
        FieldSpec("stop_line", "m", "distance to where the ego must stop now at a junction"),
        lambda o: road_ahead(o).stop_line,
    ),
]
"""The stop line (since 1.7), after the road's four fields."""

SIGNAL_CODES: dict[str, float] = {
    SignalState.NONE: 0.0,
    SignalState.OFF: 0.0,
    SignalState.GREEN: 1.0,
    SignalState.YELLOW: 2.0,
    SignalState.RED: 3.0,
}
"""`Road.signal_state` in the flat vector: 0 no light (or one that is off), 1 green, 2 yellow,
3 red (a state a newer server adds reads as 0)."""

_SIGNAL_FIELDS: list[tuple[FieldSpec, Getter]] = [
    (
        FieldSpec("signal_distance", "m", "distance to the stop line of the next traffic light"),
        lambda o: road_ahead(o).signal_distance,
    ),
    (
        FieldSpec("signal_state", "1", "its state: 0 none or off, 1 green, 2 yellow, 3 red"),
        lambda o: SIGNAL_CODES.get(road_ahead(o).signal_state, 0.0),
    ),
    (
        FieldSpec("signal_switch", "s", "seconds until that state changes (0: no light)"),
        lambda o: road_ahead(o).signal_switch,
    ),
]
"""The next traffic light (since 1.8), after the stop line."""

_FIELDS: list[tuple[FieldSpec, Getter]] = [
    (FieldSpec("time", "s", "simulation time"), lambda o: o.time),
    (FieldSpec("ego_speed", "m/s", "speed of the ego"), lambda o: o.ego.speed),
    (
        FieldSpec("ego_acceleration", "m/s^2", "acceleration of the ego over the last step"),
        lambda o: o.ego.acceleration,
    ),
    (FieldSpec("ego_lane", "1", "lane index of the ego, 0 = rightmost"), lambda o: o.ego.lane),
    (FieldSpec("ego_lane_count", "1", "number of lanes of the road"), lambda o: o.ego.lane_count),
    (
        FieldSpec("ego_position", "m", "distance of the ego's front from the start of the road"),
        lambda o: o.ego.position,
    ),
    (FieldSpec("speed_limit", "m/s", "speed limit at the ego"), lambda o: o.ego.speed_limit),
    (
        FieldSpec(
            "leader_speed_diff", "m/s", "ego speed minus leader speed (0 when there is no leader)"
        ),
        _leader_speed_diff,
    ),
    *_neighbour_fields(),
    *_ROAD_FIELDS,
    *_STOP_LINE_FIELDS,
    *_SIGNAL_FIELDS,
]

OBSERVATION_FIELDS: tuple[FieldSpec, ...] = tuple(spec for spec, _ in _FIELDS)
"""The canonical flat vector, in order."""

_BEFORE_SIGNAL = len(OBSERVATION_FIELDS) - len(_SIGNAL_FIELDS)
_BEFORE_STOP_LINE = _BEFORE_SIGNAL - len(_STOP_LINE_FIELDS)
_BEFORE_ROAD = _BEFORE_STOP_LINE - len(_ROAD_FIELDS)


def fields_for(version: tuple[int, int]) -> tuple[FieldSpec, ...]:
    """The flat vector a client of protocol `version` knows (a client refuses a field it does
    not know): the 32 fields of 1.0 before 1.6, then the road's four too, from 1.7 the stop
    line, from 1.8 the next traffic light's three."""
    if version >= SIGNAL_VERSION:
        return OBSERVATION_FIELDS
    if version >= STOP_LINE_VERSION:
        return OBSERVATION_FIELDS[:_BEFORE_SIGNAL]
    if version >= ROAD_VERSION:
        return OBSERVATION_FIELDS[:_BEFORE_STOP_LINE]
    return OBSERVATION_FIELDS[:_BEFORE_ROAD]


_GETTERS: dict[str, Getter] = {spec.name: getter for spec, getter in _FIELDS}


class Flattener:
    """Turns named observations into flat vectors in the order of a schema."""

    def __init__(self, fields: Sequence[FieldSpec] = OBSERVATION_FIELDS) -> None:
        unknown = [f.name for f in fields if f.name not in _GETTERS]
        if unknown:
            raise ValueError(
                f"observation schema has fields this protocol does not know: {unknown}"
            )
        self.names: tuple[str, ...] = tuple(f.name for f in fields)
        self._getters = [_GETTERS[name] for name in self.names]

    def __call__(self, obs: Observation) -> list[float]:
        return [float(get(obs)) for get in self._getters]

    def index(self, name: str) -> int:
        """Position of a named field in the vector."""
        return self.names.index(name)
