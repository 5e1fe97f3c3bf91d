"""The acceptance criteria of a greedy evaluation, and the screen that tells when an evaluation
under way can no longer meet them."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from agent_client.evaluation.metrics import EpisodeSummary, aggregate
from agent_client.evaluation.targets import (
    CEILING_TARGET,
    HEADWAY_TARGET,
    JERK_TARGET,
    FailureScreen,
    judge,
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
        "no_red_lights": {"red_lights_per_episode": 0.05},
        "shielded_rarely": {"safety_share": 0.021},
    }
    for name, change in cases.items():
        met = targets_met(figures(**change), IDM)
        assert [k for k, ok in met.items() if not ok] == [name]


def test_without_a_ceiling_anywhere_the_ceiling_target_does_not_apply() -> None:
    no_ceiling = {**IDM, "speed_ratio_to_ceiling": math.nan}
    assert targets_met(figures(speed_ratio_to_ceiling=math.nan), no_ceiling)["near_ceiling"]


def test_the_ceiling_asked_is_no_more_than_the_reference_reaches() -> None:
    trailing = {**IDM, "speed_ratio_to_ceiling": 0.9}  # a merging reference behind its leader
    assert targets_met(figures(speed_ratio_to_ceiling=0.91), trailing)["near_ceiling"]
    assert not targets_met(figures(speed_ratio_to_ceiling=0.89), trailing)["near_ceiling"]
    ahead = {**IDM, "speed_ratio_to_ceiling": 1.1}
    assert not targets_met(figures(speed_ratio_to_ceiling=0.97), ahead)["near_ceiling"]


def test_where_a_route_changes_lanes_a_ceiling_the_reference_trails_is_no_target() -> None:
    """The leader-at-entry is no bound where the ego changes lanes: the speed is judged against
    the reference (as_fast_as_idm), not again on the few episodes with a ceiling."""
    trailing = {**IDM, "speed_ratio_to_ceiling": 0.82, "route_lanes": 1}
    assert targets_met(figures(speed_ratio_to_ceiling=0.80), trailing)["near_ceiling"]
    assert not targets_met(figures(average_speed=13.9), trailing)["as_fast_as_idm"]
    reaching = {**IDM, "speed_ratio_to_ceiling": 1.05, "route_lanes": 1}  # there it holds
    assert not targets_met(figures(speed_ratio_to_ceiling=0.97), reaching)["near_ceiling"]


def test_on_a_road_with_a_lane_end_every_episode_must_arrive() -> None:
    routed = {**IDM, "route_lanes": 1, "arrival_share": 0.9}
    assert not targets_met(figures(arrival_share=0.95), routed)["arrives"]
    assert targets_met(figures(arrival_share=1.0), routed)["arrives"]
    assert targets_met(figures(arrival_share=0.0), IDM)["arrives"]  # an open road: any end


def test_the_screen_fails_arrives_at_the_first_episode_that_does_not() -> None:
    screen = FailureScreen(seeds=4, idm_speed=14.0, routed={1, 3})
    assert screen.failed([summary()], remaining(1)) is None
    stood = dataclasses.replace(summary(), reason="lane_end", episode=1)
    assert screen.failed([summary(), stood], remaining(2)) == "arrives"
    assert FailureScreen(seeds=4, idm_speed=14.0).failed([stood], remaining(1)) is None
    # Seed 0's scenario has no lane end (cflc in a mix): an episode that does not arrive there
    # (a time limit) fails nothing.
    timed_out = dataclasses.replace(summary(), reason="time_limit", episode=0)
    assert screen.failed([timed_out], remaining(1)) is None


def summary(
    speed: float = 14.0,
    steps: int = 1000,
    jerk: float = 0.0,
    headway: float = 0.0,
    collisions: int = 0,
    ceiling: float = 14.2,
) -> EpisodeSummary:
    """An episode with these figures (the rest plausible)."""
    return EpisodeSummary(
        episode=0, seed=0, steps=steps, reason="end_of_road", duration=steps / 10,
        distance=speed * steps / 10, average_speed=speed, collisions=collisions,
        jerk_share_above_limit=jerk, max_abs_jerk=0.0, headway_share_below_1s=headway,
        min_time_headway=None, min_ttc=None, ceiling_speed=ceiling,
        speed_ratio_to_ceiling=speed / ceiling, total_reward=0.0, lane_changes_started=0,
        lane_changes_refused=0, headway_samples=steps + 1,
    )  # fmt: skip


def remaining(done: int, seeds: int = 4) -> list[int]:
    return list(range(done, seeds))


def test_a_collision_fails_at_once() -> None:
    screen = FailureScreen(seeds=4, idm_speed=14.0)
    assert screen.failed([summary(collisions=1)], remaining(1)) == "no_collisions"
    assert screen.failed([summary()], remaining(1)) is None


def test_jerk_fails_only_once_even_the_longest_smooth_episodes_cannot_dilute_it() -> None:
    # 10 % of 1000 steps: 100 exceedances; three more clean episodes of up to 1000 steps give
    # 100 / 4000 = 2.5 % (can still pass), of up to 3000 steps 100 / 10000 = 1 %.
    assert FailureScreen(4, 14.0, max_steps=1000).failed([summary(jerk=0.10)], remaining(1)) is None
    heavy = [summary(jerk=0.11)]  # 110 / 4000 = 2.75 % > 2.6 %: failed for certain
    assert FailureScreen(4, 14.0, max_steps=1000).failed(heavy, remaining(1)) == "comfortable"
    assert FailureScreen(4, 14.0, max_steps=3000).failed(heavy, remaining(1)) is None
    assert FailureScreen(4, 14.0).failed(heavy, remaining(1)) is None  # no bound on the steps


def test_headway_fails_once_the_share_is_certain_to_stay_above_its_target() -> None:
    screen = FailureScreen(4, 14.0, max_steps=1000)
    assert screen.failed([summary(headway=0.5)], remaining(1)) == "safe_headway"
    assert screen.failed([summary(headway=0.15)], remaining(1)) is None


def test_speed_fails_once_the_ceiling_on_every_seed_left_cannot_reach_idm() -> None:
    bounds = [14.2] * 4
    screen = FailureScreen(4, 14.0, speed_bounds=bounds)
    assert screen.failed([summary(speed=13.5)], remaining(1)) is None  # 13.5 + 3 x 14.2 > 56
    slow = [summary(speed=13.5, ceiling=14.2)] * 3  # 3 x 13.5 + 14.2 < 56
    assert screen.failed(slow, remaining(3)) == "as_fast_as_idm"
    assert FailureScreen(4, 14.0).failed(slow, remaining(3)) is None  # several lanes: at the end


def test_near_ceiling_fails_once_ratios_of_one_on_every_seed_left_cannot_reach_it() -> None:
    screen = FailureScreen(4, 10.0, speed_bounds=[14.2] * 4)  # IDM's speed is easy here
    far = [summary(speed=13.2), summary(speed=13.2)]  # (2 x 0.930 + 2) / 4 = 0.965 < 0.98
    assert screen.failed(far, remaining(2)) == "near_ceiling"
    assert screen.failed(far[:1], remaining(1)) is None  # (0.930 + 3) / 4 = 0.983


def test_the_screen_never_stops_an_evaluation_that_would_pass() -> None:
    """On random evaluations within the bounds: whenever a prefix is called failed, the whole
    evaluation fails that very target (and one that passes is never stopped)."""
    rng = np.random.default_rng(0)
    seeds, max_steps = 6, 1500
    for _ in range(3000):
        ceilings = rng.uniform(11.0, 18.0, seeds)
        episodes = [
            summary(
                speed=float(c * rng.uniform(0.95, 1.0)),
                steps=int(rng.integers(300, max_steps)),
                jerk=float(rng.choice([0.0, rng.uniform(0, 0.08)])),
                headway=float(rng.choice([0.0, rng.uniform(0, 0.2)])),
                collisions=int(rng.random() < 0.02),
                ceiling=float(c),
            )
            for c in ceilings
        ]
        idm = float(np.mean(ceilings * rng.uniform(0.97, 0.99, seeds)))
        met = targets_met(aggregate(episodes), {"average_speed": idm})
        screen = FailureScreen(seeds, idm, max_steps, list(ceilings))
        for done in range(1, seeds):
            verdict = screen.failed(episodes[:done], remaining(done, seeds))
            assert verdict is None or not met[verdict], (verdict, met)


def test_over_several_scenarios_shares_and_speed_are_judged_on_the_whole_evaluation() -> None:
    """A scenario a hair slower than its reference passes where the evaluation as a whole is
    as fast; a collision or a missed arrival on one scenario fails the evaluation."""
    routed = {**IDM, "route_lanes": 1}
    slower = figures(average_speed=13.9, arrival_share=1.0)
    faster = figures(average_speed=14.3, arrival_share=1.0)
    whole = (figures(average_speed=14.1, arrival_share=1.0), routed)
    met, missed = judge({"merge": (slower, routed), "exit": (faster, routed)}, whole)
    assert all(met.values()) and missed == ""
    slow_whole = (figures(average_speed=13.95, arrival_share=1.0), routed)
    met, missed = judge({"merge": (slower, routed), "exit": (faster, routed)}, slow_whole)
    assert [t for t, ok in met.items() if not ok] == ["as_fast_as_idm"]
    assert missed == "all: as_fast_as_idm"
    stuck = figures(average_speed=14.3, arrival_share=0.9)
    met, missed = judge({"merge": (stuck, routed), "exit": (faster, routed)}, whole)
    assert [t for t, ok in met.items() if not ok] == ["arrives"] and missed == "merge: arrives"
    alone = judge({"merge": (slower, routed)}, (slower, routed))  # one scenario: as before
    assert alone == (targets_met(slower, routed), "merge: as_fast_as_idm")


def test_a_driver_that_must_beat_its_reference_needs_the_gain_and_a_rare_shield() -> None:
    reference = {"average_speed": 20.0}
    equal = figures(average_speed=20.0, safety_share=0.0)
    assert targets_met(equal, reference)["as_fast_as_idm"]
    assert not targets_met(equal, reference, speed_gain=0.01)["as_fast_as_idm"]
    assert targets_met({**equal, "average_speed": 20.21}, reference, 0.01)["as_fast_as_idm"]
    shielded = {**equal, "safety_share": 0.03}
    assert not targets_met(shielded, reference)["shielded_rarely"]
    assert not targets_met({**equal, "red_lights_per_episode": 0.1}, reference)["no_red_lights"]
