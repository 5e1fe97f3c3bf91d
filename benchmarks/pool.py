"""One address, a pool of simulators: what ``sim-server --pool N`` delivers, in one run.

On one ``sim-server --pool N`` (SUMO, `cf` by default) and, for the hop's cost, one plain
``sim-server``:

* **one client**: an IDM driver, on the plain server and through the pool (the front's extra
  hop on every step);
* **independent drivers**: N processes, each an IDM driver on its own session of the pool (what
  the simulators deliver to clients that need no time of their own);
* **lock-step**: one `RemoteVectorEnv` over the pool's address N times;
* **training**: ``agent-client train``'s learner over the pool's address N times, evaluations
  off, with each ``--sampling`` kind asked for: ``local`` (lock-step in the learner's process)
  and ``processes`` (a sampling process per session while the learner updates) by default,
  timed once learning runs (after the warm-up and the compiled update's load: `scaling.training`;
  issue 35's target: >= 0.6x the independent drivers).

With ``--cpu`` (Linux), where the CPU went in each of the last two: every process's share of
a core and its CPU time per env step, by role (`benchmarks/cpu_use.py`), and how many of the
machine's cores were busy.

    python benchmarks/pool.py --pool 2 --seconds 30 [--cpu] [--set chunks_in_flight=2]
    python benchmarks/pool.py --pool 14 --seconds 20 --sampling processes --device cpu cuda

`--device` names the learner's devices, a training measurement each (the GPU machine's run:
scripts/device_check.sh). `--set` hands a training setting on to every training measurement (a
variant to compare with the defaults, in a run of its own: the ratio is to that run's drivers).
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import multiprocessing
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


from agent_client.drivers.idm import IDMDriver
from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import UsageError
from agent_client.training.config import TrainConfig, apply_overrides, parse_assignment
from benchmarks.cpu_use import CpuUse, describe
from benchmarks.scaling import stepping, training
from protocol.readiness import LISTENING, stop_process, wait_for_line


def start_server(backend: str, *extra: str) -> tuple[subprocess.Popen[str], str]:
    command = [sys.executable, "-m", "sim_server.cli", "--bind", "tcp://127.0.0.1:0",
               "--backend", backend, "--log-level", "WARNING", *extra]  # fmt: skip
    process = subprocess.Popen(command, stdout=subprocess.PIPE, text=True)
    try:
        return process, wait_for_line(process, LISTENING, 180.0)
    except Exception:
        stop_process(process)
        raise


def idm_driver(address: str, scenario: str, seconds: float, seed: int) -> int:
    """Steps one IDM driver takes in `seconds` (run in a process of its own)."""
    env = RemoteEnv(address, scenario, reward="ra3")
    driver = IDMDriver()
    try:
        steps, started = 0, time.monotonic()
        while time.monotonic() - started < seconds:
            env.send_reset(seed=seed + steps)
            obs = env.receive_reset_observation()
            while not (obs.terminated or obs.truncated) and time.monotonic() - started < seconds:
                env.send_command(*driver.act(obs))
                obs, _ = env.receive_observation()
                steps += 1
        return steps
    finally:
        env.close()


def independent(address: str, scenario: str, seconds: float, count: int) -> float:
    context = multiprocessing.get_context("spawn")
    with context.Pool(count) as workers:
        started = time.monotonic()
        steps = workers.starmap(
            idm_driver, [(address, scenario, seconds, seed) for seed in range(count)]
        )
        elapsed = time.monotonic() - started
    return sum(steps) / max(seconds, elapsed - 2.0)  # the processes' start-up is not stepping


def measure(
    args: argparse.Namespace,
    pool_address: str,
    plain: subprocess.Popen[str],
    plain_address: str,
    cpu: CpuUse | None,
) -> dict[str, Any]:
    """Every measurement of the table, one after the other (`cpu`: where the CPU went)."""
    row: dict[str, Any] = {
        "one_client_plain": idm_driver(plain_address, args.scenario, args.seconds, 0)
        / args.seconds,
        "one_client_pool": idm_driver(pool_address, args.scenario, args.seconds, 0) / args.seconds,
    }
    stop_process(plain)
    started = time.monotonic()
    row["independent_idm"] = independent(pool_address, args.scenario, args.seconds, args.pool)
    if cpu is not None:  # from after the drivers' start-up (a few seconds) to their end
        use = cpu.table(started + 6.0, time.monotonic() - 2.0, row["independent_idm"])
        row["cpu_independent_idm"] = use
        print(describe("independent IDM drivers (this process's children)", use), flush=True)
    lock_step = stepping([pool_address] * args.pool, args.scenario, args.seconds)
    row["lock_step"] = lock_step["env_steps_per_s"]
    for sampling, device in itertools.product(args.sampling, args.device):
        trained = training(
            [pool_address] * args.pool, args.scenario, args.seconds, sampling, device,
            settings=args.settings,
        )  # fmt: skip
        rate = trained["train_env_steps_per_s"]
        name = training_key(sampling, device)
        row[name] = rate
        row[f"{name}_updates_per_s"] = trained["updates_per_s"]
        row[f"{name}_sampling"] = trained["sampling"]  # what auto resolved to
        if cpu is not None:  # the first second after learning began may hold the load's end
            use = cpu.table(trained["timed_from"] + 1.0, trained["timed_to"] - 1.0, rate)
            row[f"cpu_{name}"] = use
            print(describe(f"training, sampling {sampling}, learner on {device}", use), flush=True)
    return row


def training_key(sampling: str, device: str) -> str:
    """The row of a training measurement: ``training_processes`` on the CPU (as before there
    was a device to choose), ``training_processes_cuda`` on a GPU."""
    return f"training_{sampling}" if device == "cpu" else f"training_{sampling}_{device}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pool", type=int, default=2, help="simulators in the pool")
    parser.add_argument("--seconds", type=float, default=30.0, help="per measurement")
    parser.add_argument("--scenario", default="cf")
    parser.add_argument("--backend", default="sumo")
    parser.add_argument(
        "--sampling", nargs="+", default=["local", "processes"], help="training's sampling kinds"
    )
    parser.add_argument(
        "--device", nargs="+", default=["cpu"], help="the learner's devices (cpu, cuda, ...)"
    )
    parser.add_argument("--cpu", action="store_true", help="where the CPU went, by process")
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="for every training"
    )
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/pool.json")
    args = parser.parse_args()
    try:  # a typo now, not minutes in
        settings = [parse_assignment(text) for text in args.set]
        for assignment in [*settings, *({"device": device} for device in args.device)]:
            apply_overrides(TrainConfig(), assignment)
    except UsageError as exc:
        parser.error(str(exc))
    for option in ("sampling", "device"):
        if any(option in assignment for assignment in settings):
            parser.error(f"--set {option}=...: use --{option} (each is a row of its own)")
    args.settings = settings

    pool, pool_address = start_server(args.backend, "--pool", str(args.pool))
    plain, plain_address = start_server(args.backend)
    cpu = CpuUse({pool.pid: ("pool front", "simulators")}) if args.cpu else None
    try:
        with cpu or contextlib.nullcontext():
            row = measure(args, pool_address, plain, plain_address, cpu)
    finally:
        stop_process(plain)
        stop_process(pool)
    independent_rate = row["independent_idm"]
    print(f"\n{args.backend}/{args.scenario}, pool of {args.pool}, {os.cpu_count()} cores, "
          f"{platform.node()}, {args.seconds:g} s each:")  # fmt: skip
    print("| clients | env steps/s | x |")
    print("| --- | --- | --- |")
    print(f"| one IDM driver, plain server | {row['one_client_plain']:.0f} | |")
    print(f"| one IDM driver, through the pool | {row['one_client_pool']:.0f} | "
          f"{row['one_client_pool'] / row['one_client_plain']:.2f} of plain |")  # fmt: skip
    rows = [("independent_idm", f"{args.pool} independent IDM drivers"),
            ("lock_step", f"lock-step vector env of {args.pool}")]  # fmt: skip
    rows += [(training_key(kind, device),
              f"training over {args.pool} sessions, sampling {kind}, learner on {device}")
             for kind, device in itertools.product(args.sampling, args.device)]  # fmt: skip
    for name, label in rows:
        print(f"| {label} | {row[name]:.0f} | {row[name] / independent_rate:.2f} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    record = {"cores": os.cpu_count(), "pool": args.pool, "scenario": args.scenario,
              "seconds": args.seconds, "settings": args.set, **row}  # fmt: skip
    args.out.write_text(json.dumps(record, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
