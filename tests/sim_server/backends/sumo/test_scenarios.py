"""What the SUMO scenarios announce: their step length, and a decision interval they can apply."""

from __future__ import annotations

from pathlib import Path

import pytest

from sim_server.backends.sumo.scenarios import (
    BUILTIN_SCENARIOS,
    ROAD_STEP_LENGTH,
    CustomScenario,
)


def test_the_built_in_roads_announce_their_step_length() -> None:
    for scenario in BUILTIN_SCENARIOS.values():
        info = scenario.info()
        assert info.step_length == ROAD_STEP_LENGTH
        assert info.options["decision_interval"] == ROAD_STEP_LENGTH


@pytest.mark.parametrize(("step", "interval"), [("1", 1.0), ("0.05", 0.1), ("0.1", 0.1)])
def test_a_custom_scenario_defaults_to_a_decision_interval_it_can_apply(
    tmp_path: Path, step: str, interval: float
) -> None:
    config = tmp_path / "my.sumocfg"
    config.write_text(f'<configuration><time><step-length value="{step}"/></time></configuration>')
    info = CustomScenario("mine", config, "r0").info()
    assert info.step_length == float(step)
    assert info.options["decision_interval"] == interval  # 0.1 s is no multiple of a 1 s step
