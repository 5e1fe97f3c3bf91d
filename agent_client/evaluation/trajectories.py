"""Compact per-episode traces: the ego's and its observed neighbours' trajectories as arrays.

A report draws time-space diagrams and time series of chosen episodes long after they were
driven; keeping every `protocol.messages.Observation` of every episode for that would be
wasteful, so `EpisodeTrace.from_observations` keeps numpy arrays of what the pictures need.

Positions are metres along the route of each vehicle's **front**, like ``ego.position``. The
wire gives bumper-to-bumper gaps only (docs/protocol.md §4.3): a leader's rear is at
``ego.position + gap`` and a follower's front at ``ego.position - ego length - gap``. Vehicle
lengths are not on the wire; `VEHICLE_LENGTH` is SUMO's default passenger car, which the ego
and the scenarios' human drivers are (their vTypes set no length), so a leader's front is one
such length beyond its rear. Neighbour lanes are absolute: ``ego.lane`` for the leader and the
follower, one more for the left ones and one less for the right ones.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from agent_client.evaluation.metrics import jerk_series
from protocol.messages import Neighbour, Observation

VEHICLE_LENGTH = 5.0
"""m: SUMO's default passenger-car length, assumed for the ego and every neighbour."""

SLOTS: dict[str, tuple[int, bool]] = {
    "left_leader": (1, True),
    "left_follower": (1, False),
    "leader": (0, True),
    "follower": (0, False),
    "right_leader": (-1, True),
    "right_follower": (-1, False),
}
"""Each neighbour slot: its lane offset from the ego's (left +1) and whether it is ahead."""


def neighbour_front(
    ego_position: float, gap: float, ahead: bool, length: float = VEHICLE_LENGTH
) -> float:
    """A neighbour's front along the route (m) from its bumper-to-bumper gap to the ego.

    Ahead: its rear is at ``ego_position + gap``, its front one length further. Behind: its
    front is at the ego's rear (``ego_position - length``) minus the gap.
    """
    return ego_position + gap + length if ahead else ego_position - length - gap


@dataclass(frozen=True, eq=False)
class NeighbourTrack:
    """One surrounding vehicle while it was observed (in any of the six slots)."""

    step: np.ndarray
    """Index of the observation of each sample: consecutive samples differ by 1."""
    time: np.ndarray
    position: np.ndarray
    """Its front along the route (m)."""
    speed: np.ndarray
    lane: np.ndarray
    """Absolute lane index, 0 = rightmost."""


@dataclass(frozen=True, eq=False)
class EpisodeTrace:
    """The ego's states and events of one episode, and every neighbour it observed.

    Arrays of the ego are one entry per observation (seq 0 = reset first); `jerk` is NaN at the
    first and `gap` is NaN where there was no leader. Event times are simulation times of the
    observations that report them.
    """

    seed: int
    time: np.ndarray
    position: np.ndarray
    speed: np.ndarray
    acceleration: np.ndarray
    jerk: np.ndarray
    """m/s^3: change of acceleration from the previous observation over one simulation step
    (`agent_client.evaluation.metrics.jerk_series`, as the report's jerk figures)."""
    lane: np.ndarray
    gap: np.ndarray
    """m: bumper-to-bumper gap to the leader, NaN without one."""
    speed_limit: np.ndarray
    lane_count: int
    lane_change_starts: np.ndarray
    lane_change_directions: np.ndarray
    """+1 left, -1 right, one per start."""
    lane_change_completions: np.ndarray
    lane_change_aborts: np.ndarray
    collisions: np.ndarray
    neighbours: dict[str, NeighbourTrack] = field(default_factory=dict)
    """Keyed by the simulator's vehicle id."""

    @property
    def start(self) -> float:
        """Simulation time of the first observation: time 0 of the pictures."""
        return float(self.time[0]) if len(self.time) else 0.0

    @classmethod
    def from_observations(
        cls, observations: Sequence[Observation], step_length: float | None, seed: int = 0
    ) -> EpisodeTrace:
        """The trace of one episode's observations (jerk at `step_length`, as the metrics)."""
        if not observations:
            raise ValueError("no observations to trace")
        times = np.array([o.time for o in observations], dtype=float)
        accelerations = np.array([o.ego.acceleration for o in observations], dtype=float)
        jerks, _ = jerk_series(accelerations, times, step_length)
        leaders = [o.neighbours.leader for o in observations]
        return cls(
            seed=seed,
            time=times,
            position=np.array([o.ego.position for o in observations], dtype=float),
            speed=np.array([o.ego.speed for o in observations], dtype=float),
            acceleration=accelerations,
            jerk=np.concatenate([[np.nan], jerks]),
            lane=np.array([o.ego.lane for o in observations], dtype=int),
            gap=np.array([n.gap if n.present else np.nan for n in leaders], dtype=float),
            speed_limit=np.array([o.ego.speed_limit for o in observations], dtype=float),
            lane_count=max(o.ego.lane_count for o in observations),
            lane_change_starts=_event_times(observations, "lane_change_started"),
            lane_change_directions=np.array(
                [
                    int(np.sign(o.action.lane_change or o.action.requested_lane_change))
                    for o in observations
                    if o.events.lane_change_started
                ],
                dtype=int,
            ),
            lane_change_completions=_event_times(observations, "lane_change_completed"),
            lane_change_aborts=_event_times(observations, "lane_change_aborted"),
            collisions=_event_times(observations, "collision"),
            neighbours=neighbour_tracks(observations),
        )


def _event_times(observations: Sequence[Observation], event: str) -> np.ndarray:
    return np.array([o.time for o in observations if getattr(o.events, event)], dtype=float)


def neighbour_tracks(observations: Sequence[Observation]) -> dict[str, NeighbourTrack]:
    """Every observed neighbour's samples by vehicle id, in observation order.

    Absent slots and present ones without an id (a simulator that sends none) are skipped.
    """
    samples: dict[str, list[tuple[int, float, float, float, int]]] = {}
    for step, obs in enumerate(observations):
        for slot, (offset, ahead) in SLOTS.items():
            neighbour: Neighbour = getattr(obs.neighbours, slot)
            if not neighbour.present or not neighbour.id:
                continue
            position = neighbour_front(obs.ego.position, neighbour.gap, ahead)
            samples.setdefault(neighbour.id, []).append(
                (step, obs.time, position, neighbour.speed, obs.ego.lane + offset)
            )
    tracks = {}
    for vehicle, rows in samples.items():
        columns = list(zip(*rows, strict=True))
        tracks[vehicle] = NeighbourTrack(
            step=np.array(columns[0], dtype=int),
            time=np.array(columns[1], dtype=float),
            position=np.array(columns[2], dtype=float),
            speed=np.array(columns[3], dtype=float),
            lane=np.array(columns[4], dtype=int),
        )
    return tracks
