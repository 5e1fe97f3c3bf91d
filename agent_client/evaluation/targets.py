"""The acceptance criteria of a greedy evaluation: when a policy counts as good enough.

Training stops after enough evaluations in a row meet all of them (docs/learner.md), and the
evaluation report applies the same criteria to the policy against its baseline.
"""

from __future__ import annotations

from collections.abc import Mapping

from agent_client.evaluation.paper import DRL_JERK_SHARE_ABOVE_LIMIT

JERK_TARGET = DRL_JERK_SHARE_ABOVE_LIMIT
"""Share of jerk samples above 5.6 m/s^3 allowed: no more than the paper's DRL driver."""
HEADWAY_TARGET = 0.05
"""Share of time headways under 1 s allowed."""
CEILING_TARGET = 0.98
"""Average speed required, as a share of the leader-at-entry ceiling."""


def targets_met(policy: Mapping[str, float], idm: Mapping[str, float]) -> dict[str, bool]:
    """Which criteria the policy's figures meet against the IDM baseline's.

    Both are `agent_client.evaluation.metrics.aggregate` figures (or `summarise`'s, a superset).
    """
    return {
        "no_collisions": policy["collisions_per_episode"] == 0,
        "comfortable": policy["jerk_share_above_limit"] <= JERK_TARGET,
        "safe_headway": policy["headway_share_below_1s"] <= HEADWAY_TARGET,
        "as_fast_as_idm": policy["average_speed"] >= idm["average_speed"],
        "near_ceiling": policy["speed_ratio_to_ceiling"] >= CEILING_TARGET,
    }
