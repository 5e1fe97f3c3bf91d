"""The acceptance criteria of a greedy evaluation: when a policy counts as good enough.

Training stops after enough evaluations in a row meet all of them (docs/learner.md), and the
evaluation report applies the same criteria to the policy against its baseline.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass

from agent_client.evaluation.metrics import EpisodeSummary
from agent_client.evaluation.paper import DRL_JERK_SHARE_ABOVE_LIMIT
from protocol.messages import EndReason

JERK_TARGET = DRL_JERK_SHARE_ABOVE_LIMIT
"""Share of jerk samples above 5.6 m/s^3 allowed: no more than the paper's DRL driver."""
HEADWAY_TARGET = 0.05
"""Share of time headways under 1 s allowed."""
CEILING_TARGET = 0.98
"""Average speed required, as a share of the leader-at-entry ceiling."""
SAFETY_TARGET = 0.02
"""Share of decisions the safety layer may have overridden (`agent_client.drivers.safety`): a
policy that needs the shield more often has not learned the rules it enforces."""
BOUND_SLACK = 1e-3
"""Relative margin on a speed bound in `FailureScreen`: measurement at the road's end (the
last observation, the leader's arrival step) may put a driver a hair above its ceiling."""


def targets_met(
    policy: Mapping[str, float], idm: Mapping[str, float], speed_gain: float = 0.0
) -> dict[str, bool]:
    """Which criteria the policy's figures meet against the reference's (IDM's, or IDM +
    MOBIL's where the road needs lane changes) on the same seeds.

    Both are `agent_client.evaluation.metrics.aggregate` figures (or `summarise`'s, a superset).
    No collision and no red light passed (protocol 1.8) are hard targets: a single one fails.
    ``as_fast_as_idm`` asks the reference's speed times 1 + `speed_gain` (a learned driver
    that must be better than its reference, not equal to it); ``shielded_rarely`` at most
    `SAFETY_TARGET` of decisions overridden by the safety layer.
    ``near_ceiling`` asks `CEILING_TARGET` of the leader-at-entry ceiling, or as much as the
    reference reaches where that is less (on a road of several lanes the ceiling is no bound: a
    merging reference may trail the leader that entered ahead of it); a policy without a ceiling
    fails it unless the reference has none either (a ring; routes that no leader at entry shares):
    then it does not apply. On a road with a lane end or an exit every episode must reach the end of
    the route (``arrives``); elsewhere that target does not apply. There the leader-at-entry is
    no bound either: where the reference reaches less than `CEILING_TARGET` of its ceiling,
    ``near_ceiling`` does not apply (``as_fast_as_idm`` compares the speed with the reference's
    on every episode; ``near_ceiling`` would compare it again on the one or two with a ceiling).
    """
    ratio, reference = policy["speed_ratio_to_ceiling"], idm.get("speed_ratio_to_ceiling")
    unknown = math.isnan(ratio) and reference is not None and math.isnan(reference)
    routed = policy.get("route_lanes", 0) > 0 or idm.get("route_lanes", 0) > 0
    unbound = routed and ceiling_target(idm) < CEILING_TARGET
    return {
        "no_collisions": policy["collisions_per_episode"] == 0,
        "no_red_lights": policy.get("red_lights_per_episode", 0.0) == 0,
        "comfortable": policy["jerk_share_above_limit"] <= JERK_TARGET,
        "safe_headway": policy["headway_share_below_1s"] <= HEADWAY_TARGET,
        "as_fast_as_idm": policy["average_speed"] >= (1.0 + speed_gain) * idm["average_speed"],
        "near_ceiling": unknown or unbound or ratio >= ceiling_target(idm),
        "arrives": not routed or policy.get("arrival_share", 0.0) >= 1.0,
        "shielded_rarely": policy.get("safety_share", 0.0) <= SAFETY_TARGET,
    }


EVALUATION_TARGETS = (
    "comfortable",
    "safe_headway",
    "as_fast_as_idm",
    "near_ceiling",
    "shielded_rarely",
)
"""The targets an evaluation over several scenarios meets as a whole: shares of its time and its
average speed, over all its episodes against the reference's on the same seeds. Per scenario,
ten episodes make these figures noisier than the margin a good policy keeps: a policy faster
than IDM + MOBIL on every scenario over 50 held-out seeds missed ``as_fast_as_idm`` on one
scenario or another in 7 of 12 evaluations (docs/learner-design.md); the leader-at-entry ceiling,
where only one or two of a scenario's ten episodes have one, likewise. What single episodes
decide (a collision, a red light, an arrival) stays per scenario."""


def judge(
    scenarios: Mapping[str, tuple[Mapping[str, float], Mapping[str, float]]],
    whole: tuple[Mapping[str, float], Mapping[str, float]],
    speed_gain: float = 0.0,
) -> tuple[dict[str, bool], str]:
    """Which targets an evaluation meets, and what missed which (``merge: arrives; all:
    as_fast_as_idm``): `scenarios` maps each scenario to its (policy, reference) figures,
    `whole` holds them over all the evaluation's episodes (`EVALUATION_TARGETS` are judged
    there where there are several scenarios)."""
    met: dict[str, bool] = {}
    missed: list[str] = []

    def book(name: str, verdict: Mapping[str, bool]) -> None:
        for target, passed in verdict.items():
            met[target] = met.get(target, True) and passed
        failed = [target for target, passed in verdict.items() if not passed]
        if failed:
            missed.append(f"{name}: {', '.join(failed)}")

    pooled = EVALUATION_TARGETS if len(scenarios) > 1 else ()
    for name, (policy, reference) in scenarios.items():
        verdict = targets_met(policy, reference, speed_gain)
        book(name, {t: ok for t, ok in verdict.items() if t not in pooled})
    overall = targets_met(*whole, speed_gain)
    if pooled:
        book("all", {t: ok for t, ok in overall.items() if t in pooled})
    return {t: met[t] for t in overall if t in met}, "; ".join(missed)


def ceiling_target(reference: Mapping[str, float]) -> float:
    """The share of the ceiling ``near_ceiling`` asks: `CEILING_TARGET`, or what the reference
    reached where that is less."""
    ratio = reference.get("speed_ratio_to_ceiling")
    if ratio is None or not math.isfinite(ratio):
        return CEILING_TARGET
    return min(CEILING_TARGET, ratio)


@dataclass(frozen=True)
class FailureScreen:
    """Tells, from the episodes an evaluation has finished, when it can no longer pass.

    Exact, not a guess: a target counts as failed only when the best the remaining episodes can
    do (no jerk or headway exceedance in the longest episode possible, the speed bound on every
    seed) cannot lift the figures over it, so stopping there never loses a pass.
    """

    seeds: int
    """Episodes in the whole evaluation."""
    idm_speed: float
    """IDM's average speed on the same seeds: the `as_fast_as_idm` target."""
    max_steps: int | None = None
    """The most steps an episode can last (the scenario's time limit); None: jerk and headway
    are judged only at a collision or at the end."""
    speed_bounds: Sequence[float] | None = None
    """Per seed (in evaluation order), the highest average speed any driver can reach: on one
    lane the leader-at-entry ceiling, which IDM's episode on that seed measured. None where a
    driver can pass its leader (several lanes): the speed targets are judged at the end."""
    routed: Collection[int] = frozenset()
    """The seed indices (in evaluation order) whose road has a lane end or an exit: there an
    episode that does not reach the end of the route fails ``arrives``."""
    ceiling: float = CEILING_TARGET
    """The share of the ceiling ``near_ceiling`` asks (`ceiling_target`)."""

    def failed(self, done: Sequence[EpisodeSummary], remaining: Sequence[int]) -> str | None:
        """The first target that `done` has already failed, whatever the seed indices in
        `remaining` give; None while every target can still be met."""
        if any(s.collisions for s in done):
            return "no_collisions"
        if any(s.red_lights for s in done):
            return "no_red_lights"
        if any(s.episode in self.routed and s.reason != EndReason.END_OF_ROAD for s in done):
            return "arrives"
        left = len(remaining)
        if self.max_steps is not None:
            steps = sum(s.steps for s in done) + left * self.max_steps
            exceeded = sum(s.jerk_share_above_limit * s.steps for s in done)
            if steps and exceeded / steps > JERK_TARGET:
                return "comfortable"
            samples = sum(s.headway_samples for s in done) + left * (self.max_steps + 1)
            below = sum(round(s.headway_share_below_1s * s.headway_samples) for s in done)
            if samples and below / samples > HEADWAY_TARGET:
                return "safe_headway"
            if steps and sum(s.safety_steps for s in done) / steps > SAFETY_TARGET:
                return "shielded_rarely"
        if self.speed_bounds is not None and done:
            bound = (1 + BOUND_SLACK) * sum(self.speed_bounds[i] for i in remaining)
            if (sum(s.average_speed for s in done) + bound) / self.seeds < self.idm_speed:
                return "as_fast_as_idm"
            ratios = [s.speed_ratio_to_ceiling for s in done]
            best_ratios = sum(r or 0.0 for r in ratios) + (1 + BOUND_SLACK) * left
            if None not in ratios and best_ratios / self.seeds < self.ceiling:
                return "near_ceiling"
        return None
