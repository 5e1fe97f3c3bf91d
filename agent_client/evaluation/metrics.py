"""Driving metrics from a stream of named observations: efficiency, comfort, safety.

Jerk is measured at the simulator's step length, as a passenger feels it: the change of the
ego's realised acceleration between consecutive observations divided by one simulation step.
With a ``decision_interval`` longer than a step the acceleration is constant inside the interval,
so the whole change happens in one step and the other steps of the interval have zero jerk; they
count as samples. Time headway is gap / speed on steps with a leader and the ego moving; time to
collision is gap / (v - v_leader) on steps where the ego closes in.

`episode_summary` gives the figures (`EpisodeSummary`) of an `Episode`, and `aggregate` gives the
figures of several episodes that training, ``agent-client drive`` and the evaluation report share.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from agent_client.constants import HEADWAY_SAFE, JERK_COMFORT_LIMIT, MIN_MOVING_SPEED
from agent_client.drivers.episode import Episode
from protocol.messages import EndReason, Observation


def jerk_series(
    accelerations: np.ndarray, times: np.ndarray, step_length: float | None = None
) -> tuple[np.ndarray, int]:
    """Jerk (m/s^3) at each change of acceleration, and the number of simulation steps covered.

    Without `step_length` (or with one that is not a positive finite number, which a checked
    welcome never gives) the change is spread over the time between samples.
    """
    if len(accelerations) < 2:
        return np.zeros(0), 0
    dt = np.diff(times)
    if step_length is None or not 0 < step_length < math.inf:
        return np.diff(accelerations) / np.where(dt > 0, dt, np.nan), len(dt)
    steps = int(np.maximum(np.rint(dt / step_length), 1).sum())
    return np.diff(accelerations) / step_length, steps


def time_headways(
    gaps: np.ndarray, speeds: np.ndarray, min_speed: float = MIN_MOVING_SPEED
) -> np.ndarray:
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


@dataclass(frozen=True, eq=False)
class EpisodeSamples:
    """The per-step samples of an episode behind its shares and distributions."""

    jerks: np.ndarray
    """Signed jerk (m/s^3) at each change of acceleration; finite values only."""
    jerk_steps: int
    """Simulation steps the jerk samples cover: the denominator of the jerk share."""
    headways: np.ndarray
    """Time headways (s) on steps with a leader and the ego moving."""
    ttcs: np.ndarray
    """Times to collision (s) on steps where the ego is faster than its leader."""
    leader_steps: int
    """Observations with a leader: the denominator of the share of critical TTCs."""

    @classmethod
    def from_observations(
        cls, observations: Sequence[Observation], step_length: float | None
    ) -> EpisodeSamples:
        times = np.array([o.time for o in observations])
        speeds = np.array([o.ego.speed for o in observations])
        accelerations = np.array([o.ego.acceleration for o in observations])
        present = np.array([o.neighbours.leader.present for o in observations], dtype=bool)
        gaps = np.where(present, [o.neighbours.leader.gap for o in observations], np.nan)
        leader_speeds = np.array([o.neighbours.leader.speed for o in observations])
        jerks, jerk_steps = jerk_series(accelerations, times, step_length)
        return cls(
            jerks=jerks[np.isfinite(jerks)],
            jerk_steps=jerk_steps,
            headways=time_headways(gaps, speeds),
            ttcs=times_to_collision(gaps, speeds, leader_speeds),
            leader_steps=int(present.sum()),
        )


@dataclass
class EpisodeSummary:
    """What one episode looked like; every field is a plain number or string (JSON-ready)."""

    episode: int
    seed: int
    steps: int
    reason: str
    """Why the episode ended: a `protocol.messages.EndReason` value."""
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
    headway_samples: int = 0
    """Time headways behind `headway_share_below_1s`: its weight when episodes are pooled."""
    route_lanes: int = 0
    """The most lanes the route asked the ego to cross at once (`Road.lanes_to_change`): above
    0 on a road with a lane end or an exit, where reaching the end of the route is a target."""
    red_lights: int = 0
    """Red lights the ego passed (`Events.red_light`, protocol 1.8)."""
    collision_type: str = ""
    """Where its collision happened ("lane", "junction"; "" without one)."""
    route_length: float | None = None
    """m of the ego's route (`Observation.route`, protocol 1.8; None where not reported)."""
    route_edges: str = ""
    """The roads of the route the ego entered, space-separated, in order: the trip, traceable
    (where the simulator reports routes)."""
    safety_steps: int = 0
    """Decisions in which a safety layer overrode the driver (its acceleration or its lane
    change; `agent_client.drivers.safety`): 0 for a driver without one."""
    safety_lane_changes: int = 0
    """Lane changes the safety layer decided that started."""
    safety_rules: str = ""
    """The layer's decisions by rule, ``collision:N stop_line:N yellow:N lane_end:N
    standstill:N`` ("": none)."""
    own_lane_changes: int | None = None
    """Lane changes started (the driver's, not the safety layer's) that IDM + MOBIL, asked on
    the same observation, would not have made: the driver's own decisions (None: not
    measured; `benchmarks/table.py` measures it)."""

    def to_dict(self) -> dict[str, object]:
        return asdict(self)


def episode_summary(episode: Episode) -> EpisodeSummary:
    """The figures of one episode."""
    observations = episode.observations
    if not observations:
        raise ValueError("no observations recorded")
    samples = EpisodeSamples.from_observations(observations, episode.step_length)
    first, last = observations[0], observations[-1]
    duration = float(last.time - first.time)
    distance = float(last.ego.position - first.ego.position)
    average_speed = distance / duration if duration > 0 else 0.0
    ceiling = ceiling_speed(first, last)
    jerks = np.abs(samples.jerks)
    headways = samples.headways
    return EpisodeSummary(
        episode=episode.episode,
        seed=episode.seed,
        steps=len(observations) - 1,
        reason=last.reason,
        duration=duration,
        distance=distance,
        average_speed=average_speed,
        collisions=sum(o.events.collision for o in observations),
        jerk_share_above_limit=float(np.sum(jerks > JERK_COMFORT_LIMIT)) / samples.jerk_steps
        if samples.jerk_steps
        else 0.0,
        max_abs_jerk=float(jerks.max()) if len(jerks) else 0.0,
        headway_share_below_1s=float(np.mean(headways < HEADWAY_SAFE)) if len(headways) else 0.0,
        min_time_headway=float(headways.min()) if len(headways) else None,
        min_ttc=float(samples.ttcs.min()) if len(samples.ttcs) else None,
        ceiling_speed=ceiling,
        speed_ratio_to_ceiling=average_speed / ceiling if ceiling else None,
        total_reward=float(sum(episode.rewards)),
        lane_changes_started=sum(o.events.lane_change_started for o in observations),
        lane_changes_refused=sum(o.events.lane_change_refused for o in observations),
        successful_lc_reward=_successful_lc_reward(episode),
        lane_changes_aborted=sum(o.events.lane_change_aborted for o in observations),
        headway_samples=len(headways),
        route_lanes=max((abs(o.road.lanes_to_change) for o in observations if o.road), default=0),
        red_lights=sum(o.events.red_light for o in observations),
        safety_steps=sum(o.any for o in episode.overrides),
        safety_lane_changes=sum(
            o.lane_change and after.events.lane_change_started
            for o, after in zip(episode.overrides, observations[1:], strict=False)
        ),
        safety_rules=" ".join(
            f"{rule}:{count}"
            for rule, count in sorted(Counter(o.rule for o in episode.overrides if o.any).items())
        ),
        collision_type=next(
            (o.events.collision_type for o in observations if o.events.collision), ""
        ),
        **_route(first, last),
    )


def _route(first: Observation, last: Observation) -> dict[str, Any]:
    """The route's length and the roads of it the ego entered, from the first and the last
    observation (empty where the simulator reports no route)."""
    route = last.route or first.route
    if route is None:
        return {}
    driven = route.driven if last.route is not None else 1
    return {"route_length": route.length, "route_edges": " ".join(route.edges[:driven])}


def _successful_lc_reward(episode: Episode) -> float:
    """Sum of the rewards of the steps whose lane-change instruction started a change."""
    after = episode.observations[1:]
    return float(
        sum(r for o, r in zip(after, episode.rewards, strict=True) if o.events.lane_change_started)
    )


def format_summary(summary: EpisodeSummary) -> str:
    """One human-readable line per episode."""
    ceiling = (
        f"{summary.ceiling_speed:5.2f} m/s ({summary.speed_ratio_to_ceiling:.3f}x)"
        if summary.ceiling_speed and summary.speed_ratio_to_ceiling
        else "  n/a"
    )
    ttc = f"{summary.min_ttc:6.2f} s" if summary.min_ttc is not None else "    n/a"
    red = f"red lights {summary.red_lights} | " if summary.red_lights else ""
    return (
        f"episode {summary.episode:3d} seed {summary.seed:10d} | {summary.steps:5d} steps "
        f"{summary.reason:12s} | avg speed {summary.average_speed:5.2f} m/s, ceiling {ceiling} | "
        f"collisions {summary.collisions} | {red}"
        f"jerk>{JERK_COMFORT_LIMIT} {100 * summary.jerk_share_above_limit:5.1f}% | "
        f"headway<{HEADWAY_SAFE:g}s {100 * summary.headway_share_below_1s:5.1f}% | min TTC {ttc}"
    )


def aggregate(summaries: Sequence[EpisodeSummary]) -> dict[str, float]:
    """The figures of several episodes, NaN where one does not exist.

    Speeds, collisions, ratios and rewards are means over episodes; the jerk share is weighted by
    steps, the headway share by headway samples (both are then shares of all samples), and the
    minimum TTC is over all episodes.
    """
    if not summaries:
        raise ValueError("no episodes to summarise")
    steps = np.array([s.steps for s in summaries], dtype=float)
    weights = steps / steps.sum() if steps.sum() > 0 else np.full(len(steps), 1 / len(steps))
    speeds = [s.average_speed for s in summaries]
    ratios = [s.speed_ratio_to_ceiling for s in summaries if s.speed_ratio_to_ceiling is not None]
    ttcs = [s.min_ttc for s in summaries if s.min_ttc is not None]
    return {
        "episodes": len(summaries),
        "average_speed": float(np.mean(speeds)),
        "average_speed_sd": float(np.std(speeds)),
        "collisions_per_episode": float(np.mean([s.collisions for s in summaries])),
        "red_lights_per_episode": float(np.mean([s.red_lights for s in summaries])),
        "safety_share": float(sum(s.safety_steps for s in summaries) / max(1.0, steps.sum())),
        "jerk_share_above_limit": float(
            np.dot(weights, [s.jerk_share_above_limit for s in summaries])
        ),
        "headway_share_below_1s": _pooled_headway_share(summaries),
        "speed_ratio_to_ceiling": float(np.mean(ratios)) if ratios else float("nan"),
        "min_ttc": float(np.min(ttcs)) if ttcs else float("nan"),
        "total_reward": float(np.mean([s.total_reward for s in summaries])),
        "arrival_share": float(np.mean([s.reason == EndReason.END_OF_ROAD for s in summaries])),
        "route_lanes": max(s.route_lanes for s in summaries),
    }


def safety_rule_shares(summaries: Sequence[EpisodeSummary]) -> dict[str, float]:
    """The share of all the episodes' steps in which the safety layer decided, by rule
    (``{"lane_end": 0.026, ...}``; `EpisodeSummary.safety_rules`): which stated rule drove
    where the layer did. Empty where it never did."""
    counts: Counter[str] = Counter()
    for s in summaries:
        for item in s.safety_rules.split():
            rule, _, count = item.rpartition(":")
            counts[rule] += int(count)
    steps = sum(s.steps for s in summaries)
    return {rule: count / max(steps, 1) for rule, count in sorted(counts.items())}


def _pooled_headway_share(summaries: Sequence[EpisodeSummary]) -> float:
    """Share of all the episodes' time headways below `HEADWAY_SAFE` (0 without any).

    Counts are recovered from each episode's share and sample count, so the result is the share
    of the pooled samples to the last bit.
    """
    samples = sum(s.headway_samples for s in summaries)
    if samples == 0:
        return 0.0
    below = sum(round(s.headway_share_below_1s * s.headway_samples) for s in summaries)
    return below / samples
