"""How fast a blocking evaluation runs: the learner driving its servers in lock-step, or one
worker process per server (`EvaluationPool`, what `agent-client train --eval-server ...`
uses, in the background or, with --set eval_while_training=false, while training waits).
Prints steps/s for each and their ratio.

Four `direct://` SUMO servers on free loopback ports (two for each way, so that neither waits
for the other's connections); the two ways take turns, `--rounds` times, on the same held-out
seeds with the same driver: IDM, and a policy file if one is given (a trained one: an
untrained policy's episodes end early). Ratios are of medians measured in one run.

    python benchmarks/evaluation_speed.py --policy runs/main/train-cf/policy.pt

This is a measurement, not a test.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent_client.drivers.episode import Driver
from agent_client.drivers.idm import IDMDriver
from agent_client.drivers.policy import load_policy_driver
from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import BridgeError
from agent_client.training.evaluations.inline import EvaluationJob, Evaluator
from agent_client.training.evaluations.pool import EvaluationPool
from benchmarks.learning import start_servers
from protocol.readiness import stop_process

FIRST_SEED = 100_000
"""Held-out seeds, as the trainer's evaluations use (`TrainConfig.eval_seed`)."""


def measure(run: Any, job: EvaluationJob) -> float:
    """Steps per second of one evaluation."""
    started = time.perf_counter()
    summaries = run(job)
    return sum(s.steps for s in summaries) / (time.perf_counter() - started)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="cf")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--policy", type=Path, help="a policy file to evaluate besides IDM")
    parser.add_argument("--save", type=Path, help="write the figures as JSON here")
    args = parser.parse_args()
    drivers: dict[str, Driver] = {"idm": IDMDriver()}
    if args.policy is not None:
        try:
            drivers["policy"] = load_policy_driver(args.policy)
        except (OSError, ValueError, BridgeError) as exc:
            print(f"error: --policy {args.policy}: {exc}", file=sys.stderr)
            return 2
    seeds = list(range(FIRST_SEED, FIRST_SEED + args.episodes))
    options = {"decision_interval": 0.1}
    supervisor, addresses = start_servers(4, "direct")
    envs: list[RemoteEnv] = []
    pool: EvaluationPool | None = None
    rates: dict[str, dict[str, list[float]]] = {
        name: {"lockstep": [], "workers": []} for name in drivers
    }
    try:
        envs = [RemoteEnv(a, args.scenario, reward="safe", **options) for a in addresses[:2]]
        pool = EvaluationPool(addresses[2:], args.scenario, "safe", {}, options)
        lockstep = Evaluator(envs).run
        for name, driver in drivers.items():  # once each, not timed: load the networks, warm up
            lockstep(EvaluationJob(name, driver, seeds[:1]))
            pool.run(EvaluationJob(name, driver, seeds[:1]))
        for round_ in range(args.rounds):
            for name, driver in drivers.items():
                for way, run in (("lockstep", lockstep), ("workers", pool.run)):
                    rates[name][way].append(measure(run, EvaluationJob(name, driver, seeds)))
                line = ", ".join(f"{way} {rates[name][way][-1]:,.0f}" for way in rates[name])
                print(f"round {round_ + 1}, {name}: {line} steps/s", flush=True)
    finally:
        if pool is not None:
            pool.close()
        for env in envs:
            env.close()
        stop_process(supervisor)
    figures = {}
    print()
    for name, ways in rates.items():
        medians = {way: statistics.median(values) for way, values in ways.items()}
        ratio = medians["workers"] / medians["lockstep"]
        figures[name] = {**ways, "median": medians, "ratio": ratio}
        print(f"{name}: lock-step {medians['lockstep']:,.0f} steps/s, one worker per server "
              f"{medians['workers']:,.0f} steps/s ({ratio:.2f}x)")  # fmt: skip
    if args.save is not None:
        policy = str(args.policy) if args.policy else None
        payload = {"scenario": args.scenario, "episodes": args.episodes, "rounds": args.rounds,
                   "policy": policy, "figures": figures}  # fmt: skip
        args.save.write_text(json.dumps(payload, indent=2))
        print(f"wrote {args.save}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
