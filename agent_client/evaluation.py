"""Evaluate a driver against a baseline on the same seeds: the figures of the paper's §4.4-4.5.

Each episode is driven through the bridge and kept as an `EpisodeRecord`: the summary of
`agent_client.metrics` plus the samples behind the distributions (jerk, time headway, time to
collision) and the target-lane gaps at each lane-change start. The functions below turn records
into the report's numbers; `agent_client.report` writes them out.

Definitions (all over the steps of the evaluation episodes):

* time headway: gap / ego speed on steps with a leader and the ego moving (> 0.1 m/s);
* time to collision (TTC): gap / closing speed on steps where the ego is faster than its leader;
  the share of TTC < 4 s is over the steps with a leader;
* lane-change instructions: lane changes started + refused (any reason); success rate: started /
  instructions; frequency: lane changes started / (km driven x lanes), in veh/km/lane;
* Table 3 headways: at the observation before a lane change starts (the state the decision was
  made on), the gap to the leader (lead) and to the follower (lag) in the target lane, each
  divided by the ego's speed; a missing vehicle gives no headway.
"""

from __future__ import annotations

import itertools
import math
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from agent_client.drive import Driver, aggregate
from agent_client.metrics import (
    HEADWAY_SAFE,
    EpisodeRecorder,
    EpisodeSummary,
    jerk_series,
    time_headways,
    times_to_collision,
)
from protocol.messages import Observation, OptionValue

TTC_CRITICAL = 4.0
"""s: times to collision below this count as critical."""
MIN_MOVING_SPEED = 0.1
"""m/s: below this a time headway is not defined."""

PAPER: dict[str, Any] = {
    "source": "Ye, Zhang and Sun, §4.4-4.5, Figs. 9-10 and 13, Tables 2-3",
    "cf": {
        "drl_average_speed": 12.44,
        "idm_average_speed": 11.53,
        "drl_gain_over_idm": 0.079,
        "drl_jerk_share_above_limit": 0.026,
    },
    "lc": {
        "integrated_average_speed": 12.74,
        "cf_average_speed": 12.44,
        "integrated_gain_over_cf": 0.024,
        "lc_frequency": 0.81,
        "lc_frequency_ngsim": {"US-101": 0.63, "I-80": 0.80},
        "table3": {
            "US-101": {"lead": 2.78, "lag": 3.14},
            "I-80": {"lead": 1.49, "lag": 1.71},
            "DRL-LC": {"lead": 4.70, "lag": 4.81},
        },
        "table2_last_row": {
            "episodes": "10000-11000",
            "instructions_per_episode": 16,
            "success_rate": 0.043,
            "reward_of_successful_lc": 6.50,
            "lc_frequency": 0.69,
        },
    },
}
"""The paper's figures shown beside ours."""


@dataclass(frozen=True)
class LaneChangeGap:
    """Target-lane time headways (s) when a lane change starts; None when no vehicle is there."""

    direction: int
    lead_headway: float | None
    lag_headway: float | None


@dataclass(eq=False)
class EpisodeRecord:
    """An evaluation episode: its summary and the samples behind the distributions."""

    summary: EpisodeSummary
    jerks: np.ndarray
    """Signed jerk samples (m/s^3) at the simulator's step length."""
    headways: np.ndarray
    ttcs: np.ndarray
    leader_steps: int
    lane_count: int
    lane_change_gaps: list[LaneChangeGap] = field(default_factory=list)
    refusals: dict[str, int] = field(default_factory=dict)
    """Refused lane changes by reason (gap_too_small, no_lane, in_progress...)."""


# --------------------------------------------------------------------------- driving


def lane_change_gaps(observations: Sequence[Observation]) -> list[LaneChangeGap]:
    """Target-lane lead and lag headways at each `events.lane_change_started`."""
    gaps = []
    for before, after in itertools.pairwise(observations):
        if not after.events.lane_change_started:
            continue
        direction = after.action.lane_change or after.action.requested_lane_change
        side = before.neighbours
        lead, lag = (
            (side.left_leader, side.left_follower)
            if direction > 0
            else (side.right_leader, side.right_follower)
        )
        speed = before.ego.speed
        moving = speed > MIN_MOVING_SPEED
        gaps.append(
            LaneChangeGap(
                direction=int(direction),
                lead_headway=max(lead.gap, 0.0) / speed if lead.present and moving else None,
                lag_headway=max(lag.gap, 0.0) / speed if lag.present and moving else None,
            )
        )
    return gaps


def record_episode(recorder: EpisodeRecorder) -> EpisodeRecord:
    """Summary and samples of a recorded episode."""
    observations = recorder.observations
    summary = recorder.summary()
    times = np.array([o.time for o in observations])
    speeds = np.array([o.ego.speed for o in observations])
    accelerations = np.array([o.ego.acceleration for o in observations])
    present = np.array([o.neighbours.leader.present for o in observations])
    gaps = np.where(present, [o.neighbours.leader.gap for o in observations], np.nan)
    leader_speeds = np.array([o.neighbours.leader.speed for o in observations])
    jerks, _ = jerk_series(accelerations, times, recorder.step_length)
    refusals = Counter(
        o.action.lane_change_refused for o in observations if o.events.lane_change_refused
    )
    return EpisodeRecord(
        summary=summary,
        jerks=jerks[np.isfinite(jerks)],
        headways=time_headways(gaps, speeds, MIN_MOVING_SPEED),
        ttcs=times_to_collision(gaps, speeds, leader_speeds),
        leader_steps=int(present.sum()),
        lane_count=max(o.ego.lane_count for o in observations),
        lane_change_gaps=lane_change_gaps(observations),
        refusals=dict(refusals),
    )


def drive_recorded(env: Any, driver: Driver, seed: int, episode: int = 0) -> EpisodeRecord:
    """Drive one episode through a `RemoteEnv` and keep its record."""
    from agent_client.drive import record_episode as drive_episode

    return record_episode(drive_episode(env, driver, seed, episode))


def evaluate_driver(
    env: Any,
    driver: Driver,
    seeds: Sequence[int],
    on_episode: Callable[[EpisodeRecord], None] | None = None,
) -> list[EpisodeRecord]:
    """Drive one episode per seed (the same seeds for every driver compared)."""
    records = []
    for index, seed in enumerate(seeds):
        record = drive_recorded(env, driver, seed, index)
        if on_episode is not None:
            on_episode(record)
        records.append(record)
    return records


# --------------------------------------------------------------------------- metrics


def _nan_to_none(value: float) -> float | None:
    return None if value is None or not math.isfinite(value) else float(value)


def headway_stats(headways: np.ndarray) -> dict[str, float | None]:
    """Share of time headways below 1 s, their mean and median (s), and how many there are."""
    headways = np.asarray(headways, dtype=float)
    if len(headways) == 0:
        return {"share_below_1s": 0.0, "mean": None, "median": None, "samples": 0}
    return {
        "share_below_1s": float(np.mean(headways < HEADWAY_SAFE)),
        "mean": float(np.mean(headways)),
        "median": float(np.median(headways)),
        "samples": len(headways),
    }


def ttc_stats(ttcs: np.ndarray, leader_steps: int) -> dict[str, float | None]:
    """Minimum TTC (s) and the share of steps with a leader whose TTC is below 4 s."""
    ttcs = np.asarray(ttcs, dtype=float)
    return {
        "min": float(ttcs.min()) if len(ttcs) else None,
        "share_below_4s": float(np.sum(ttcs < TTC_CRITICAL)) / leader_steps
        if leader_steps
        else 0.0,
    }


def lane_change_frequency(lane_changes: float, distance_m: float, lanes: int) -> float | None:
    """Lane changes per km driven per lane (veh/km/lane, the paper's Table 2 unit)."""
    if distance_m <= 0 or lanes <= 0:
        return None
    return lane_changes / (distance_m / 1000.0 * lanes)


def table3(gaps: Iterable[LaneChangeGap]) -> dict[str, float | int | None]:
    """Average lead and lag time headways at lane-change starts (Table 3)."""
    gaps = list(gaps)
    lead = [g.lead_headway for g in gaps if g.lead_headway is not None]
    lag = [g.lag_headway for g in gaps if g.lag_headway is not None]
    return {
        "lane_changes": len(gaps),
        "lead": float(np.mean(lead)) if lead else None,
        "lag": float(np.mean(lag)) if lag else None,
        "lead_samples": len(lead),
        "lag_samples": len(lag),
    }


def lane_change_stats(
    started: int, refused: int, distance_m: float, lanes: int, episodes: int, aborted: int = 0
) -> dict[str, float | int | None]:
    """Instructions per episode, success rate and frequency from lane-change counts.

    The frequency counts the lane changes made: started and not given up by the simulator.
    """
    instructions = started + refused
    return {
        "started": started,
        "refused": refused,
        "aborted": aborted,
        "instructions_per_episode": instructions / episodes if episodes else None,
        "success_rate": started / instructions if instructions else None,
        "frequency": lane_change_frequency(started - aborted, distance_m, lanes),
    }


def summarise(records: Sequence[EpisodeRecord]) -> dict[str, Any]:
    """Every figure of one driver over its evaluation episodes."""
    if not records:
        raise ValueError("no episodes to summarise")
    summaries = [r.summary for r in records]
    totals = aggregate(summaries)
    headways = np.concatenate([r.headways for r in records])
    ttcs = np.concatenate([r.ttcs for r in records])
    jerks = np.concatenate([r.jerks for r in records])
    ceilings = [s.ceiling_speed for s in summaries if s.ceiling_speed is not None]
    lanes = max(r.lane_count for r in records)
    distance = float(sum(s.distance for s in summaries))
    refusals: Counter[str] = Counter()
    for record in records:
        refusals.update(record.refusals)
    return {
        "episodes": len(records),
        "average_speed": totals["average_speed"],
        "average_speed_sd": totals["average_speed_sd"],
        "ceiling_speed": float(np.mean(ceilings)) if ceilings else None,
        "speed_ratio_to_ceiling": _nan_to_none(totals["speed_ratio_to_ceiling"]),
        "collisions_per_episode": totals["collisions_per_episode"],
        "episodes_with_collision": sum(s.collisions > 0 for s in summaries),
        "jerk_share_above_limit": totals["jerk_share_above_limit"],
        "max_abs_jerk": float(np.max(np.abs(jerks))) if len(jerks) else 0.0,
        "headway": headway_stats(headways),
        "min_time_headway": float(headways.min()) if len(headways) else None,
        "ttc": ttc_stats(ttcs, sum(r.leader_steps for r in records)),
        "distance_km": distance / 1000.0,
        "lanes": lanes,
        "lane_changes": {
            **lane_change_stats(
                sum(s.lane_changes_started for s in summaries),
                sum(s.lane_changes_refused for s in summaries),
                distance,
                lanes,
                len(records),
                sum(s.lane_changes_aborted for s in summaries),
            ),
            "refused_by_reason": dict(sorted(refusals.items())),
        },
        "table3": table3(g for r in records for g in r.lane_change_gaps),
        "end_reasons": dict(sorted(Counter(s.reason for s in summaries).items())),
        "per_episode": {
            "seed": [s.seed for s in summaries],
            "average_speed": [s.average_speed for s in summaries],
            "ceiling_speed": [s.ceiling_speed for s in summaries],
            "collisions": [s.collisions for s in summaries],
            "reason": [s.reason for s in summaries],
        },
    }


def _column(rows: Sequence[Mapping[str, str]], key: str) -> np.ndarray:
    try:
        return np.array([float(row[key]) for row in rows])
    except KeyError as exc:
        raise ValueError(f"the run's episodes.csv has no column {key!r}") from exc


def table2(rows: Sequence[Mapping[str, str]], lanes: int, bins: int = 10) -> list[dict[str, Any]]:
    """Table 2 from a run's ``episodes.csv``: lane-change figures per range of training episodes.

    The episodes are split into `bins` consecutive ranges of (nearly) equal size. The reward of
    successful lane changes is the mean reward of the steps whose instruction started a change
    (None for logs written before it was recorded, or a range without any change).
    """
    if not rows:
        return []
    episodes = _column(rows, "episode").astype(int)
    started = _column(rows, "lane_changes_started")
    refused = _column(rows, "lane_changes_refused")
    distance = _column(rows, "distance")
    lc_reward = _column(rows, "successful_lc_reward") if "successful_lc_reward" in rows[0] else None
    table = []
    for chunk in np.array_split(np.arange(len(rows)), min(bins, len(rows))):
        stats = lane_change_stats(
            int(started[chunk].sum()),
            int(refused[chunk].sum()),
            float(distance[chunk].sum()),
            lanes,
            len(chunk),
        )
        table.append(
            {
                "episodes": f"{episodes[chunk[0]]}-{episodes[chunk[-1]]}",
                "count": len(chunk),
                "instructions_per_episode": stats["instructions_per_episode"],
                "success_rate": stats["success_rate"],
                "reward_of_successful_lc": float(lc_reward[chunk].sum() / started[chunk].sum())
                if lc_reward is not None and started[chunk].sum() > 0
                else None,
                "frequency": stats["frequency"],
            }
        )
    return table


# --------------------------------------------------------------------------- the whole evaluation


@dataclass
class DriverRun:
    """One driver's evaluation episodes."""

    spec: str
    records: list[EpisodeRecord]


@dataclass
class Evaluation:
    """Everything a report needs: the setting, the drivers' episodes, the training log."""

    scenario: str
    seeds: list[int]
    options: dict[str, OptionValue]
    versions: dict[str, str]
    command: str
    policy: DriverRun
    baseline: DriverRun
    cf_policy: DriverRun | None = None
    training_rows: list[dict[str, str]] | None = None
    run_folder: str | None = None
    table2_bins: int = 10

    def drivers(self) -> dict[str, DriverRun]:
        """The compared drivers by role: policy, baseline and (if given) cf_policy."""
        found = {"policy": self.policy, "baseline": self.baseline}
        if self.cf_policy is not None:
            found["cf_policy"] = self.cf_policy
        return found

    @property
    def lanes(self) -> int:
        return max(r.lane_count for run in self.drivers().values() for r in run.records)
