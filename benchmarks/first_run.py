"""A newcomer's first run: `agent-client train --scenario S --stop-when-converged`, nothing else.

Starts one default `sim-server` (SUMO through libsumo) on a free loopback port, then runs the
plain training command against it for each scenario and seed, as a separate process with no
other flag than `--server` (the free port), `--seed` and `--out`, and measures what a user
sees: whether it converged, at which episode and env step, the wall time from the command to
its exit, and the env steps per second while learning (the median over the episodes after
learning began) and over the whole command (start-up and evaluations included).

    python benchmarks/first_run.py --scenario cf cflc --seeds 0 7
    python benchmarks/first_run.py --scenario cflc --seeds 7 --set reward_params.headway_sigma=0.2

`--set` hands a setting on to every command (a variant of the defaults, to compare with them).

Seeds other than the ones the recommended settings were tuned on (0-2) are the honest test.
This is a measurement, not a test: minutes per run.
"""

from __future__ import annotations

import argparse
import json
import platform
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent_client.training.run_log import read_rows
from protocol.readiness import LISTENING, stop_process, wait_for_line

CONVERGED = re.compile(r"converged at episode (\d+)")
RUN_TIMEOUT_S = 3600.0
"""The longest one run may take (the default episode cap ends it long before)."""


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", nargs="+", default=["cf", "cflc"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 7])
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "first-run")
    parser.add_argument("--results", type=Path, help="JSON file (default: OUT/first_run.json)")
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="for every command"
    )
    args = parser.parse_args()
    server = subprocess.Popen(
        [sys.executable, "-m", "sim_server.cli", "--bind", "tcp://127.0.0.1:0",
         "--log-level", "WARNING"],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
    )  # fmt: skip
    runs: list[dict[str, Any]] = []
    results = args.results or args.out / "first_run.json"
    results.parent.mkdir(parents=True, exist_ok=True)
    machine = f"{platform.node()} {platform.machine()}, {platform.python_version()}"
    try:
        address = wait_for_line(server, LISTENING, 120.0)
        for scenario in args.scenario:
            for seed in args.seeds:
                out = args.out / f"{scenario}-{seed}"
                run = first_run(address, scenario, seed, out, args.set)
                runs.append(run)
                print(line(run), flush=True)
                results.write_text(json.dumps({"machine": machine, "runs": runs}, indent=2))
    finally:
        stop_process(server)
    print()
    print(table(runs))
    print(f"wrote {results}")
    return 0


def first_run(
    address: str, scenario: str, seed: int, out: Path, settings: list[str]
) -> dict[str, Any]:
    """Run the plain command once (with `settings` as ``--set``) and read what it did from its
    output and run folder."""
    command = [
        sys.executable, "-m", "agent_client", "train", "--server", address,
        "--scenario", scenario, "--seed", str(seed), "--stop-when-converged", "--out", str(out),
        *[arg for setting in settings for arg in ("--set", setting)],
    ]  # fmt: skip
    print(f"== {' '.join(command[2:])}", flush=True)
    started = time.perf_counter()
    result = subprocess.run(
        command, capture_output=True, text=True, check=False, timeout=RUN_TIMEOUT_S
    )
    wall = time.perf_counter() - started
    if result.returncode != 0:
        raise SystemExit(f"train failed ({result.returncode}): {result.stderr[-2000:]}")
    rows = read_rows(out / "episodes.csv")
    converged = CONVERGED.search(result.stdout)
    config = json.loads((out / "config.json").read_text())
    starts = int(config["learner"]["learning_starts"])
    rates, last_step, last_wall = [], 0, 0.0
    for row in rows:
        step, at = int(row["global_step"]), float(row["wall_time"])
        if last_step >= starts and at > last_wall:
            rates.append((step - last_step) / (at - last_wall))
        last_step, last_wall = step, at
    return {
        "scenario": scenario,
        "seed": seed,
        "settings": settings,
        "converged_episode": int(converged.group(1)) if converged else None,
        "episodes": len(rows),
        "env_steps": last_step,
        "wall_minutes": wall / 60.0,
        "learning_steps_per_s": statistics.median(rates) if rates else None,
        "overall_steps_per_s": last_step / wall,
        "evaluations": _evaluation_line(result.stdout + result.stderr),
    }


def _evaluation_line(output: str) -> str:
    """Where the command said its evaluations run."""
    for text in output.splitlines():
        if text.startswith("evaluation simulator:"):
            return text
    return ""


def line(run: dict[str, Any]) -> str:
    converged = run["converged_episode"]
    verdict = f"converged at episode {converged}" if converged else "not converged"
    return (
        f"   {run['scenario']} seed {run['seed']}: {verdict} ({run['env_steps']:,} env steps), "
        f"{run['wall_minutes']:.1f} min, {_rate(run['learning_steps_per_s'])} env steps/s "
        f"learning, {_rate(run['overall_steps_per_s'])} overall"
    )


def _rate(value: float | None) -> str:
    return "-" if value is None else f"{value:,.0f}"


def table(runs: list[dict[str, Any]]) -> str:
    lines = [
        "| scenario, seed | converged (episode, env steps) | wall time (min) | env steps/s "
        "learning / overall |",
        "| --- | --- | --- | --- |",
    ]
    for run in runs:
        converged = run["converged_episode"]
        verdict = (
            f"episode {converged}, {run['env_steps']:,}"
            if converged
            else f"no: {run['episodes']} episodes, {run['env_steps']:,}"
        )
        lines.append(
            f"| `{run['scenario']}`, {run['seed']} | {verdict} | {run['wall_minutes']:.1f} "
            f"| {_rate(run['learning_steps_per_s'])} / {_rate(run['overall_steps_per_s'])} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
