"""Many simulators, one learner: environment steps/s and learner updates/s for N = 1, 2, 4.

One ``sim-server --workers MAX`` (SUMO, `cf` by default) on free loopback ports, then for each N:

* **stepping**: `RemoteVectorEnv` over N servers driven by a fixed action for `--seconds`
  (what the simulators deliver to a learner that does nothing else);
* **training**: the recommended DDPG configuration (learning from step 500) over the same N
  servers for `--seconds` (its updates per environment step are the learner's real load).

Prints a table with the speed-ups over N = 1 and writes JSON. On a machine with C cores the
simulators and the learner share them, so the curve flattens once N + 1 processes outnumber C.

    python benchmarks/scaling.py --counts 1 2 4 --seconds 60
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np

from agent_client.envs.vector_env import RemoteVectorEnv
from agent_client.training.config import TrainConfig, apply_overrides
from agent_client.training.trainer import QuietReporter, Trainer
from protocol.readiness import LISTENING, NotReady, wait_for_line


def start_workers(count: int, backend: str) -> tuple[subprocess.Popen[str], list[str]]:
    command = [sys.executable, "-m", "sim_server.cli", "--bind", "tcp://127.0.0.1:0",
               "--workers", str(count), "--backend", backend, "--log-level", "WARNING"]  # fmt: skip
    process = subprocess.Popen(command, stdout=subprocess.PIPE, text=True)
    try:  # one readiness line per worker, printed once all are ready
        addresses = [wait_for_line(process, LISTENING, 180.0) for _ in range(count)]
    except NotReady:
        process.kill()
        raise
    return process, addresses


def stepping(addresses: list[str], scenario: str, seconds: float) -> dict[str, float]:
    env = RemoteVectorEnv(addresses, scenario, reward="ra3")
    try:
        n = env.num_envs
        env.reset(seed=0)
        actions = {"acceleration": np.full((n, 1), 0.3), "lane_change": np.zeros(n)}
        steps, started = 0, time.monotonic()
        while time.monotonic() - started < seconds:
            env.step(actions)
            steps += n
        elapsed = time.monotonic() - started
    finally:
        env.close()
    return {"env_steps_per_s": steps / elapsed}


class StopAfter(QuietReporter):
    """Requests a stop once the time budget is spent (checked after every episode)."""

    def __init__(self, seconds: float) -> None:
        self.end = time.monotonic() + seconds
        self.trainer: Trainer | None = None

    def episode(self, row: dict[str, Any]) -> None:
        if time.monotonic() > self.end and self.trainer is not None:
            self.trainer.request_stop()


def training(
    addresses: list[str], scenario: str, seconds: float, sampling: str = "local"
) -> dict[str, float]:
    config = apply_overrides(
        TrainConfig(),
        {
            "scenario": scenario,
            "sampling": sampling,
            "episodes": 100_000,
            "eval_every": 0,
            "checkpoint_every": 1000,
            "learner": {"learning_starts": 500},
        },  # mostly steady-state learning within the budget
    )
    reporter = StopAfter(seconds)
    with tempfile.TemporaryDirectory() as out:
        trainer = Trainer(config, addresses, Path(out), reporter=reporter)
        reporter.trainer = trainer
        try:
            started = time.monotonic()
            progress = trainer.run()
            elapsed = time.monotonic() - started
        finally:
            trainer.close()
    return {
        "train_env_steps_per_s": progress.global_step / elapsed,
        "updates_per_s": trainer.agent.n_updates / elapsed,
        "episodes": progress.episode,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", nargs="+", type=int, default=[1, 2, 4])
    parser.add_argument("--seconds", type=float, default=60.0, help="per measurement")
    parser.add_argument("--scenario", default="cf")
    parser.add_argument("--backend", default="sumo")
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/scaling.json")
    args = parser.parse_args()

    process, addresses = start_workers(max(args.counts), args.backend)
    rows = []
    try:
        for count in args.counts:
            row: dict[str, Any] = {"servers": count}
            row.update(stepping(addresses[:count], args.scenario, args.seconds))
            row.update(training(addresses[:count], args.scenario, args.seconds))
            rows.append(row)
            print(
                f"N={count}: stepping {row['env_steps_per_s']:7.0f} steps/s | training "
                f"{row['train_env_steps_per_s']:6.0f} steps/s, {row['updates_per_s']:6.0f} "
                "updates/s",
                flush=True,
            )
    finally:
        process.send_signal(signal.SIGTERM)
        process.wait(timeout=60)
    base = rows[0]
    print(f"\n{args.backend}/{args.scenario}, {os.cpu_count()} cores, {platform.node()}:")
    print("| servers | stepping steps/s | x | training steps/s | x | updates/s |")
    print("| --- | --- | --- | --- | --- | --- |")
    for row in rows:
        print(
            f"| {row['servers']} | {row['env_steps_per_s']:.0f} | "
            f"{row['env_steps_per_s'] / base['env_steps_per_s']:.2f} | "
            f"{row['train_env_steps_per_s']:.0f} | "
            f"{row['train_env_steps_per_s'] / base['train_env_steps_per_s']:.2f} | "
            f"{row['updates_per_s']:.0f} |"
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(
        json.dumps({"cores": os.cpu_count(), "scenario": args.scenario, "rows": rows}, indent=2)
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
