"""What a training run's evaluations are judged against: the reference driver's figures on the
held-out evaluation seeds, over all of them, per scenario and per seed.

The reference (IDM, or IDM + MOBIL where lanes change: `TrainConfig.reference`) drives the
evaluation seeds once, before the first policy evaluation. Each policy evaluation is then
judged on the same seeds (`agent_client.evaluation.targets.judge`): against each scenario's own
figures, and over the whole evaluation against the reference's speed on the seeds the policy
drove. Its `FailureScreen` stops an evaluation once it has certainly failed.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from agent_client.evaluation.metrics import EpisodeSummary, aggregate
from agent_client.evaluation.targets import FailureScreen, ceiling_target, judge


class Reference:
    """The reference's figures on the evaluation seeds, and the verdicts of evaluations on them."""

    def __init__(
        self, seeds: Sequence[int], scenario_for: Callable[[int], str], speed_gain: float = 0.0
    ) -> None:
        """`seeds`: the evaluation seeds in order (an episode's index is its seed's);
        `scenario_for`: the scenario a seed picks; `speed_gain`: how much faster than the
        reference a policy must drive (`TrainConfig.speed_gain`)."""
        self.seeds = list(seeds)
        self.speed_gain = speed_gain
        self.scenario_for = scenario_for
        self.overall: dict[str, float] | None = None
        """Over all its episodes (None until it has driven them)."""
        self.by_scenario: dict[str, dict[str, float]] = {}
        self.speeds: list[float] = []
        """Its average speed per seed: the same seeds' figure for an evaluation stopped early."""
        self.ceilings: list[float] | None = None
        """The leader-at-entry ceiling per seed: a bound on any driver's average speed there on
        one lane (None where one is missing, or where the reference did not reach the end of
        the road within the time limit: a drive cut short may average more than its leader's
        whole trip)."""

    @property
    def known(self) -> bool:
        return self.overall is not None

    def book(self, summaries: Sequence[EpisodeSummary]) -> dict[str, float]:
        """Keep the reference's figures from its episodes on the seeds; returns the overall."""
        self.overall = aggregate(summaries)
        self.by_scenario = {name: aggregate(group) for name, group in self.group(summaries).items()}
        ceilings = [s.ceiling_speed for s in summaries]
        self.speeds = [s.average_speed for s in summaries]
        known = [c for c in ceilings if c is not None]
        arrived = all(s.reason == "end_of_road" for s in summaries)
        self.ceilings = known if len(known) == len(ceilings) and arrived else None
        return self.overall

    def group(self, summaries: Sequence[EpisodeSummary]) -> dict[str, list[EpisodeSummary]]:
        """Episodes grouped by the scenario of their seed (an insertion retry kept the scenario,
        not the seed)."""
        groups: dict[str, list[EpisodeSummary]] = {}
        for summary in summaries:
            groups.setdefault(self.scenario_for(self.seeds[summary.episode]), []).append(summary)
        return groups

    def targets(self, summaries: Sequence[EpisodeSummary]) -> tuple[dict[str, bool], str]:
        """Which targets an evaluation meets against the reference on the same seeds, and what
        missed which (`judge`)."""
        assert self.overall is not None
        scenarios = {
            name: (aggregate(group), self.by_scenario[name])
            for name, group in self.group(summaries).items()
        }
        whole = {**self.overall, "average_speed": self.speed_on(summaries)}
        return judge(scenarios, (aggregate(summaries), whole), self.speed_gain)

    def speed_on(self, summaries: Sequence[EpisodeSummary]) -> float:
        """The reference's average speed on the seeds these episodes drove (all of them unless
        an evaluation stopped early, or its per-seed figures are unknown)."""
        assert self.overall is not None
        indices = [s.episode for s in summaries]
        if len(indices) == len(self.speeds) or not all(0 <= i < len(self.speeds) for i in indices):
            return self.overall["average_speed"]
        return float(np.mean([self.speeds[i] for i in indices]))

    def screen(self, max_steps: int | None, one_lane: bool) -> FailureScreen:
        """What lets an evaluation stop once it has certainly failed: `max_steps` (the
        scenario's time limit) bounds an episode's steps, and on one lane the reference's
        ceilings bound every seed's speed; where the reference's route changed lanes, every
        episode must arrive."""
        assert self.overall is not None
        routed = {  # where the reference's route made it change lanes: there it must arrive
            index
            for index, seed in enumerate(self.seeds)
            if self.by_scenario.get(self.scenario_for(seed), {}).get("route_lanes", 0) > 0
        }
        ceilings = self.ceilings
        bounds = ceilings if one_lane and ceilings and len(ceilings) == len(self.seeds) else None
        return FailureScreen(
            len(self.seeds), (1.0 + self.speed_gain) * self.overall["average_speed"], max_steps,
            bounds, routed,
            ceiling_target(self.overall),
        )  # fmt: skip

    def state_dict(self) -> dict[str, Any]:
        """The figures for a checkpoint (the keys older checkpoints have)."""
        return {
            "idm_eval": self.overall,
            "reference_figures": self.by_scenario,
            "idm_speeds": self.speeds,
            "idm_ceilings": self.ceilings,
        }

    def load_state_dict(self, state: dict[str, Any], first_scenario: str) -> None:
        """Restore `state_dict()`; one written before the figures per scenario holds only
        `first_scenario`'s."""
        self.overall = state["idm_eval"]
        self.by_scenario = state.get("reference_figures") or (
            {first_scenario: self.overall} if self.overall else {}
        )
        self.speeds = state.get("idm_speeds") or []
        self.ceilings = state.get("idm_ceilings")
