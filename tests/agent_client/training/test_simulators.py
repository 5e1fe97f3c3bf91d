from __future__ import annotations

from dataclasses import replace

from agent_client.training.simulators import serving_differently
from protocol.messages import ActionSchema, ScenarioInfo, Welcome


def welcome(**changes: object) -> Welcome:
    values: dict[str, object] = {
        "protocol": (1, 7),
        "server": "sim-server",
        "backend": "sumo",
        "backend_version": "1.28.0",
        "scenarios": (
            ScenarioInfo("cf", "car following", {"flow": 1200.0}, 0.1),
            ScenarioInfo("merge", "an on-ramp", {"flow": 1500.0}, 0.1),
        ),
        "observation_fields": (),
        "action": ActionSchema(-6.0, 3.0),
        "sensor_range": 200.0,
        "max_frame_bytes": 1 << 20,
    }
    values.update(changes)
    return Welcome(**values)  # type: ignore[arg-type]


def test_a_simulator_serving_the_runs_scenarios_alike_differs_in_nothing() -> None:
    training = welcome()
    own = replace(training, scenarios=(*training.scenarios, ScenarioInfo("ring", "", {}, 0.1)))
    assert serving_differently(training, own, ["cf", "merge"]) == ""


def test_what_makes_a_simulator_serve_differently_is_named() -> None:
    training = welcome()
    other_flow = (ScenarioInfo("cf", "car following", {"flow": 900.0}, 0.1),)
    cases = {
        "backend version": replace(training, backend_version="1.20.0"),
        "action bounds": replace(training, action=ActionSchema(-9.0, 3.0)),
        "sensor range": replace(training, sensor_range=150.0),
        "'merge' is not offered": replace(training, scenarios=training.scenarios[:1]),
        "'cf' has other options": replace(training, scenarios=other_flow),
    }
    for why, own in cases.items():
        assert why in serving_differently(training, own, ["cf", "merge"]), why
    assert serving_differently(training, replace(training, scenarios=other_flow), ["merge"])
