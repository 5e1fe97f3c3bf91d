"""Typed scenario options: parsed and range-checked once, refused with ``invalid_option``."""

from __future__ import annotations

import pytest

from protocol.errors import ErrorCode
from protocol.messages import OptionValue
from sim_server.backends.options import (
    COMMON_OPTIONS,
    TRAFFIC_OPTIONS,
    EpisodeOptions,
    TrafficOptions,
)
from sim_server.errors import BackendError, SimServerError


def refusal(call: object) -> str:
    assert callable(call)
    with pytest.raises(BackendError) as refused:
        call()
    assert refused.value.code is ErrorCode.INVALID_OPTION
    return refused.value.message


def test_the_announced_defaults_are_the_dataclass_defaults_in_order() -> None:
    assert list(COMMON_OPTIONS) == [
        "decision_interval", "max_episode_time", "warmup", "insertion_timeout", "stop_speed",
        "stop_gap", "stop_patience", "lane_end_patience", "jam_patience", "end_on_red_light",
        "report_ceiling", "ego_driver", "egos",
    ]  # fmt: skip
    assert COMMON_OPTIONS["warmup"] == 30.0 and COMMON_OPTIONS["report_ceiling"] is True
    assert TRAFFIC_OPTIONS == {
        "flow": 1500.0,
        "speed_factor_mean": 0.85,
        "speed_factor_dev": 0.15,
        "sigma": 0.5,
        "human_model": "krauss",
    }
    # The wire type of each default is that of the field: a float stays a float.
    assert all(type(v) is float for k, v in TRAFFIC_OPTIONS.items() if k != "human_model")
    assert EpisodeOptions.parse(COMMON_OPTIONS) == EpisodeOptions()


def test_parse_takes_the_given_values_and_defaults_for_the_rest() -> None:
    parsed = EpisodeOptions.parse({"decision_interval": 1, "ego_driver": "sumo", "flow": 9.0})
    assert parsed.decision_interval == 1.0 and type(parsed.decision_interval) is float
    assert parsed.simulator_drives and parsed.max_episode_time == 300.0
    assert not EpisodeOptions.parse({}).simulator_drives


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"decision_interval": 0.0}, "option decision_interval must be > 0"),
        ({"decision_interval": 61.0}, "option decision_interval must be <= 60"),
        ({"max_episode_time": 1e9}, "option max_episode_time must be <= 86400"),
        ({"warmup": -1.0}, "option warmup must be >= 0"),
        ({"warmup": 0.0}, None),
        ({"insertion_timeout": 0.0}, "option insertion_timeout must be > 0"),
        ({"stop_gap": 1e9}, "option stop_gap must be <= 10000"),
        ({"stop_speed": -0.1}, "option stop_speed must be >= 0"),
        ({"stop_patience": 3601.0}, "option stop_patience must be <= 3600"),
        ({"decision_interval": "fast"}, "option decision_interval must be float, got str"),
        ({"report_ceiling": 1}, "option report_ceiling must be bool, got int"),
        ({"ego_driver": "robot"}, "option ego_driver must be agent or sumo"),
    ],
)
def test_episode_options_out_of_range_are_refused_naming_the_bound(
    options: dict[str, OptionValue], message: str | None
) -> None:
    if message is None:
        EpisodeOptions.parse(options)
    else:
        assert refusal(lambda: EpisodeOptions.parse(options)) == message


def test_the_simulator_driver_may_have_aliases() -> None:
    drivers = ("simulator", "sumo")
    assert EpisodeOptions.parse({"ego_driver": "sumo"}, drivers).simulator_drives
    assert EpisodeOptions.parse({"ego_driver": "simulator"}, drivers).simulator_drives
    assert refusal(lambda: EpisodeOptions.parse({"ego_driver": "x"}, drivers)) == (
        "option ego_driver must be agent or simulator (sumo is accepted as an alias)"
    )
    assert refusal(lambda: EpisodeOptions.parse({"ego_driver": "simulator"})) == (
        "option ego_driver must be agent or sumo"
    )


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"flow": 3601.0}, "option flow must be <= 3600 veh/h/lane"),
        ({"flow": -1.0}, "option flow must be >= 0"),
        ({"flow": 0.0}, None),
        ({"speed_factor_mean": 0.0}, "option speed_factor_mean must be > 0"),
        ({"speed_factor_dev": 3.5}, "option speed_factor_dev must be <= 3"),
        ({"sigma": 1.5}, "option sigma must be within [0, 1]"),
        ({"sigma": -0.5}, "option sigma must be within [0, 1]"),
    ],
)
def test_traffic_options_out_of_range_are_refused(
    options: dict[str, OptionValue], message: str | None
) -> None:
    if message is None:
        assert TrafficOptions.parse(options).flow == 0.0
    else:
        assert refusal(lambda: TrafficOptions.parse(options)) == message


@pytest.mark.parametrize(
    ("interval", "step", "steps"), [(0.1, 0.1, 1), (1.0, 0.1, 10), (0.3, 0.1, 3), (2.0, 1.0, 2)]
)
def test_a_decision_is_a_whole_number_of_simulation_steps(
    interval: float, step: float, steps: int
) -> None:
    assert EpisodeOptions(decision_interval=interval).steps_per_decision(step) == steps


@pytest.mark.parametrize(("interval", "step"), [(0.15, 0.1), (0.05, 0.1), (1.5, 1.0)])
def test_a_decision_between_simulation_steps_is_refused(interval: float, step: float) -> None:
    message = refusal(lambda: EpisodeOptions(decision_interval=interval).steps_per_decision(step))
    assert message == (
        f"decision_interval {interval} s is not a multiple of the step length {step} s"
    )


def test_backend_errors_share_the_server_root() -> None:
    assert issubclass(BackendError, SimServerError)
