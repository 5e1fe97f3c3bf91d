"""What a run says as it goes: the one-time wait before the first update is said as such."""

from __future__ import annotations

from pathlib import Path

import pytest

from agent_client.training.config import TrainConfig, apply_overrides
from agent_client.training.progress import QuietReporter
from agent_client.training.trainer import Trainer
from tests.conftest import RunningServer


class Lines(QuietReporter):
    def __init__(self) -> None:
        self.lines: list[str] = []

    def message(self, text: str) -> None:
        self.lines.append(text)


@pytest.mark.slow
@pytest.mark.parametrize("compiled", [False, True])
def test_the_first_update_says_when_it_loads_the_compiled_update(
    fake_server: RunningServer, tmp_path: Path, compiled: bool
) -> None:
    config = apply_overrides(
        TrainConfig(),
        {
            "episodes": 3, "eval_every": 0, "sampling": "local",
            "scenario_options": {"max_episode_time": 3.0},
            "learner": {"learning_starts": 32, "batch_size": 32, "compile": compiled},
        },
    )  # fmt: skip
    lines = Lines()
    trainer = Trainer(config, fake_server.address, tmp_path / "run", reporter=lines)
    try:
        trainer.run()
    finally:
        trainer.close()
    begins = [line for line in lines.lines if line.startswith("learning begins")]
    assert len(begins) == 1
    assert ("loading the compiled update first" in begins[0]) is compiled
