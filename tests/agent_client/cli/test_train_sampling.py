"""`agent-client train --sampling KIND --ray-address ...` reaches the training configuration."""

from __future__ import annotations

import pytest

from agent_client.cli.main import build_parser
from agent_client.cli.train import build_config
from agent_client.training.config import TrainConfig


def config_of(*argv: str) -> TrainConfig:
    return build_config(build_parser().parse_args(["train", *argv]))


def test_sampling_is_chosen_by_the_run_unless_asked() -> None:
    config = config_of()
    assert (config.sampling, config.ray_address) == ("auto", "")
    assert config_of("--sampling", "processes").sampling == "processes"
    assert config_of("--sampling", "local").sampling == "local"


def test_ray_sampling_and_its_address_are_settings() -> None:
    config = config_of("--sampling", "ray", "--ray-address", "auto", "--set", "sampling_chunk=16")
    assert (config.sampling, config.ray_address, config.sampling_chunk) == ("ray", "auto", 16)
    assert config.to_dict()["sampling"] == "ray"  # saved in config.json, kept by --resume


def test_an_unknown_sampling_is_refused_by_the_parser(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        config_of("--sampling", "spark")
    assert "invalid choice: 'spark'" in capsys.readouterr().err
