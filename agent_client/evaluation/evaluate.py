"""Evaluate drivers on the same seeds and keep what the paper's §4.4-4.5 figures are made of.

Each episode is driven through `agent_client.drivers.episode.run_episode` and kept as an
`EpisodeRecord`: the summary of `agent_client.evaluation.metrics` plus the samples behind the
distributions (jerk, time headway, time to collision) and the target-lane gaps at each
lane-change start. An `Evaluation` holds every driver's records and the setting;
`agent_client.evaluation.summaries` turns records into figures and
`agent_client.evaluation.report` writes them out.

Table 3's headways are taken at the observation before a lane change starts (the state the
decision was made on): the gap to the leader (lead) and to the follower (lag) in the target lane,
each divided by the ego's speed; a missing vehicle gives no headway.
"""

from __future__ import annotations

import itertools
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from agent_client.constants import MIN_MOVING_SPEED
from agent_client.drivers.episode import Driver, Episode, run_episode
from agent_client.envs.remote_env import RemoteEnv
from agent_client.evaluation.metrics import EpisodeSamples, EpisodeSummary, episode_summary
from agent_client.evaluation.routes import RouteChange, route_changes
from agent_client.evaluation.trajectories import EpisodeTrace
from protocol.messages import Observation, OptionValue, Safety

ROLE_LABELS = {
    "policy": "policy",
    "baseline": "baseline",
    "reference": "reference",
    "cf_policy": "CF-only policy",
}
"""How the report names each role of `Evaluation.drivers`."""


@dataclass(frozen=True)
class LaneChangeGap:
    """Target-lane time headways (s) when a lane change starts; None when no vehicle is there."""

    direction: int
    lead_headway: float | None
    lag_headway: float | None


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
    """Refused lane changes by `protocol.messages.LaneChangeRefusal` value."""
    trace: EpisodeTrace | None = None
    """The ego's and its neighbours' trajectories, for the report's pictures of an episode."""
    safety: Safety | None = None
    """The simulator's surrogate safety measures of the episode (None if not reported)."""
    route_changes: list[RouteChange] = field(default_factory=list)
    """The lane changes it started towards its route (`agent_client.evaluation.routes`)."""

    @classmethod
    def from_episode(cls, episode: Episode) -> EpisodeRecord:
        """The record of a driven episode: summary, samples, lane-change gaps and refusals."""
        observations = episode.observations
        summary = episode_summary(episode)
        samples = EpisodeSamples.from_observations(observations, episode.step_length)
        refusals = Counter(
            o.action.lane_change_refused for o in observations if o.events.lane_change_refused
        )
        return cls(
            summary=summary,
            jerks=samples.jerks,
            headways=samples.headways,
            ttcs=samples.ttcs,
            leader_steps=samples.leader_steps,
            lane_count=max(o.ego.lane_count for o in observations),
            lane_change_gaps=lane_change_gaps(observations),
            refusals=dict(refusals),
            trace=EpisodeTrace.from_observations(observations, episode.step_length, episode.seed),
            safety=observations[-1].safety,
            route_changes=route_changes(observations),
        )


def evaluate_driver(
    env: RemoteEnv,
    driver: Driver,
    seeds: Sequence[int],
    on_episode: Callable[[EpisodeRecord], None] | None = None,
) -> list[EpisodeRecord]:
    """Drive one episode per seed (the same seeds for every driver compared), with the
    simulator's surrogate safety measures where the scenario offers them (option ``ssm``)."""
    records = []
    measures: dict[str, OptionValue] = {"ssm": True} if _offers_ssm(env) else {}
    for index, seed in enumerate(seeds):
        episode = run_episode(env, driver, seed, index, options=measures)
        record = EpisodeRecord.from_episode(episode)
        if on_episode is not None:
            on_episode(record)
        records.append(record)
    return records


def _offers_ssm(env: RemoteEnv) -> bool:
    """The server measures safety (protocol 1.3, option ``ssm``) and the user did not say no."""
    return (
        env.welcome.protocol >= (1, 3)
        and "ssm" in env.scenario_options
        and "ssm" not in env.options
    )


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
    reference: DriverRun | None = None
    """A second baseline on the same seeds (the simulator's own driver, ``sumo``)."""
    training_rows: list[dict[str, str]] | None = None
    run_folder: str | None = None
    table2_bins: int = 10

    def drivers(self) -> dict[str, DriverRun]:
        """The compared drivers by role: policy, baseline and (if given) reference and
        cf_policy."""
        found = {"policy": self.policy, "baseline": self.baseline}
        if self.reference is not None:
            found["reference"] = self.reference
        if self.cf_policy is not None:
            found["cf_policy"] = self.cf_policy
        return found

    @property
    def lanes(self) -> int:
        return max(r.lane_count for run in self.drivers().values() for r in run.records)
