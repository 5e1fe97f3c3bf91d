from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from agent_client.cli.main import build_parser
from agent_client.cli.train import build_config
from agent_client.errors import UsageError
from agent_client.training.config import (
    INTEGRATED,
    TrainConfig,
    apply_overrides,
    load_config_file,
    parse_assignment,
    recommended,
)


def test_defaults_are_documented_dataclass_fields() -> None:
    config = TrainConfig()
    assert config.reward == "safe"
    assert config.learner.algo == "td3"  # the recommended learner
    assert TrainConfig.from_dict(config.to_dict()) == config


def test_unknown_settings_are_refused() -> None:
    with pytest.raises(ValueError, match="warp"):
        apply_overrides(TrainConfig(), {"warp": 1})
    with pytest.raises(ValueError, match="warp"):
        apply_overrides(TrainConfig(), {"learner": {"warp": 1}})


def test_assignments_parse_json_values_and_nested_keys() -> None:
    assert parse_assignment("episodes=40") == {"episodes": 40}
    assert parse_assignment("learner.actor_lr=3e-4") == {"learner": {"actor_lr": 3e-4}}
    assert parse_assignment("reward=ra3") == {"reward": "ra3"}


def test_precedence_defaults_file_flags_set(tmp_path: Path) -> None:
    file = tmp_path / "run.toml"
    file.write_text('episodes = 50\nreward = "ra3"\nseed = 4\n[ddpg]\nactor_lr = 0.002\n')
    assert load_config_file(file)["ddpg"] == {"actor_lr": 0.002}
    args = build_parser().parse_args(
        ["train", "--config", str(file), "--episodes", "70", "--algo", "ddpg",
         "--set", "seed=9", "--set", "learner.critic_lr=0.01"]
    )  # fmt: skip
    config = build_config(args)
    assert config.episodes == 70  # flag beats file
    assert config.reward == "ra3"  # file beats default
    assert config.seed == 9  # --set beats file
    assert config.learner.actor_lr == 0.002
    assert config.learner.critic_lr == 0.01
    assert config.learner.algo == "ddpg"  # --algo switches the trio off, keeps the rest
    assert config.learner.gamma == TrainConfig().learner.gamma


@pytest.mark.parametrize(
    ("decision", "lane", "every"), [(0.1, 1.0, 10), (0.3, 1.0, 3), (2.0, 1.0, 1), (0.5, 0.5, 1)]
)
def test_lane_decisions_come_every_whole_number_of_decisions(
    decision: float, lane: float, every: int
) -> None:
    config = TrainConfig(decision_interval=decision, lane_decision_interval=lane)
    assert config.lane_decision_every == every


def test_a_lane_decision_interval_must_be_positive() -> None:
    with pytest.raises(UsageError, match="lane_decision_interval"):
        TrainConfig(lane_decision_interval=0.0)


def test_reward_params_reach_the_reward_and_merge_like_the_learner_table(tmp_path: Path) -> None:
    file = tmp_path / "run.toml"
    file.write_text("[reward_params]\ndesired_headway = 1.1\n")
    args = build_parser().parse_args(
        ["train", "--scenario", "cflc", "--config", str(file),
         "--set", "reward_params.jerk_weight=0.25"]
    )  # fmt: skip
    config = build_config(args)
    merged = {"headway_sigma": 0.2, "desired_headway": 1.1, "jerk_weight": 0.25}  # cflc's own too
    assert config.reward_params == merged
    reward = config.reward_fn()
    assert (reward.desired_headway, reward.jerk_weight) == (1.1, 0.25)  # type: ignore[attr-defined]
    assert TrainConfig.from_dict(config.to_dict()) == config  # config.json keeps them
    assert TrainConfig().reward_fn() == TrainConfig(reward_params={}).reward_fn()


@pytest.mark.parametrize(
    ("params", "named"),
    [
        ({"desired_headwy": 1.1}, "desired_headwy"),  # a typo names itself and the known ones
        ({"desired_headway": "far"}, "desired_headway"),
        ({"desired_headway": True}, "desired_headway"),
        ({"desired_headway": -1.0}, "positive"),  # the reward's own check
    ],
)
def test_a_bad_reward_parameter_is_a_usage_error_naming_it(
    params: dict[str, object], named: str
) -> None:
    with pytest.raises(UsageError, match=named):
        TrainConfig(reward_params=params)  # type: ignore[arg-type]


def test_reward_params_belong_to_the_chosen_reward() -> None:
    with pytest.raises(UsageError, match="reward ra3 has no such parameter"):
        TrainConfig(reward="ra3", reward_params={"ttc_weight": 0.5})


@pytest.mark.parametrize("text", ["eval_while_training=False", "eval_screen=1", "pretrain_idm=no"])
def test_a_switch_takes_true_or_false_only(text: str) -> None:
    key = text.partition("=")[0]
    with pytest.raises(UsageError, match=f"{key} must be true or false"):
        apply_overrides(TrainConfig(), parse_assignment(text))
    assert apply_overrides(TrainConfig(), parse_assignment(f"{key}=false")).to_dict()[key] is False


def _shipped(name: str) -> TrainConfig:
    """A file of configs/ as `agent-client train --config` reads it."""
    path = Path(__file__).resolve().parents[3] / "configs" / name
    return build_config(build_parser().parse_args(["train", "--config", str(path)]))


def test_the_recommended_cf_settings_are_what_train_uses_by_default() -> None:
    plain = build_config(build_parser().parse_args(["train", "--scenario", "cf"]))
    assert plain == recommended("cf") == build_config(build_parser().parse_args(["train"]))
    default = TrainConfig()
    assert plain.eval_budget == 1.0 != default.eval_budget
    assert plain.warmup_policy == "auto" == default.warmup_policy  # random on cf: not residual
    assert plain.learner.deploy_tau == 0.001 != default.learner.deploy_tau
    assert plain.reward_params == {  # exactly these: an extra key would change the reward too
        "desired_headway": 1.1,
        "headway_far_sigma": 0.5,
        "headway_far_weight": 0.5,
    }
    reward = plain.reward_fn()
    assert reward.desired_headway == 1.1  # type: ignore[attr-defined]
    assert reward.headway_far_sigma == 0.5  # type: ignore[attr-defined]
    assert reward.headway_far_weight == 0.5  # type: ignore[attr-defined]
    # nothing else moves: the rest is the default configuration
    learner = dataclasses.replace(plain.learner, deploy_tau=default.learner.deploy_tau)
    rest = dataclasses.replace(
        plain, eval_budget=default.eval_budget, reward_params={}, learner=learner
    )
    assert rest == default


def test_the_recommended_reward_parameters_go_only_with_their_reward() -> None:
    parsed = build_parser().parse_args(["train", "--scenario", "cf", "--reward", "ra3"])
    config = build_config(parsed)
    assert config.reward_params == {} and config.eval_budget == 1.0


def test_cflc_trains_the_integrated_driver_and_other_scenarios_with_the_defaults() -> None:
    cflc = recommended("cflc")
    assert cflc.reward_params == {"headway_sigma": 0.2}
    assert cflc.residual == "idm+mobil" and cflc.residual_lanes == "default"
    assert not cflc.residual_shield and cflc.residual_reach >= 9.0
    assert cflc.reference == "idm+mobil" and cflc.speed_gain > 0  # beats the strongest baseline
    assert cflc.safety_layer_training and cflc.override_penalty > 0 and cflc.pretrain_idm
    assert build_config(build_parser().parse_args(["train", "--scenario", "cflc"])) == cflc
    other_reward = recommended("cflc", reward="ra3")  # the parametrisation stays, the knee goes
    assert other_reward.reward_params == {} and other_reward.residual == "idm+mobil"
    several = apply_overrides(
        TrainConfig(scenario=["merge", "cf"], episodes=2 * TrainConfig().episodes), INTEGRATED
    )
    assert recommended(["merge", "cf"]) == several  # as many episodes of each as one alone
    assert several.residual == "idm+mobil" and several.residual_reach == 4.0
    assert several.learner.deploy_tau == 0.0002  # the roads training converged with (5 of 5)
    assert several.learn_own_decision and not cflc.learn_own_decision  # measured on the roads
    assert not several.residual_shield and several.residual_lanes == "default"
    assert not several.lane_route_masks and several.speed_gain > 0
    assert several.features == "drive" and several.pretrain_idm
    assert recommended(["merge", "cflc"]).reward_params == {"headway_sigma": 0.2}
    assert recommended(["merge", "cflc"], reward="ra3").reward_params == {}
    assert recommended("merge") == TrainConfig(scenario="merge")


def test_the_shipped_configuration_files_spell_the_recommended_settings_out() -> None:
    assert _shipped("cf.toml") == recommended("cf")
    assert _shipped("cflc.toml") == recommended("cflc")


def test_a_configuration_file_overrides_the_recommended_settings(tmp_path: Path) -> None:
    file = tmp_path / "mine.toml"
    file.write_text("eval_budget = 0.4\n[learner]\ndeploy_tau = 0.005\n")
    parsed = build_parser().parse_args(["train", "--scenario", "cf", "--config", str(file)])
    config = build_config(parsed)
    assert config.eval_budget == 0.4 and config.learner.deploy_tau == 0.005
    assert config.reward_params == recommended("cf").reward_params  # what it did not name


@pytest.mark.parametrize(
    ("setting", "named"),
    [
        ({"reference": "sumo"}, "evaluate --reference sumo"),  # no actions to compare with
        ({"residual_burn_in": -1}, "residual_burn_in must be >= 0"),
        ({"residual": "pid"}, "residual 'pid' is not one of"),
        ({"warmup_policy": "mobil"}, "warmup_policy 'mobil' is not one of: auto"),
    ],
)
def test_a_bad_real_roads_setting_is_a_usage_error_naming_it(
    setting: dict[str, object], named: str
) -> None:
    with pytest.raises(UsageError, match=named):
        TrainConfig(**setting)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("settings", "servers", "evaluation_servers", "cores", "sampling"),
    [
        ({}, 1, 1, 2, "processes"),  # the plain command: a core for the learner, one for SUMO
        ({}, 2, 1, 2, "processes"),  # two simulators and the learner on two cores
        ({}, 4, 1, 2, "processes"),
        ({}, 5, 1, 2, "local"),  # more than two servers per core: lock-step
        ({}, 2, 1, 1, "local"),  # one core: the learner has none of its own
        ({}, 14, 1, 16, "processes"),
        ({}, 1, 0, 2, "local"),  # evaluations on the training server: it must stay here
        ({"eval_every": 0}, 1, 0, 2, "processes"),
        ({"egos": 4}, 1, 1, 16, "local"),  # many egos: one multi-ego session per server
        ({"sampling": "local"}, 1, 1, 16, "local"),
        ({"sampling": "ray"}, 2, 1, 2, "ray"),
        ({"simulators": 3}, 1, 1, 2, "processes"),  # workers that start their simulators
    ],
)
def test_auto_sampling_uses_processes_where_the_servers_and_the_cores_are_free(
    settings: dict[str, object], servers: int, evaluation_servers: int, cores: int, sampling: str
) -> None:
    config = apply_overrides(TrainConfig(), settings)
    assert config.sampling_on(servers, evaluation_servers, cores) == sampling


def test_simulators_need_sampling_workers_and_egos_lock_step() -> None:
    with pytest.raises(UsageError, match="--sampling processes"):
        TrainConfig(simulators=2, sampling="local")
    with pytest.raises(UsageError, match="egos 2 needs sampling = local"):
        TrainConfig(egos=2, sampling="processes")
