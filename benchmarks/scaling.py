"""Many simulators, one learner: environment steps/s and learner updates/s for N servers.

One ``sim-server --workers MAX`` (SUMO, `cf` by default) on free loopback ports, then for each N:

* **stepping**: `RemoteVectorEnv` over N servers driven by a fixed action for `--seconds`
  (what the simulators deliver to a learner that does nothing else);
* **training**: the recommended learner (learning from step 500) over the same N servers for
  `--seconds` of learning, timed from the first episode end after the compiled update has
  loaded (said on the screen; its updates per environment step are the learner's real load),
  once per `--sampling` kind and `--device`.

Prints a table with the speed-ups over N = 1 and writes JSON. On a machine with C cores the
simulators and the learner share them, so the curve flattens once N + 1 processes outnumber C.

    python benchmarks/scaling.py --counts 1 2 4 --seconds 60
    python benchmarks/scaling.py --counts 1 2 4 8 14 --sampling local processes --device cpu cuda
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
from collections.abc import Sequence
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
    """Marks when learning runs (the first episode end after the compiled update has loaded)
    and requests a stop `seconds` later (checked after every episode); says the one-time
    wait as it comes."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self.trainer: Trainer | None = None
        self.learning_from: tuple[float, int, int] | None = None
        """(time, env steps, updates) at the first episode end with updates behind it."""
        self.stopped_at: float | None = None
        """When the stop was asked for (the run's checkpoint and release come after)."""

    def message(self, text: str) -> None:
        if text.startswith(("learning begins", "the compiled update")):
            print(f"   {text}", flush=True)

    def episode(self, row: dict[str, Any]) -> None:
        trainer, now = self.trainer, time.monotonic()
        if trainer is None or trainer.agent.n_updates == 0:
            return
        if self.learning_from is None:
            self.learning_from = (now, trainer.progress.global_step, trainer.agent.n_updates)
        elif now - self.learning_from[0] > self.seconds and self.stopped_at is None:
            self.stopped_at = now
            trainer.request_stop()


def training(
    addresses: list[str],
    scenario: str,
    seconds: float,
    sampling: str = "local",
    device: str = "cpu",
    settings: Sequence[dict[str, Any]] = (),
) -> dict[str, float]:
    """The learner over `addresses` for `seconds` of learning (after the warm-up and the
    compiled update's load, which are not timed): env steps/s and updates/s. `settings`:
    `parse_assignment`s applied last (a variant to compare with the defaults)."""
    config = apply_overrides(
        TrainConfig(),
        {
            "scenario": scenario,
            "sampling": sampling,
            "device": device,
            "episodes": 100_000,
            "eval_every": 0,
            "checkpoint_every": 1000,
            "learner": {"learning_starts": 500},
        },
    )
    for assignment in settings:
        config = apply_overrides(config, assignment)
    reporter = StopAfter(seconds)
    with tempfile.TemporaryDirectory() as out:
        trainer = Trainer(config, addresses, Path(out), reporter=reporter)
        reporter.trainer = trainer
        try:
            progress = trainer.run()
            ended = time.monotonic()
        finally:
            trainer.close()
    if reporter.learning_from is None:
        raise SystemExit(f"{sampling}/{device}: no episode ended after learning began")
    began, steps, updates = reporter.learning_from
    return {
        "train_env_steps_per_s": (progress.global_step - steps) / (ended - began),
        "updates_per_s": (trainer.agent.n_updates - updates) / (ended - began),
        "episodes": progress.episode,
        "sampling": trainer.sampling,
        "device": str(trainer.device),
        "timed_from": began,
        "timed_to": reporter.stopped_at or ended,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", nargs="+", type=int, default=[1, 2, 4])
    parser.add_argument("--seconds", type=float, default=60.0, help="per measurement")
    parser.add_argument("--scenario", default="cf")
    parser.add_argument("--backend", default="sumo")
    parser.add_argument(
        "--sampling", nargs="+", default=["local", "processes"], help="training's sampling kinds"
    )
    parser.add_argument(
        "--device", nargs="+", default=["cpu"], help="the learner's devices (cpu, cuda, ...)"
    )
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/scaling.json")
    args = parser.parse_args()

    process, addresses = start_workers(max(args.counts), args.backend)
    rows = []
    try:
        for count in args.counts:
            row: dict[str, Any] = {"servers": count}
            row.update(stepping(addresses[:count], args.scenario, args.seconds))
            print(f"N={count}: stepping {row['env_steps_per_s']:7.0f} steps/s", flush=True)
            for sampling in args.sampling:
                for device in args.device:
                    trained = training(
                        addresses[:count], args.scenario, args.seconds, sampling, device
                    )
                    row[f"training/{sampling}/{device}"] = {
                        key: value for key, value in trained.items() if not key.startswith("timed")
                    }
                    print(
                        f"N={count}, {sampling}, {device}: training "
                        f"{trained['train_env_steps_per_s']:6.0f} steps/s, "
                        f"{trained['updates_per_s']:6.0f} updates/s",
                        flush=True,
                    )
            rows.append(row)
    finally:
        process.send_signal(signal.SIGTERM)
        process.wait(timeout=60)
    kinds = [f"{s}/{d}" for s in args.sampling for d in args.device]
    print(f"\n{args.backend}/{args.scenario}, {os.cpu_count()} cores, {platform.node()}, "
          "training after the warm-up and the compiled update's load:")  # fmt: skip
    print("| servers | stepping steps/s | " + " | ".join(f"training {k}: steps/s (x stepping)"
                                                          for k in kinds) + " |")  # fmt: skip
    print("| --- | --- |" + " --- |" * len(kinds))
    for row in rows:
        rate = row["env_steps_per_s"]
        trained = [row[f"training/{kind}"]["train_env_steps_per_s"] for kind in kinds]
        cells = [f"{value:.0f} ({value / rate:.2f})" for value in trained]
        print(f"| {row['servers']} | {rate:.0f} | " + " | ".join(cells) + " |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(
        json.dumps({"cores": os.cpu_count(), "scenario": args.scenario, "rows": rows}, indent=2)
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
