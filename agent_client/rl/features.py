"""What the networks see: scaled features computed from the named observation.

The wire carries raw SI values (and the flat vector of the protocol's schema); choosing and
scaling inputs is a learning decision, so it lives here. Three sets:

* ``cf`` — the paper's car-following state (§4.3): speed, acceleration, gap and speed difference
  to the leader, plus the time headway and leader presence (a missing leader is a flag, not a
  huge gap).
* ``lc`` — ``cf`` plus the other five neighbours of Fig. 11 (presence, gap, relative speed) and
  whether there is a lane to the left and to the right.
* ``drive`` — ``road`` plus what closes the way ahead (protocol 1.7-1.8): the stop line (its
  distance, and the braking that stopping there takes at the ego's speed) and the next traffic
  light (its distance, its state as red / yellow / green flags, the seconds until it changes):
  the integrated driver's inputs on any road, the city's included.
* ``road`` — ``lc`` plus the road ahead along the route (`protocol.messages.Road`, protocol 1.6):
  how far the ego's lane and the lanes beside it go on, the lanes it must cross (and to which side),
  the seconds left to the end of its lane at its speed, and how far the gap beside it on that side
  is from a safe one (ahead and behind). On a road whose lanes all go on (``cf``, ``cflc``, the
  ring) they are constant but for the lanes beside the ego, which repeat ``lc``'s last two features;
  from a server older than 1.6 they are those of the open road.

All features are O(1): speeds by the speed limit, gaps by 100 m (capped at 2), speed differences
by 10 m/s, headways by 5 s (capped at 1), the road's distances by `ROAD_RANGE`, the lanes to
change by 2 (capped at ±1.5), the time to the lane end by 10 s (capped at 1), the gap margins by
100 m (within ±1).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np

from agent_client.constants import PAPER_SPEED_LIMIT
from agent_client.errors import FeatureMismatch, UsageError
from agent_client.rl.lanes import lane_phase, secure_gap
from protocol.messages import (
    ROAD_RANGE,
    SIGNAL_HORIZON,
    Neighbour,
    Observation,
    SignalState,
    road_ahead,
)

__all__ = [
    "FEATURE_SETS",
    "FeatureMap",
    "FeatureMismatch",
    "car_following",
    "driving",
    "lane_changing",
    "road_reading",
]

GAP_SCALE = 100.0
GAP_CAP = 2.0
SPEED_DIFF_SCALE = 10.0
HEADWAY_SCALE = 5.0
ACCELERATION_SCALE = 3.0

_OTHER_SLOTS = ("left_leader", "left_follower", "follower", "right_leader", "right_follower")


def _neighbour(n: Neighbour, ego_speed: float) -> list[float]:
    if not n.present:
        return [0.0, GAP_CAP, 0.0]
    return [1.0, min(n.gap / GAP_SCALE, GAP_CAP), (n.speed - ego_speed) / SPEED_DIFF_SCALE]


def car_following(obs: Observation) -> list[float]:
    """The six car-following features."""
    ego = obs.ego
    limit = ego.speed_limit if ego.speed_limit > 0 else PAPER_SPEED_LIMIT
    leader = obs.neighbours.leader
    if leader.present:
        headway = min(max(leader.gap, 0.0) / max(ego.speed, 0.5) / HEADWAY_SCALE, 1.0)
        lead = [
            1.0,
            min(leader.gap / GAP_SCALE, GAP_CAP),
            (leader.speed - ego.speed) / SPEED_DIFF_SCALE,
        ]
    else:
        headway, lead = 1.0, [0.0, GAP_CAP, 0.0]
    return [ego.speed / limit, ego.acceleration / ACCELERATION_SCALE, *lead, headway]


def lane_changing(obs: Observation) -> list[float]:
    """Car-following features, the other five neighbours and the lanes available."""
    features = car_following(obs)
    for slot in _OTHER_SLOTS:
        features += _neighbour(getattr(obs.neighbours, slot), obs.ego.speed)
    ego = obs.ego
    features += [float(ego.lane < ego.lane_count - 1), float(ego.lane > 0)]
    return features


LANES_SCALE = 2.0
LANES_CAP = 1.5
LANE_END_TIME_SCALE = 10.0


def road_reading(obs: Observation) -> list[float]:
    """Lane-changing features and the road ahead along the route."""
    features = lane_changing(obs)
    road = road_ahead(obs)
    lanes = min(max(road.lanes_to_change / LANES_SCALE, -LANES_CAP), LANES_CAP)
    seconds = road.lane_end / max(obs.ego.speed, 1.0) / LANE_END_TIME_SCALE
    features += [
        road.lane_end / ROAD_RANGE,
        lanes,
        road.left_lane_end / ROAD_RANGE,
        road.right_lane_end / ROAD_RANGE,
        min(seconds, 1.0),
        *_gap_margins(obs, road.lanes_to_change),
    ]
    return features


def _gap_margins(obs: Observation, lanes_to_change: int) -> list[float]:
    """How much longer (+) or shorter (-) than a safe driver's secure gap the gaps to the new
    leader and from the new follower are, on the side the route leads to (0 and 0 on a road
    whose lanes lead on): what the ego's speed must open before it can change."""
    if not lanes_to_change:
        return [0.0, 0.0]
    near, speed = obs.neighbours, obs.ego.speed
    lead, lag = (
        (near.left_leader, near.left_follower)
        if lanes_to_change > 0
        else (near.right_leader, near.right_follower)
    )
    ahead = lead.gap - secure_gap(speed, lead.speed) if lead.present else GAP_SCALE
    behind = lag.gap - secure_gap(lag.speed, speed) if lag.present else GAP_SCALE
    return [min(max(m / GAP_SCALE, -1.0), 1.0) for m in (ahead, behind)]


STOP_DECELERATION_SCALE = 6.0
"""m/s²: the braking a stop needs is given as a share of this (the ego's hardest), capped at 1.5."""


def driving(obs: Observation) -> list[float]:
    """Road-reading features and what closes the way ahead: the stop line and the next light."""
    features = road_reading(obs)
    road = road_ahead(obs)
    speed = max(obs.ego.speed, 0.0)
    line = road.stop_line
    if line < ROAD_RANGE:
        needed = speed * speed / (2.0 * max(line, 0.5)) / STOP_DECELERATION_SCALE
        stop = [1.0, line / ROAD_RANGE, min(needed, 1.5)]
    else:
        stop = [0.0, 1.0, 0.0]
    state = road.signal_state
    light = [
        road.signal_distance / ROAD_RANGE,
        float(state == SignalState.RED),
        float(state == SignalState.YELLOW),
        float(state == SignalState.GREEN),
        road.signal_switch / SIGNAL_HORIZON,
    ]
    return features + stop + light


FEATURE_SETS: dict[str, Callable[[Observation], list[float]]] = {
    "cf": car_following,
    "lc": lane_changing,
    "road": road_reading,
    "drive": driving,
}


class FeatureMap:
    """Named observation -> float32 feature vector of a chosen set.

    With lane decisions taken every `lane_phase_every` decisions (> 1), the vector ends with the
    phase between two of them (`LaneChoice.phase`), so the critic knows when it may change lanes.
    """

    def __init__(self, name: str, lane_phase_every: int = 1) -> None:
        if name not in FEATURE_SETS:
            raise UsageError(f"unknown feature set {name!r}; known: {', '.join(FEATURE_SETS)}")
        self.name = name
        self._extract = FEATURE_SETS[name]
        self.lane_phase_every = lane_phase_every
        self.dim = len(self._extract(_EXAMPLE)) + (lane_phase_every > 1)

    def __call__(self, obs: Observation) -> np.ndarray:
        features = self._extract(obs)
        if self.lane_phase_every > 1:
            features.append(lane_phase(obs.seq, self.lane_phase_every))
        vector = np.asarray(features, dtype=np.float64)
        if not np.all(np.abs(vector) <= FEATURE_CAP):  # NaN included: out of the designed range
            _warn_once(obs, vector)
            vector = np.clip(np.nan_to_num(vector, nan=0.0), -FEATURE_CAP, FEATURE_CAP)
        return vector.astype(np.float32)


FEATURE_CAP = 10.0
"""Every feature is designed to lie within a few units; a value beyond this (an observation no
driver should meet, valid as it is on the wire) is clipped, so that it cannot turn the
networks' outputs into infinities, and reported once."""
_warned: list[bool] = []


def _warn_once(obs: Observation, vector: np.ndarray) -> None:
    if not _warned:
        _warned.append(True)
        warnings.warn(
            f"features beyond +-{FEATURE_CAP:g} (clipped): {vector.tolist()} from {obs}",
            RuntimeWarning,
            stacklevel=3,
        )


def _example() -> Observation:
    from protocol.messages import AppliedAction, Ego, Events, Neighbours

    absent = Neighbour(False, 200.0, 0.0, 0.0)
    return Observation(
        0, 0.0, Ego(0.0, 0.0, 0, 1, 0.0, 22.22), Neighbours(*(absent,) * 6), Events(),
        AppliedAction(0.0, 0, 0.0, 0),
    )  # fmt: skip


_EXAMPLE = _example()
