"""Short training runs against a live server, for the trainer's tests."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from agent_client.training.config import TrainConfig, apply_overrides
from agent_client.training.trainer import Trainer


def train(address: str, out: Path, fast: Mapping[str, object], **changes: object) -> Trainer:
    """Run the recommended configuration with `fast` and then `changes` applied, to its end."""
    config = apply_overrides(apply_overrides(TrainConfig(), dict(fast)), dict(changes))
    trainer = Trainer(config, address, out, timeout_s=5.0)
    try:
        trainer.run()
    finally:
        trainer.close()
    return trainer
