"""A driver's figures over its evaluation episodes, and the lane-change tables (Tables 2-3).

`summarise` extends `agent_client.evaluation.metrics.aggregate` (the figures training and
``agent-client drive`` report too, under the same names) with those only the samples give.
Definitions, all over the steps of the evaluation episodes:

* time headway: gap / ego speed on steps with a leader and the ego moving;
* time to collision (TTC): gap / closing speed on steps where the ego is faster than its leader;
  the share of TTC < 4 s is over the steps with a leader;
* lane-change instructions: lane changes started + refused (any reason); success rate: started /
  instructions; frequency: lane changes made / (km driven x lanes), in veh/km/lane.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from agent_client.constants import HEADWAY_SAFE, TTC_CRITICAL
from agent_client.evaluation.evaluate import EpisodeRecord, LaneChangeGap
from agent_client.evaluation.metrics import EpisodeSummary, aggregate
from agent_client.evaluation.routes import min_pet, route_figures
from agent_client.evaluation.safety import safety_figures


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
    """Every figure of one driver over its evaluation episodes: `aggregate`'s and the samples'."""
    summaries = [r.summary for r in records]
    figures: dict[str, Any] = dict(aggregate(summaries))
    headways = np.concatenate([r.headways for r in records])
    jerks = np.concatenate([r.jerks for r in records])
    ceilings = [s.ceiling_speed for s in summaries if s.ceiling_speed is not None]
    figures.update(
        {
            "ceiling_speed": float(np.mean(ceilings)) if ceilings else None,
            "episodes_with_collision": sum(s.collisions > 0 for s in summaries),
            "episodes_with_red_light": sum(s.red_lights > 0 for s in summaries),
            "max_abs_jerk": float(np.max(np.abs(jerks))) if len(jerks) else 0.0,
            "headway": headway_stats(headways),
            "min_time_headway": float(headways.min()) if len(headways) else None,
            "ttc": ttc_stats(
                np.concatenate([r.ttcs for r in records]), sum(r.leader_steps for r in records)
            ),
            **_lane_change_figures(records),
            "safety": safety_figures(records),
            "end_reasons": dict(sorted(Counter(s.reason for s in summaries).items())),
            "per_episode": _per_episode(summaries),
            "route": route_figures(
                [s.reason for s in summaries],
                [r.route_changes for r in records],
                [min_pet(r.safety) for r in records],
            )
            if any(s.route_lanes for s in summaries)
            else None,
        }
    )
    return figures


def _lane_change_figures(records: Sequence[EpisodeRecord]) -> dict[str, Any]:
    """Distance, lanes, lane-change counts and rates, refusals by reason and Table 3."""
    summaries = [r.summary for r in records]
    lanes = max(r.lane_count for r in records)
    distance = float(sum(s.distance for s in summaries))
    refusals: Counter[str] = Counter()
    for record in records:
        refusals.update(record.refusals)
    stats = lane_change_stats(
        sum(s.lane_changes_started for s in summaries),
        sum(s.lane_changes_refused for s in summaries),
        distance,
        lanes,
        len(records),
        sum(s.lane_changes_aborted for s in summaries),
    )
    return {
        "distance_km": distance / 1000.0,
        "lanes": lanes,
        "lane_changes": {**stats, "refused_by_reason": dict(sorted(refusals.items()))},
        "table3": table3(g for r in records for g in r.lane_change_gaps),
    }


def _per_episode(summaries: Sequence[EpisodeSummary]) -> dict[str, list[Any]]:
    """The per-episode figures the speed plot and the ceiling comparison need."""
    return {
        "seed": [s.seed for s in summaries],
        "average_speed": [s.average_speed for s in summaries],
        "ceiling_speed": [s.ceiling_speed for s in summaries],
        "collisions": [s.collisions for s in summaries],
        "reason": [s.reason for s in summaries],
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
    (None when the log has no such column or the range no lane change).
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
