"""The training rate of a tree's own learner, so that two commits compare in one run.

Starts that tree's SUMO server on a free loopback port, trains its recommended configuration
(learning from step `--learning-starts`, no evaluations) and measures environment steps per
second between episode ends once learning has run for `--settle` steps. It uses only what every
version since the layout of 0.2 has (`Trainer`, `TrainConfig`, `apply_overrides`,
`Progress.global_step`), so it measures an old commit as well as this one:

    python benchmarks/training_rate.py --seconds 40
    git worktree add /tmp/before 8c6abbe
    python benchmarks/training_rate.py --tree /tmp/before --seconds 40 --profile
    python benchmarks/training_rate.py --tree /tmp/before --update-only

`--profile` adds cProfile's view of where the time went (the functions with the most own time,
and the learner's own functions by cumulative time; cProfile slows Python-heavy code most):
the trees since issue 12 also print their built-in per-phase profile. This is a measurement,
not a test.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import pstats
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tree", type=Path, default=ROOT, help="the checkout to measure")
    parser.add_argument("--scenario", default="cf")
    parser.add_argument("--seconds", type=float, default=40.0)
    parser.add_argument("--learning-starts", type=int, default=2000)
    parser.add_argument("--settle", type=int, default=3000, help="learning steps not measured")
    parser.add_argument("--profile", action="store_true")
    parser.add_argument(
        "--update-only", action="store_true", help="time the update alone (cf shapes), no server"
    )
    args = parser.parse_args()
    tree = args.tree.resolve()
    sys.path.insert(0, str(tree))
    if args.update_only:
        print(json.dumps({"tree": str(tree), **update_time()}, indent=2))
        return 0

    from agent_client.training.config import TrainConfig, apply_overrides
    from agent_client.training.trainer import QuietReporter, Trainer
    from protocol.readiness import LISTENING, stop_process, wait_for_line

    class Clock(QuietReporter):  # type: ignore[misc]
        def __init__(self) -> None:
            self.marks: list[tuple[float, int]] = []
            self.trainer: Any = None

        def episode(self, row: dict[str, Any]) -> None:
            step = self.trainer.progress.global_step
            if step < args.learning_starts + args.settle:
                return
            self.marks.append((time.perf_counter(), step))
            if self.marks[-1][0] - self.marks[0][0] > args.seconds:
                self.trainer.request_stop()

    command = [sys.executable, "-m", "sim_server.cli", "--bind", "tcp://127.0.0.1:0",
               "--log-level", "WARNING"]  # fmt: skip
    server = subprocess.Popen(
        command, cwd=tree, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
    )
    try:
        address = wait_for_line(server, LISTENING, 120.0)
        values = {"scenario": args.scenario, "episodes": 100_000, "eval_every": 0,
                  "checkpoint_every": 100_000,
                  "learner": {"learning_starts": args.learning_starts}}  # fmt: skip
        config = apply_overrides(TrainConfig(), values)
        clock = Clock()
        profiler = cProfile.Profile() if args.profile else None
        with tempfile.TemporaryDirectory() as out:
            trainer = Trainer(config, address, Path(out), reporter=clock)
            clock.trainer = trainer
            try:
                if profiler is not None:
                    profiler.enable()
                trainer.run()
            finally:
                if profiler is not None:
                    profiler.disable()
                close = getattr(trainer, "close", None)
                if close is not None:
                    close()
    finally:
        stop_process(server)

    if len(clock.marks) < 2 or clock.marks[-1][0] <= clock.marks[0][0]:
        raise SystemExit("too few episode ends to measure a rate: give it more --seconds")
    (t0, s0), (t1, s1) = clock.marks[0], clock.marks[-1]
    result = {
        "tree": str(tree),
        "scenario": args.scenario,
        "env_steps_per_s": (s1 - s0) / (t1 - t0),
        "measured_s": t1 - t0,
        "batch_size": config.learner.batch_size,
    }
    built_in = getattr(trainer, "profile", None)
    if built_in is not None:
        result["profile"] = built_in.to_dict()
        print(built_in.line())
    print(json.dumps(result, indent=2))
    if profiler is not None:
        text = io.StringIO()
        stats = pstats.Stats(profiler, stream=text)
        stats.sort_stats("tottime").print_stats(15)
        stats.sort_stats("cumulative").print_stats("agent_client", 25)
        print(text.getvalue())
    return 0


def update_time(n: int = 2000) -> dict[str, float]:
    """The recommended learner's update alone on a filled buffer, as the tree defines both."""
    import numpy as np
    import torch

    from agent_client.rl.features import FeatureMap
    from agent_client.rl.replay import ReplayBuffer
    from agent_client.rl.td3 import Agent
    from agent_client.training.config import TrainConfig

    torch.set_num_threads(1)  # as the trainer runs it (`TrainConfig.torch_threads`)
    config = TrainConfig().learner
    dim, size = FeatureMap("cf").dim, 20_000
    agent = Agent(dim, 1, config, seed=0)
    buffer = ReplayBuffer(100_000, dim, seed=0)
    rng = np.random.default_rng(0)
    buffer.add_batch(
        rng.normal(size=(size, dim)), rng.uniform(-1, 1, size), np.zeros(size, np.int64),
        rng.normal(size=size), rng.normal(size=(size, dim)), np.zeros(size),
    )  # fmt: skip
    for _ in range(20):  # compilation, if the tree compiles
        agent.update(buffer.sample(config.batch_size))
    started = time.perf_counter()
    for _ in range(n):
        agent.update(buffer.sample(config.batch_size))
    seconds = (time.perf_counter() - started) / n
    return {"ms_per_update": 1e3 * seconds, "batch_size": config.batch_size}


if __name__ == "__main__":
    sys.exit(main())
