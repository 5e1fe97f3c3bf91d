"""The first lines of a training run: what it trains, how it is judged, where it stops."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

from agent_client.training.config import TrainConfig
from agent_client.training.plan import plan_lines


def trainer_for(config: TrainConfig, sampling: str = "processes") -> Any:
    """What `plan_lines` reads of a trainer, without a server."""
    return SimpleNamespace(
        config=config,
        sampling=sampling,
        device="cpu",
        agent=SimpleNamespace(n_lane_actions=3),
        vec=SimpleNamespace(envs=[object(), object()]),
        reference=SimpleNamespace(name="idm+mobil"),
        eval_servers=["ipc:///tmp/eval"],
        features=SimpleNamespace(name="road"),
    )


def test_the_plan_names_the_run_its_targets_and_where_it_stops() -> None:
    config = TrainConfig(scenario="cflc", stop_when_converged=True)
    text = "\n".join(plan_lines(trainer_for(config), Path("runs/x")))
    assert "training TD3 (on cpu) on cflc" in text and "lane changes learned" in text
    assert "as fast as the reference (idm+mobil)" in text
    assert "3 evaluations in a row" in text and "at most 300 episodes" in text
    assert "runs/x" in text and "over the whole evaluation" not in text


def test_over_several_scenarios_the_plan_says_what_is_judged_where() -> None:
    config = TrainConfig(scenario=["merge", "exit", "cflc"], stop_when_converged=True)
    text = "\n".join(plan_lines(trainer_for(config), Path("runs/x")))
    assert "merge, exit, cflc" in text and "per scenario on held-out seeds" in text
    assert "collisions, red lights and route ends per scenario" in text
    assert "jerk, headways, speed, the ceiling and the safety layer over the whole" in text
    assert "no red light passed" in text and "as fast as the reference" in text
    gain = TrainConfig(scenario=["merge", "cflc"], speed_gain=0.01)
    assert "1.01x as fast as the reference" in "\n".join(plan_lines(trainer_for(gain), Path("x")))


def test_the_plan_says_who_steps_the_servers() -> None:
    chosen = "\n".join(plan_lines(trainer_for(TrainConfig()), Path("runs/x")))
    assert "sampling: processes (auto): a process per server steps it" in chosen
    asked = TrainConfig(sampling="local")
    text = "\n".join(plan_lines(trainer_for(asked, "local"), Path("runs/x")))
    assert "sampling: local: this process steps the servers in lock-step" in text
