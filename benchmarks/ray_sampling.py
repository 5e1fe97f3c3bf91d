"""Our learner's sampling, lockstep and on Ray, beside the field's libraries, in one run.

Two SUMO servers (`cf`) on free loopback ports, then, each for `--seconds` of training with the
recommended learner (learning from step 1000):

* **local**: `LocalCollector`, this process stepping 1 and then 2 servers in lockstep;
* **ray**: `ChunkCollector` with `RayWorkers`, one asynchronous Ray worker per server (1, then
  2) on a local Ray;

env steps/s and learner updates/s are measured in the steady state (from 3 s after the first
update to the end). Then the examples train through the same servers: Stable-Baselines3's TD3
(`examples/sb3_td3.py`), the CleanRL-style TD3 (`examples/cleanrl_td3.py`) and RLlib's PPO with
one env runner per server (`examples/rllib_ppo.py`); their rates are over their whole training
(updates included). Prints a table and writes JSON.

    python benchmarks/ray_sampling.py --seconds 40
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent_client.training.config import TrainConfig, apply_overrides
from agent_client.training.trainer import QuietReporter, Trainer
from benchmarks.scaling import start_workers


def steady_rates(samples: list[tuple[float, int, int]]) -> dict[str, float]:
    """Env steps/s and updates/s from 3 s after the first update to the last sample."""
    first = next((s for s in samples if s[2] > 0), samples[0])
    window = [s for s in samples if s[0] >= first[0] + 3.0] or samples
    (t0, steps0, updates0), (t1, steps1, updates1) = window[0], window[-1]
    elapsed = max(t1 - t0, 1e-9)
    return {
        "env_steps_per_s": round((steps1 - steps0) / elapsed, 1),
        "updates_per_s": round((updates1 - updates0) / elapsed, 1),
        "window_s": round(elapsed, 1),
    }


def train(addresses: list[str], sampling: str, seconds: float) -> dict[str, Any]:
    config = apply_overrides(
        TrainConfig(),
        {
            "episodes": 100_000,
            "eval_every": 0,
            "checkpoint_every": 1000,
            "sampling": sampling,
            "max_minutes": seconds / 60.0,
            "learner": {"learning_starts": 1000},
        },
    )
    samples: list[tuple[float, int, int]] = []
    with tempfile.TemporaryDirectory() as out:
        trainer = Trainer(config, addresses, Path(out), reporter=QuietReporter())
        done = threading.Event()

        def watch() -> None:
            while not done.wait(0.5):
                progress = trainer.progress
                samples.append((time.monotonic(), progress.global_step, progress.updates))

        watcher = threading.Thread(target=watch, daemon=True)
        watcher.start()
        try:
            trainer.run()
        finally:
            done.set()
            watcher.join()
            trainer.close()
            close = getattr(trainer.collector, "close", None)
            if close is not None:
                close()
    return {"learner": f"ours, {sampling}", "servers": len(addresses), **steady_rates(samples)}


def example(script: str, *args: str) -> dict[str, Any]:
    command = [sys.executable, str(ROOT / "examples" / script), *args, "--json"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=900, check=False)
    if done.returncode != 0:
        return {"learner": script, "error": done.stderr.strip().splitlines()[-1:]}
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=40.0, help="per measurement of ours")
    parser.add_argument("--library-steps", type=int, default=4000, help="SB3 / CleanRL steps")
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/ray_sampling.json")
    args = parser.parse_args()
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

    process, addresses = start_workers(2, "sumo")
    rows: list[dict[str, Any]] = []
    try:
        for sampling in ("local", "ray"):
            for count in (1, 2):
                rows.append(train(addresses[:count], sampling, args.seconds))
                print(rows[-1], flush=True)
        steps = str(args.library_steps)
        common = ["--server", addresses[0], "--learning-starts", "1000"]
        rows.append(example("sb3_td3.py", *common, "--steps", steps))
        print(rows[-1], flush=True)
        rows.append(example("cleanrl_td3.py", *common, "--total-timesteps", steps))
        print(rows[-1], flush=True)
        servers = [flag for address in addresses for flag in ("--server", address)]
        rows.append(example("rllib_ppo.py", *servers, "--iterations", "4", "--batch", "1000"))
        print(rows[-1], flush=True)
    finally:
        process.terminate()
        process.wait(timeout=60)
    print(f"\nsumo/cf, {os.cpu_count()} cores, {platform.node()}:")
    print("| learner | servers | env steps/s | updates/s |")
    print("| --- | ---: | ---: | ---: |")
    for row in rows:
        name = row.get("learner") or row.get("library")
        servers = row.get("servers", row.get("env_runners", 1))
        print(f"| {name} | {servers} | {row.get('env_steps_per_s', '-')} | "
              f"{row.get('updates_per_s', '-')} |")  # fmt: skip
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"cores": os.cpu_count(), "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
