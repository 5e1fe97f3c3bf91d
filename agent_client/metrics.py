"""Driving metrics from a stream of named observations: efficiency, comfort, safety.

Jerk is measured at the simulator's step length, as a passenger feels it: the change of the
ego's realised acceleration between consecutive observations divided by one simulation step.
With a ``decision_interval`` longer than a step the acceleration is constant inside the interval,
so the whole change happens in one step and the other steps of the interval have zero jerk; they
count as samples. Time headway is gap / speed on steps with a leader; time to collision is
gap / (v - v_leader) on steps where the ego closes in.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from protocol.messages import Observation

JERK_COMFORT_LIMIT = 5.6
"""m/s^3: the paper's threshold of uncomfortable jerk (its Fig. 10)."""
HEADWAY_SAFE = 1.0
"""s: time headways below this count as tailgating."""


def jerk_series(
    accelerations: np.ndarray, times: np.ndarray, step_length: float | None = None
) -> tuple[np.ndarray, int]:
    """Jerk (m/s^3) at each change of acceleration, and the number of simulation steps covered.

    Without `step_length` the change is spread over the time between samples.
    """
    if len(accelerations) < 2:
        return np.zeros(0), 0
    dt = np.diff(times)
    if step_length is None:
        return np.diff(accelerations) / np.where(dt > 0, dt, np.nan), len(dt)
    steps = int(np.maximum(np.rint(dt / step_length), 1).sum())
    return np.diff(accelerations) / step_length, steps


def time_headways(gaps: np.ndarray, speeds: np.ndarray, min_speed: float = 0.1) -> np.ndarray:
    """Gap / speed on samples where the ego moves (s); NaN gaps (no leader) are dropped."""
    mask = np.isfinite(gaps) & (speeds > min_speed)
    return gaps[mask] / speeds[mask]


def times_to_collision(
    gaps: np.ndarray, speeds: np.ndarray, leader_speeds: np.ndarray
) -> np.ndarray:
    """Gap / closing speed on samples where the ego is faster than its leader (s)."""
    closing = speeds - leader_speeds
    mask = np.isfinite(gaps) & (closing > 1e-6)
    return np.maximum(gaps[mask], 0.0) / closing[mask]


def ceiling_speed(first: Observation, last: Observation) -> float | None:
    """Average speed the ego would have had arriving together with its leader-at-entry.

    On one lane the ego cannot overtake that vehicle, so this bounds the ego's average speed
    over its trip (from its entry to the end of the road).
    """
    trip = last.ceiling
    if trip is None or trip.arrival_time is None or trip.average_speed is None:
        return None
    road_length = trip.average_speed * (trip.arrival_time - trip.depart_time)
    duration = trip.arrival_time - first.time
    return (road_length - first.ego.position) / duration if duration > 0 else None


@dataclass
class EpisodeSummary:
    """What one episode looked like; every field is a plain number or string (JSON-ready)."""

    episode: int
    seed: int
    steps: int
    reason: str
    duration: float
    distance: float
    average_speed: float
    collisions: int
    jerk_share_above_limit: float
    max_abs_jerk: float
    headway_share_below_1s: float
    min_time_headway: float | None
    min_ttc: float | None
    ceiling_speed: float | None
    speed_ratio_to_ceiling: float | None
    total_reward: float
    lane_changes_started: int
    lane_changes_refused: int
    successful_lc_reward: float = 0.0
    """Sum of the rewards of the steps whose lane-change instruction started a change."""
    lane_changes_aborted: int = 0
    """Started lane changes the simulator gave up (counted in `lane_changes_started` too)."""

    def to_dict(self) -> dict[str, object]:
        return asdict(self)


@dataclass
class EpisodeRecorder:
    """Collects an episode's observations and rewards; `summary` computes the metrics."""

    episode: int = 0
    seed: int = 0
    step_length: float | None = None
    observations: list[Observation] = field(default_factory=list)
    rewards: list[float] = field(default_factory=list)

    def add(self, obs: Observation, reward: float = 0.0) -> None:
        if self.observations:
            self.rewards.append(reward)
        self.observations.append(obs)

    def summary(self) -> EpisodeSummary:
        observations = self.observations
        if not observations:
            raise ValueError("no observations recorded")
        times = np.array([o.time for o in observations])
        speeds = np.array([o.ego.speed for o in observations])
        accelerations = np.array([o.ego.acceleration for o in observations])
        gaps = np.array(
            [
                o.neighbours.leader.gap if o.neighbours.leader.present else np.nan
                for o in observations
            ]
        )
        leader_speeds = np.array([o.neighbours.leader.speed for o in observations])
        jerks, jerk_samples = jerk_series(accelerations, times, self.step_length)
        jerks = np.abs(jerks[np.isfinite(jerks)])
        headways = time_headways(gaps, speeds)
        ttcs = times_to_collision(gaps, speeds, leader_speeds)
        last = observations[-1]
        duration = float(times[-1] - times[0])
        distance = float(last.ego.position - observations[0].ego.position)
        average_speed = distance / duration if duration > 0 else 0.0
        ceiling = ceiling_speed(observations[0], last)
        return EpisodeSummary(
            episode=self.episode,
            seed=self.seed,
            steps=len(observations) - 1,
            reason=last.reason,
            duration=duration,
            distance=distance,
            average_speed=average_speed,
            collisions=sum(o.events.collision for o in observations),
            jerk_share_above_limit=(
                float(np.sum(jerks > JERK_COMFORT_LIMIT)) / jerk_samples if jerk_samples else 0.0
            ),
            max_abs_jerk=float(jerks.max()) if len(jerks) else 0.0,
            headway_share_below_1s=float(np.mean(headways < HEADWAY_SAFE))
            if len(headways)
            else 0.0,
            min_time_headway=float(headways.min()) if len(headways) else None,
            min_ttc=float(ttcs.min()) if len(ttcs) else None,
            ceiling_speed=ceiling,
            speed_ratio_to_ceiling=average_speed / ceiling if ceiling else None,
            total_reward=float(sum(self.rewards)),
            lane_changes_started=sum(o.events.lane_change_started for o in observations),
            lane_changes_refused=sum(o.events.lane_change_refused for o in observations),
            successful_lc_reward=float(
                sum(
                    reward
                    for obs, reward in zip(observations[1:], self.rewards, strict=True)
                    if obs.events.lane_change_started
                )
            ),
            lane_changes_aborted=sum(o.events.lane_change_aborted for o in observations),
        )


def format_summary(summary: EpisodeSummary) -> str:
    """One human-readable line per episode."""
    ceiling = (
        f"{summary.ceiling_speed:5.2f} m/s ({summary.speed_ratio_to_ceiling:.3f}x)"
        if summary.ceiling_speed and summary.speed_ratio_to_ceiling
        else "  n/a"
    )
    ttc = f"{summary.min_ttc:6.2f} s" if summary.min_ttc is not None else "    n/a"
    return (
        f"episode {summary.episode:3d} seed {summary.seed:10d} | {summary.steps:5d} steps "
        f"{summary.reason:12s} | avg speed {summary.average_speed:5.2f} m/s, ceiling {ceiling} | "
        f"collisions {summary.collisions} | jerk>5.6 {100 * summary.jerk_share_above_limit:5.1f}% "
        f"| headway<1s {100 * summary.headway_share_below_1s:5.1f}% | min TTC {ttc}"
    )


def mean_or_nan(values: list[float]) -> float:
    """Mean of a possibly empty list (NaN when empty)."""
    return float(np.mean(values)) if values else math.nan
