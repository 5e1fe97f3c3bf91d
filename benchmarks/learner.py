"""Does the learner keep up with its simulator? Update rate, stepping rate, training rate and
where a training iteration's time goes, measured in one run against the same server.

1. **update**: the recommended learner's gradient update alone (`Agent.update` on a filled
   buffer, the scenario's feature and lane-choice sizes), compiled and, with ``--eager``,
   without compilation;
2. **stepping**: the bridge driven by IDM (no updates): what the simulator and the transport
   deliver to a learner that does nothing else;
3. **training**: `agent-client train`'s loop with the recommended configuration at an
   update-to-data ratio of 1 (`--set` changes it), learning from step `--learning-starts`, no
   evaluations; the rate is measured between episode ends once the update is compiled and
   learning has begun, so the compilation and the warm-up are not in it;
4. **profile**: the trainer's own per-phase timing of those iterations.

    python benchmarks/learner.py                          # cf over tcp://, 40 s of training
    python benchmarks/learner.py --scenario cflc --transport direct --save

This is a measurement, not a test: it prints what it measured and, with --save, writes
benchmarks/results/learner-SCENARIO-TRANSPORT[-Nservers].json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np
import torch

from agent_client.drivers.episode import drive
from agent_client.drivers.idm import IDMDriver
from agent_client.envs.remote_env import RemoteEnv
from agent_client.rl.features import FeatureMap
from agent_client.rl.replay import ReplayBuffer
from agent_client.rl.td3 import Agent
from agent_client.training.config import (
    RECOMMENDED_LEARNER,
    TrainConfig,
    apply_overrides,
    parse_assignment,
)
from agent_client.training.trainer import QuietReporter, Trainer
from protocol.readiness import LISTENING, NotReady, stop_process, wait_for_line

RESULTS = ROOT / "benchmarks" / "results"
SHAPES = {"cf": (FeatureMap("cf").dim, 1), "cflc": (FeatureMap("lc", 10).dim, 3)}


def start_server(
    transport: str, cpu: int | None = None, workers: int = 1
) -> tuple[subprocess.Popen[str], list[str]]:
    command = [sys.executable, "-m", "sim_server.cli", "--bind", f"{transport}://127.0.0.1:0",
               "--workers", str(workers), "--log-level", "WARNING"]  # fmt: skip
    if cpu is not None:
        command = ["taskset", "-c", str(cpu), *command]
    server = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        return server, [wait_for_line(server, LISTENING, 120.0) for _ in range(workers)]
    except NotReady:
        server.kill()
        raise


def update_rate(scenario: str, compiled: bool, n: int = 2000) -> dict[str, float]:
    obs_dim, lanes = SHAPES[scenario]
    config = dataclasses.replace(RECOMMENDED_LEARNER, compile=compiled)
    agent = Agent(obs_dim, lanes, config, seed=0)
    buffer = ReplayBuffer(100_000, obs_dim, seed=0, n_lanes=lanes)
    rng = np.random.default_rng(0)
    size = 20_000
    buffer.add_batch(
        rng.normal(size=(size, obs_dim)), rng.uniform(-1, 1, size), rng.integers(0, lanes, size),
        rng.normal(size=size), rng.normal(size=(size, obs_dim)), np.zeros(size),
    )  # fmt: skip
    started = time.perf_counter()
    for _ in range(4):
        agent.update(buffer.sample(config.batch_size))
    warmup = time.perf_counter() - started
    started = time.perf_counter()
    for _ in range(n):
        agent.update(buffer.sample(config.batch_size))
    seconds = (time.perf_counter() - started) / n
    return {"ms_per_update": 1e3 * seconds, "updates_per_s": 1 / seconds, "warmup_s": warmup}


def stepping_rate(address: str, scenario: str, seconds: float) -> dict[str, float]:
    """IDM drives (long, realistic episodes): what the bridge delivers to a learner that only
    chooses actions."""
    env = RemoteEnv(address, scenario, reward="safe")
    try:
        steps, started = 0, time.perf_counter()
        for episode in drive(env, IDMDriver(), 10_000, first_seed=1):
            steps += len(episode.observations) - 1
            if time.perf_counter() - started > seconds:
                break
        elapsed = time.perf_counter() - started
    finally:
        env.close()
    return {"env_steps_per_s": steps / elapsed}


class Clock(QuietReporter):
    """Marks (time, steps, updates) at every episode end; stops the run after the budget."""

    def __init__(self, seconds: float, learning_starts: int) -> None:
        self.seconds, self.learning_starts = seconds, learning_starts
        self.marks: list[tuple[float, int, int]] = []
        self.trainer: Trainer | None = None
        self.measuring_since: float | None = None

    def episode(self, row: dict[str, Any]) -> None:
        trainer = self.trainer
        assert trainer is not None
        now = time.perf_counter()
        if self.measuring_since is None and trainer.progress.updates > 100:
            self.measuring_since = now  # learning has begun and the update is compiled
            trainer.profile.reset()  # the profile of the measured iterations only
        if self.measuring_since is not None:
            self.marks.append((now, trainer.progress.global_step, trainer.progress.updates))
            if now - self.measuring_since > self.seconds:
                trainer.request_stop()


def training_rate(
    address: list[str], scenario: str, seconds: float, learning_starts: int, settings: list[str]
) -> dict[str, Any]:
    config = apply_overrides(
        TrainConfig(),
        {
            "scenario": scenario,
            "episodes": 100_000,
            "eval_every": 0,
            "checkpoint_every": 100_000,
            "sampling": "local",  # the lock-step iteration whose time it breaks down
            "learner": {"learning_starts": learning_starts},
        },
    )
    for assignment in settings:
        config = apply_overrides(config, parse_assignment(assignment))
    clock = Clock(seconds, learning_starts)
    with tempfile.TemporaryDirectory() as out:
        trainer = Trainer(config, address, Path(out), reporter=clock)
        clock.trainer = trainer
        try:
            trainer.run()
        finally:
            trainer.close()
    if len(clock.marks) < 2 or clock.marks[-1][0] <= clock.marks[0][0]:
        raise SystemExit("too few episode ends to measure a rate: give it more --seconds")
    (t0, s0, u0), (t1, s1, u1) = clock.marks[0], clock.marks[-1]
    return {
        "env_steps_per_s": (s1 - s0) / (t1 - t0),
        "updates_per_s": (u1 - u0) / (t1 - t0),
        "measured_s": t1 - t0,
        "update_to_data": (u1 - u0) / max(s1 - s0, 1),
        "profile": trainer.profile.to_dict(),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", choices=sorted(SHAPES), default="cf")
    parser.add_argument("--transport", choices=("tcp", "ipc", "direct"), default="tcp")
    parser.add_argument("--seconds", type=float, default=40.0, help="training measured (s)")
    parser.add_argument("--stepping-seconds", type=float, default=15.0)
    parser.add_argument("--learning-starts", type=int, default=2000)
    parser.add_argument("--eager", action="store_true", help="also time the eager update")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--servers", type=int, default=1, help="training servers (default 1)")
    parser.add_argument(
        "--pin", action="store_true", help="server on CPU 1, this process on CPU 0 (taskset)"
    )
    parser.add_argument("--save", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(1)

    result: dict[str, Any] = {
        "scenario": args.scenario,
        "transport": args.transport,
        "machine": f"{platform.machine()}, Python {platform.python_version()}, "
        f"torch {torch.__version__}",
        "settings": args.set,
        "pinned": args.pin,
    }
    print(f"== update alone ({args.scenario} shapes, recommended learner)", flush=True)
    result["update"] = update_rate(args.scenario, compiled=True)
    if args.eager:
        result["update_eager"] = update_rate(args.scenario, compiled=False, n=500)
    if args.pin:
        os.sched_setaffinity(0, {0})
    server, addresses = start_server(args.transport, 1 if args.pin else None, args.servers)
    result["servers"] = args.servers
    try:
        print(f"== stepping through {addresses[0]} with IDM", flush=True)
        result["stepping"] = stepping_rate(addresses[0], args.scenario, args.stepping_seconds)
        print("== training (update-to-data ratio as configured, no evaluations)", flush=True)
        result["training"] = training_rate(
            addresses, args.scenario, args.seconds, args.learning_starts, args.set
        )
    finally:
        stop_process(server)
    print_result(result)
    if args.save:
        servers = f"-{args.servers}servers" if args.servers > 1 else ""
        path = RESULTS / f"learner-{args.scenario}-{args.transport}{servers}.json"
        path.write_text(json.dumps(result, indent=2) + "\n")
        print(f"wrote {path.relative_to(ROOT)}")
    return 0


def print_result(result: dict[str, Any]) -> None:
    update, stepping, training = result["update"], result["stepping"], result["training"]

    def rate(figures: dict[str, float]) -> str:
        return f"{figures['ms_per_update']:.3f} ms ({figures['updates_per_s']:,.0f}/s)"

    rows = [(f"{result['scenario']} over {result['transport']}://", "figure"), ("---", "---:")]
    rows.append(("update alone, compiled", rate(update)))
    if "update_eager" in result:
        rows.append(("update alone, eager", rate(result["update_eager"])))
    rows.append(("stepping, IDM, no updates", f"{stepping['env_steps_per_s']:,.0f} env steps/s"))
    rows.append(
        (
            f"training, {result['servers']} server(s)",
            f"{training['env_steps_per_s']:,.0f} env steps/s, "
            f"{training['updates_per_s']:,.0f} updates/s "
            f"(ratio {training['update_to_data']:.2f})",
        )
    )
    ratio = training["env_steps_per_s"] / stepping["env_steps_per_s"]
    rows.append(("training / stepping", f"{ratio:.2f}"))
    print()
    for name, value in rows:
        print(f"| {name} | {value} |")
    parts = ", ".join(f"{k} {v:.0f}" for k, v in training["profile"]["us_per_iteration"].items())
    print(f"\nper training iteration (us): {parts}")


if __name__ == "__main__":
    sys.exit(main())
