"""The reference's figures on the evaluation seeds, and evaluations judged against them."""

from __future__ import annotations

import dataclasses

import pytest

from agent_client.evaluation.metrics import EpisodeSummary
from agent_client.training.evaluations.reference import Reference
from tests.agent_client.evaluation.test_targets import summary

SEEDS = [100, 101, 102, 103]


def scenario_for(seed: int) -> str:
    return "merge" if seed % 2 == 0 else "cf"


def episodes(speeds: list[float], **changes: object) -> list[EpisodeSummary]:
    return [
        dataclasses.replace(summary(speed), episode=i, seed=SEEDS[i], **changes)  # type: ignore[arg-type]
        for i, speed in enumerate(speeds)
    ]


def test_the_reference_is_booked_over_all_per_scenario_and_per_seed() -> None:
    reference = Reference(SEEDS, scenario_for)
    assert not reference.known
    overall = reference.book(episodes([10.0, 12.0, 14.0, 16.0]))
    assert reference.known and overall["average_speed"] == pytest.approx(13.0)
    assert reference.by_scenario["merge"]["average_speed"] == pytest.approx(12.0)
    assert reference.by_scenario["cf"]["average_speed"] == pytest.approx(14.0)
    assert reference.ceilings == [14.2] * 4
    assert reference.speed_on(episodes([0.0, 0.0])) == pytest.approx(11.0)  # seeds 0 and 1
    stopped = Reference(SEEDS, scenario_for)
    stopped.book(episodes([10.0] * 4, reason="time_limit"))
    assert stopped.ceilings is None  # a drive cut short may beat its leader's whole trip


def test_a_policy_faster_than_the_reference_on_its_seeds_meets_the_speed_target() -> None:
    reference = Reference(SEEDS, scenario_for)
    reference.book(episodes([10.0, 12.0, 14.0, 16.0]))
    met, missed = reference.targets(episodes([10.5, 12.5, 14.0, 16.0]))
    assert met["as_fast_as_idm"] and missed == ""
    met, missed = reference.targets(episodes([9.0, 12.0]))  # stopped after two, slower there
    assert not met["as_fast_as_idm"] and "as_fast_as_idm" in missed


def test_the_figures_survive_a_checkpoint_and_an_old_one_holds_one_scenarios() -> None:
    reference = Reference(SEEDS, scenario_for)
    reference.book(episodes([10.0, 12.0, 14.0, 16.0]))
    restored = Reference(SEEDS, scenario_for)
    restored.load_state_dict(reference.state_dict(), "merge")
    assert restored.state_dict() == reference.state_dict()
    old = Reference(SEEDS, scenario_for)
    old.load_state_dict({"idm_eval": reference.overall}, "cf")
    assert old.by_scenario == {"cf": reference.overall} and old.speeds == []


def test_the_screen_bounds_speeds_by_the_ceilings_on_one_lane_only() -> None:
    reference = Reference(SEEDS, scenario_for)
    reference.book(episodes([10.0, 12.0, 14.0, 16.0]))
    assert reference.screen(max_steps=500, one_lane=True).speed_bounds == [14.2] * 4
    assert reference.screen(max_steps=500, one_lane=False).speed_bounds is None
    routed = Reference(SEEDS, scenario_for)
    routed.book(episodes([10.0, 12.0, 14.0, 16.0], route_lanes=1))
    assert set(routed.screen(max_steps=None, one_lane=False).routed) == {0, 1, 2, 3}
