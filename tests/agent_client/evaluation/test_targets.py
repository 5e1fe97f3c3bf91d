"""The acceptance criteria of a greedy evaluation."""

from __future__ import annotations

import math

from agent_client.evaluation.targets import (
    CEILING_TARGET,
    HEADWAY_TARGET,
    JERK_TARGET,
    targets_met,
)

IDM = {"average_speed": 14.0}


def figures(**changes: float) -> dict[str, float]:
    passing = {
        "collisions_per_episode": 0.0,
        "jerk_share_above_limit": JERK_TARGET,
        "headway_share_below_1s": HEADWAY_TARGET,
        "average_speed": 14.0,
        "speed_ratio_to_ceiling": CEILING_TARGET,
    }
    return {**passing, **changes}


def test_every_target_met_at_its_limit() -> None:
    assert all(targets_met(figures(), IDM).values())


def test_each_target_fails_alone() -> None:
    cases = {
        "no_collisions": {"collisions_per_episode": 0.05},
        "comfortable": {"jerk_share_above_limit": JERK_TARGET + 1e-6},
        "safe_headway": {"headway_share_below_1s": HEADWAY_TARGET + 1e-6},
        "as_fast_as_idm": {"average_speed": 13.99},
        "near_ceiling": {"speed_ratio_to_ceiling": math.nan},  # no ceiling: not near it
    }
    for name, change in cases.items():
        met = targets_met(figures(**change), IDM)
        assert [k for k, ok in met.items() if not ok] == [name]
