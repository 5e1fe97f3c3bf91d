"""One shared policy for many egos: how fast does the learner get experience and update?

`agent-client train`'s own loop (`Trainer`, the recommended learner, an update-to-data ratio of
1 unless ``--set`` changes it, no evaluations) on SUMO's ``ring`` with 1 ego per simulation
(today's path, `LocalCollector`) and with 4 and 8 (`MultiEgoCollector`: one simulation, one
batched forward pass of the shared actor for all egos, every ego's steps into the one buffer),
against one server, in interleaved rounds (1, 4, 8, 1, 4, 8, ...). Each run is measured between
episode ends once learning has begun and the update is compiled (more than 100 updates), so
compilation and the warm-up are not in it; the simulations' resets (the ring's warm-up) are.

    python benchmarks/shared_policy.py                      # 3 rounds of 30 s per run
    python benchmarks/shared_policy.py --rounds 1 --seconds 10 --egos 1 4

It prints ego-steps (transitions) per second and updates per second per run, their medians
over the rounds and the ratio of transitions per second to one ego, and writes
benchmarks/results/shared_policy.json (``--out`` elsewhere). A measurement, not a test.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torch

from agent_client.training.config import TrainConfig, apply_overrides, parse_assignment
from agent_client.training.trainer import QuietReporter, Trainer
from protocol.readiness import LISTENING, NotReady, stop_process, wait_for_line

RESULTS = ROOT / "benchmarks" / "results" / "shared_policy.json"
MEASURE_AFTER_UPDATES = 100
"""Updates after which a run is measured: learning has begun and the update is compiled."""


class Clock(QuietReporter):
    """Marks (time, transitions, updates) at every episode end once learning runs; stops the
    run `seconds` after the first mark."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self.marks: list[tuple[float, int, int]] = []
        self.trainer: Trainer | None = None
        self.since: float | None = None

    def episode(self, row: dict[str, Any]) -> None:
        trainer = self.trainer
        assert trainer is not None
        now = time.perf_counter()
        if self.since is None and trainer.progress.updates > MEASURE_AFTER_UPDATES:
            self.since = now
            trainer.profile.reset()  # the measured iterations only
        if self.since is not None:
            self.marks.append((now, trainer.progress.global_step, trainer.progress.updates))
            if now - self.since > self.seconds:
                trainer.request_stop()


def start_server() -> tuple[subprocess.Popen[str], str]:
    """One SUMO server on a free loopback port, after its readiness line."""
    command = [sys.executable, "-m", "sim_server.cli", "--bind", "tcp://127.0.0.1:0",
               "--backend", "sumo", "--log-level", "WARNING"]  # fmt: skip
    server = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        return server, wait_for_line(server, LISTENING, 120.0)
    except NotReady:
        server.kill()
        server.wait(timeout=10)
        raise


def config_for(egos: int, args: argparse.Namespace) -> TrainConfig:
    config = apply_overrides(
        TrainConfig(),
        {
            "scenario": "ring",
            "egos": egos,
            "sampling": "local",  # one ego and many under the same lock-step collector
            "episodes": 10_000_000,
            "max_minutes": 10.0,  # a stop in case the clock never starts
            "eval_every": 0,
            "checkpoint_every": 10_000_000,
            "seed": args.seed,
            "scenario_options": {"max_episode_time": args.episode_time},
            "learner": {"learning_starts": args.learning_starts},
        },
    )
    for assignment in args.set:
        config = apply_overrides(config, parse_assignment(assignment))
    return config


def measure(address: str, egos: int, args: argparse.Namespace) -> dict[str, Any]:
    """One training run with `egos` egos per simulation; its rates between episode ends."""
    clock = Clock(args.seconds)
    with tempfile.TemporaryDirectory() as out:
        trainer = Trainer(config_for(egos, args), address, Path(out), reporter=clock)
        clock.trainer = trainer
        try:
            trainer.run()
        finally:
            trainer.close()
    if len(clock.marks) < 2 or clock.marks[-1][0] <= clock.marks[0][0]:
        raise SystemExit(f"egos {egos}: too few episode ends to measure: give more --seconds")
    (t0, s0, u0), (t1, s1, u1) = clock.marks[0], clock.marks[-1]
    profile = trainer.profile.to_dict()
    return {
        "egos": egos,
        "transitions_per_s": (s1 - s0) / (t1 - t0),
        "updates_per_s": (u1 - u0) / (t1 - t0),
        "measured_s": t1 - t0,
        "transitions": s1 - s0,
        "update_to_data": (u1 - u0) / max(s1 - s0, 1),
        "transitions_per_iteration": (s1 - s0) / max(profile["iterations"], 1),
        "us_per_iteration": profile["us_per_iteration"],
    }


def summary(runs: list[dict[str, Any]], egos: list[int]) -> dict[str, dict[str, float]]:
    """Medians over the rounds, and the ratio of transitions per second to the first `egos`."""
    table: dict[str, dict[str, float]] = {}
    for n in egos:
        mine = [run for run in runs if run["egos"] == n]
        table[str(n)] = {
            "transitions_per_s": statistics.median(r["transitions_per_s"] for r in mine),
            "updates_per_s": statistics.median(r["updates_per_s"] for r in mine),
        }
    base = egos[0]
    for n in egos:
        ratios = [
            mine["transitions_per_s"] / theirs["transitions_per_s"]
            for mine, theirs in zip(
                [r for r in runs if r["egos"] == n], [r for r in runs if r["egos"] == base],
                strict=True,
            )
        ]  # fmt: skip
        table[str(n)]["ratio_to_first"] = statistics.median(ratios)
        table[str(n)]["ratio_min"], table[str(n)]["ratio_max"] = min(ratios), max(ratios)
    return table


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--egos", type=int, nargs="+", default=[1, 4, 8])
    parser.add_argument("--rounds", type=int, default=3, help="interleaved rounds (default 3)")
    parser.add_argument("--seconds", type=float, default=30.0, help="measured s per run")
    parser.add_argument("--episode-time", type=float, default=30.0, help="max_episode_time (s)")
    parser.add_argument("--learning-starts", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--out", type=Path, default=RESULTS, help="where the JSON goes")
    args = parser.parse_args()
    torch.set_num_threads(1)
    report: dict[str, Any] = {
        "command": " ".join(["python", "benchmarks/shared_policy.py", *sys.argv[1:]]),
        "machine": f"{platform.machine()}, {os.cpu_count()} cpus, Python "
        f"{platform.python_version()}, torch {torch.__version__}, load average "
        f"{os.getloadavg()[0]:.2f} at start",
        "scenario": {"name": "ring", "max_episode_time": args.episode_time},
        "learner": config_for(1, args).to_dict()["learner"],
        "settings": args.set,
        "runs": [],
    }
    server, address = start_server()
    try:
        for round_ in range(args.rounds):
            for egos in args.egos:
                run = {"round": round_ + 1, **measure(address, egos, args)}
                report["runs"].append(run)
                print(
                    f"round {run['round']}, {egos} egos: {run['transitions_per_s']:,.0f} "
                    f"transitions/s, {run['updates_per_s']:,.0f} updates/s "
                    f"({run['transitions_per_iteration']:.2f} transitions per iteration, "
                    f"{run['measured_s']:.0f} s)",
                    flush=True,
                )
    finally:
        stop_process(server)
    report["load_average_at_end"] = round(os.getloadavg()[0], 2)
    report["summary"] = summary(report["runs"], args.egos)
    print(f"\nmedians over {args.rounds} rounds (ratio of transitions/s to {args.egos[0]} ego):")
    for egos, row in report["summary"].items():
        print(
            f"  {egos:>3} egos: {row['transitions_per_s']:>8,.0f} transitions/s "
            f"{row['updates_per_s']:>8,.0f} updates/s  {row['ratio_to_first']:.2f}x "
            f"({row['ratio_min']:.2f}-{row['ratio_max']:.2f})"
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
