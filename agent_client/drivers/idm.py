"""The Intelligent Driver Model (Treiber, Hennecke and Helbing 2000): the baseline driver.

    a_IDM = a * (1 - (v / v0)^delta - (s*(v, dv) / s)^2)
    s*(v, dv) = s0 + v T + v dv / (2 sqrt(a b))

with s the net gap to the leader and dv = v - v_leader (positive when closing in). Without a
leader only the free-road term acts. A stop line (protocol 1.7, `Road.stop_line`: a red light, a
road that must give way) is a standing vehicle there, as SUMO's and highway-env's drivers treat
a closed way. It reads the same named observations as any policy.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from protocol.messages import ROAD_RANGE, Observation


@dataclass(frozen=True)
class IDMParams:
    """IDM parameters; defaults are common highway values (Treiber and Kesting)."""

    a: float = 1.5
    """Maximum acceleration (m/s^2)."""
    b: float = 2.0
    """Comfortable deceleration (m/s^2)."""
    T: float = 1.5
    """Desired time headway (s)."""
    s0: float = 2.0
    """Minimum gap at standstill (m)."""
    v0: float | None = None
    """Desired speed (m/s); None drives at the road's speed limit."""
    delta: float = 4.0
    """Acceleration exponent."""

    def to_dict(self) -> dict[str, float | None]:
        return asdict(self)


def idm_acceleration(
    params: IDMParams, speed: float, speed_limit: float, gap: float | None, leader_speed: float
) -> float:
    """IDM acceleration for a follower at `speed` with net `gap` (None: no leader)."""
    v0 = params.v0 if params.v0 is not None else speed_limit
    free = 1.0 - (max(speed, 0.0) / max(v0, 1e-6)) ** params.delta
    if gap is None:
        return params.a * free
    dv = speed - leader_speed
    desired = params.s0 + max(
        0.0, speed * params.T + speed * dv / (2.0 * math.sqrt(params.a * params.b))
    )
    return params.a * (free - (desired / max(gap, 0.1)) ** 2)


def stop_line_acceleration(params: IDMParams, obs: Observation) -> float:
    """IDM's acceleration before the ego's stop line (`Road.stop_line`) as before a standing
    vehicle there; infinite where there is none."""
    road = obs.road
    if road is None or road.stop_line >= ROAD_RANGE:
        return math.inf
    return idm_acceleration(params, obs.ego.speed, obs.ego.speed_limit, road.stop_line, 0.0)


class IDMDriver:
    """A policy that drives the ego with IDM and keeps its lane."""

    name = "idm"

    def __init__(self, params: IDMParams | None = None) -> None:
        self.params = params or IDMParams()

    def act(self, obs: Observation) -> tuple[float, int]:
        """Acceleration (m/s^2) and lane change (always 0) for one observation."""
        leader = obs.neighbours.leader
        gap = leader.gap if leader.present else None
        acc = idm_acceleration(self.params, obs.ego.speed, obs.ego.speed_limit, gap, leader.speed)
        return min(acc, stop_line_acceleration(self.params, obs)), 0
