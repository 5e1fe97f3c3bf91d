"""Action and observation spaces of `RemoteEnv`: the encodings third-party learners accept.

The wire always carries one decision: an acceleration in m/s² (within the server's
`ActionSchema` bounds) and a lane change (-1 right, 0 keep, +1 left). What a learner hands to
`step` is one of these encodings of it, chosen with ``RemoteEnv(action_space=...)``:

========================  =================================  ===================================
name                      space                              decoded as
========================  =================================  ===================================
``"box"``                 ``Box(-1, 1, (1,))``               acceleration = low + (u + 1) / 2 ·
                                                             (high - low); lane kept
``"hybrid"``              ``Box(-1, 1, (2,))``               component 0 as ``"box"``; component
                                                             1 selects the lane: below -1/3
                                                             right, above +1/3 left, else keep
``"discrete"``            ``Discrete(K)`` (one lane) or      index i: acceleration level i % K,
                          ``Discrete(3 K)``                  lane (keep, left, right)[i // K]
``"multi_discrete"``      ``MultiDiscrete([K])`` or          [acceleration level, lane choice
                          ``MultiDiscrete([K, 3])``          (keep, left, right)]
``"dict"``                ``Dict(acceleration: Box(low,      acceleration in m/s², lane_change
                          high, (1,)), lane_change:          -1 / 0 / +1 as on the wire
                          Discrete(3, start=-1))``
``"auto"`` (default)      ``"box"`` on a one-lane road,      Stable-Baselines3's TD3 and SAC
                          ``"hybrid"`` with several lanes    take both as they are
========================  =================================  ===================================

The flat boxes are symmetric and normalised, as Stable-Baselines3 and Gymnasium's checker
recommend; the discrete encodings use K acceleration levels evenly spaced over the bounds (7 by
default: every 1.5 m/s² over SUMO's [-6, 3], 0 included). Every encoding also accepts the named
form ``{"acceleration": [a], "lane_change": k}`` (m/s², as `Dict`), so drivers and scripts need
not know which one a learner chose.

Observations are the protocol's flat vector (`protocol.schema`), in SI units. `observation_bounds`
gives each field finite bounds, from what the schema and the server's welcome say about it and,
where they say nothing (the top of speeds, times and distances), from caps no vehicle reaches.
The env clips the vector into them, so an observation is always inside its space; the named
observation in ``info["observation"]`` keeps the raw values.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from gymnasium import spaces

from protocol.messages import ROAD_RANGE, SIGNAL_HORIZON, ActionSchema, FieldSpec
from protocol.schema import SIGNAL_CODES

ACTION_SPACES = ("auto", "box", "hybrid", "discrete", "multi_discrete", "dict")
"""The names `RemoteEnv(action_space=...)` accepts."""
DEFAULT_ACCELERATION_LEVELS = 7
LANE_THRESHOLD = 1.0 / 3.0
"""Where the hybrid encoding's lane component switches from keep to left (and, mirrored, right)."""
LANE_CHOICES = (0, 1, -1)
"""Lane choice index of the discrete encodings -> lane-change command: keep, left, right."""

MAX_SPEED = 100.0
"""m/s (360 km/h): the cap of every speed in the vector, above any road vehicle."""
MAX_LANES = 16
"""The cap of lane indices and counts."""
MAX_TIME = 1.0e6
"""s (11.6 days of simulated time): the cap of the simulation time."""
MAX_DISTANCE = 1.0e6
"""m (1000 km): the cap of the ego's position along its route."""

Action = Any


@dataclass(frozen=True)
class ActionEncoding:
    """One way of writing the (acceleration, lane change) decision as a Gymnasium action."""

    name: str
    space: spaces.Space[Any]
    low: float
    """Acceleration bounds of the server (m/s²)."""
    high: float
    lanes: bool
    """Whether the encoding can ask for a lane change."""
    levels: int = DEFAULT_ACCELERATION_LEVELS

    def decode(self, action: Action) -> tuple[float, int]:
        """(acceleration m/s², lane change -1 / 0 / +1) of one action of this encoding."""
        if isinstance(action, Mapping):
            return decode_named(action)
        if self.name == "dict":  # a bare acceleration in m/s²
            return float(np.asarray(action, dtype=np.float64).reshape(-1)[0]), 0
        if self.name in ("box", "hybrid"):
            u = np.asarray(action, dtype=np.float64).reshape(-1)
            lane = _lane_of(float(u[1])) if self.name == "hybrid" else 0
            return self.to_acceleration(float(u[0])), lane
        if self.name == "discrete":
            index = int(np.asarray(action).reshape(-1)[0])
            return self._level(index % self.levels), LANE_CHOICES[index // self.levels]
        indices = np.asarray(action).reshape(-1)  # multi_discrete
        lane = LANE_CHOICES[int(indices[1])] if self.lanes else 0
        return self._level(int(indices[0])), lane

    def encode(self, acceleration: float, lane_change: int = 0) -> Action:
        """The action of this encoding closest to (acceleration m/s², lane change)."""
        if lane_change not in (-1, 0, 1):
            raise ValueError(f"lane_change must be -1, 0 or 1, got {lane_change}")
        lane_change = lane_change if self.lanes else 0
        if self.name == "dict":
            return {
                "acceleration": np.array([acceleration], np.float32),
                "lane_change": lane_change,
            }
        if self.name in ("box", "hybrid"):
            u = [self.to_policy(acceleration)]
            if self.name == "hybrid":
                u.append(float(lane_change))
            return np.array(u, dtype=np.float32)
        level = self._nearest_level(acceleration)
        lane = LANE_CHOICES.index(lane_change)
        if self.name == "discrete":
            return level + self.levels * lane
        return np.array([level, lane] if self.lanes else [level], dtype=np.int64)

    def decode_batch(self, actions: Any, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Accelerations (n,) m/s² and lane changes (n,) of a batch of `n` actions."""
        if isinstance(actions, Mapping):
            return decode_named_batch(actions, n)
        rows = np.asarray(actions).reshape(n, -1)
        decoded = [self.decode(row) for row in rows]
        return (
            np.array([a for a, _ in decoded], dtype=np.float64),
            np.array([lane for _, lane in decoded], dtype=np.int64),
        )

    def to_acceleration(self, u: float) -> float:
        """[-1, 1] -> m/s² (values outside are clipped)."""
        u = min(1.0, max(-1.0, u))
        return self.low + (u + 1.0) * 0.5 * (self.high - self.low)

    def to_policy(self, acceleration: float) -> float:
        """m/s² -> [-1, 1] (clipped to the bounds)."""
        u = 2.0 * (acceleration - self.low) / (self.high - self.low) - 1.0
        return min(1.0, max(-1.0, u))

    def _level(self, index: int) -> float:
        if not 0 <= index < self.levels:
            raise ValueError(f"acceleration level {index} is not in 0..{self.levels - 1}")
        return float(np.linspace(self.low, self.high, self.levels)[index])

    def _nearest_level(self, acceleration: float) -> int:
        levels = np.linspace(self.low, self.high, self.levels)
        return int(np.abs(levels - acceleration).argmin())


def make_action_encoding(
    name: str, schema: ActionSchema, lanes: bool, levels: int = DEFAULT_ACCELERATION_LEVELS
) -> ActionEncoding:
    """The encoding `name` (one of `ACTION_SPACES`) for the server's acceleration bounds;
    ``"auto"`` is ``"hybrid"`` if `lanes` (the road has several) else ``"box"``."""
    if name not in ACTION_SPACES:
        raise ValueError(f"action_space {name!r} is not one of: {', '.join(ACTION_SPACES)}")
    if levels < 2:
        raise ValueError(f"acceleration_levels must be at least 2, got {levels}")
    low, high = float(schema.acceleration_min), float(schema.acceleration_max)
    if name == "auto":
        name = "hybrid" if lanes else "box"
    space: spaces.Space[Any]
    if name == "box":
        space, lanes = spaces.Box(-1.0, 1.0, (1,), np.float32), False
    elif name == "hybrid":
        space, lanes = spaces.Box(-1.0, 1.0, (2,), np.float32), True
    elif name == "discrete":
        space = spaces.Discrete(levels * (3 if lanes else 1))
    elif name == "multi_discrete":
        space = spaces.MultiDiscrete([levels, 3] if lanes else [levels])
    else:
        acceleration = spaces.Box(low, high, (1,), np.float32)
        space, lanes = spaces.Dict({"acceleration": acceleration, "lane_change": _LANE}), True
    return ActionEncoding(name, space, low, high, lanes, levels)


_LANE: spaces.Discrete = spaces.Discrete(3, start=-1)


def decode_named(action: Mapping[str, Any]) -> tuple[float, int]:
    """(acceleration m/s², lane change) of the named form ``{"acceleration": [a], ...}``."""
    acceleration = float(np.asarray(action["acceleration"], dtype=np.float64).reshape(-1)[0])
    return acceleration, int(action.get("lane_change", 0))


def decode_named_batch(actions: Mapping[str, Any], n: int) -> tuple[np.ndarray, np.ndarray]:
    """Accelerations (n,) m/s² and lane changes (n,) of a batch of the named form."""
    accelerations = np.asarray(actions["acceleration"], dtype=np.float64).reshape(n, -1)
    lanes = np.asarray(actions.get("lane_change", np.zeros(n)), dtype=np.int64)
    return accelerations[:, 0], lanes.reshape(n)


def _lane_of(u: float) -> int:
    if u > LANE_THRESHOLD:
        return 1
    if u < -LANE_THRESHOLD:
        return -1
    return 0


# ----------------------------------------------------------------------- observations


def field_bounds(spec: FieldSpec, sensor_range: float, schema: ActionSchema) -> tuple[float, float]:
    """Finite (low, high) of one field of the flat vector, from its name and unit.

    Neighbour flags are 0 or 1; gaps are at most the sensor range (an absent neighbour reports
    exactly it) and an overlap deeper than it is clipped, still negative; lateral offsets lie
    within the sensor range too; the ego's acceleration within the server's action bounds (every
    command is clipped to them); the road's distances within [0, `ROAD_RANGE`] and the lanes to
    change within ±(`MAX_LANES` - 1); the next light's state code within `SIGNAL_CODES` and
    its seconds to a change within `SIGNAL_HORIZON`; lane indices and counts, speeds, times
    and distances are not negative and capped at `MAX_LANES`, `MAX_SPEED`, `MAX_TIME` and
    `MAX_DISTANCE`.
    """
    name, unit = spec.name, spec.unit
    if name.endswith("_present"):
        return 0.0, 1.0
    if name.endswith(("_gap", "_lateral")):
        return -sensor_range, sensor_range
    if name == "leader_speed_diff":
        return -MAX_SPEED, MAX_SPEED
    if name == "ego_acceleration":
        return float(schema.acceleration_min), float(schema.acceleration_max)
    if name == "ego_lane":
        return 0.0, MAX_LANES - 1.0
    if name == "ego_lane_count":
        return 1.0, float(MAX_LANES)
    if name == "lanes_to_change":
        return 1.0 - MAX_LANES, MAX_LANES - 1.0
    if name.endswith("lane_end") or name in ("stop_line", "signal_distance"):
        return 0.0, ROAD_RANGE
    if name == "signal_state":
        return 0.0, max(SIGNAL_CODES.values())
    if name == "signal_switch":
        return 0.0, SIGNAL_HORIZON
    caps = {"m/s": MAX_SPEED, "s": MAX_TIME, "m": MAX_DISTANCE}
    if unit in caps:
        return 0.0, caps[unit]
    return -np.inf, np.inf


def observation_space(
    fields: Sequence[FieldSpec], sensor_range: float, schema: ActionSchema
) -> spaces.Box:
    """The Box of the flat vector with `field_bounds` for every field."""
    bounds = [field_bounds(spec, sensor_range, schema) for spec in fields]
    low = np.array([b[0] for b in bounds], dtype=np.float32)
    high = np.array([b[1] for b in bounds], dtype=np.float32)
    return spaces.Box(low, high, dtype=np.float32)
