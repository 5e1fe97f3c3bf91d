"""How fast is the highway-env backend? Steps/s in-process and through the bridge.

For each scenario, the same episodes (seeds ``--seed + k``) driven by the same policy (IDM,
keeping its lane) at 0.1 s decisions, so that one step is one simulation step:

* ``inproc``  - `HighwayBackend` called directly in this process;
* ``bridge``  - a real ``sim-server --backend highway`` subprocess on a free loopback port, this
  process the client (`agent_client.transport.ZmqChannel`);
* ``sumo``    - (``--sumo``) `SumoBackend` in-process on the same-named scenario, for reference.

Only steps are timed, with ``report_ceiling`` off; resets and the ceiling's run-on (the
simulation of the leader-at-entry to the end of the road after an episode ends early) are timed
apart, in-process.

    python benchmarks/highway_speed.py                    # cf and cflc, 3000 steps each
    python benchmarks/highway_speed.py --steps 10000 --sumo --json

A measurement, not a test: the machine is shared and noisy; repeat a run to see the spread.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent_client.drivers.idm import IDMDriver
from agent_client.transport import ZmqChannel
from protocol.messages import Observation, OptionValue, Reset, Step
from protocol.readiness import LISTENING, wait_for_line
from sim_server.backends.highway import HighwayBackend

StepFn = Callable[[int, float, int], Observation]
ResetFn = Callable[[int], Observation]


def drive(reset: ResetFn, step: StepFn, steps: int, seed: int) -> tuple[int, float, int]:
    """`steps` IDM steps over as many episodes as needed; (steps, seconds stepping, episodes)."""
    driver, done, elapsed, episodes = IDMDriver(), 0, 0.0, 0
    while done < steps:
        obs, seq = reset(seed + episodes), 0
        episodes += 1
        while done < steps and not (obs.terminated or obs.truncated):
            seq += 1
            acceleration, _ = driver.act(obs)
            started = time.perf_counter()
            obs = step(seq, acceleration, 0)
            elapsed += time.perf_counter() - started
            done += 1
    return done, elapsed, episodes


def scenario_options(backend: Any, scenario: str, **changes: OptionValue) -> dict[str, Any]:
    info = {s.name: s for s in backend.scenarios()}[scenario]
    return {**info.options, **changes}


def in_process(scenario: str, steps: int, seed: int) -> dict[str, float]:
    backend = HighwayBackend()
    options = scenario_options(backend, scenario, report_ceiling=False)
    done, elapsed, episodes = drive(
        lambda s: backend.reset(scenario, s, options), backend.step, steps, seed
    )
    return {"steps": done, "steps_per_s": done / elapsed, "episodes": episodes}


def resets_and_run_on(scenario: str, seed: int, count: int = 3) -> dict[str, float]:
    """Mean reset time, and the time the ceiling adds to an episode cut after 20 s."""
    backend = HighwayBackend()
    resets, run_ons = [], []
    for k in range(count):
        for ceiling in (False, True):
            options = scenario_options(
                backend, scenario, max_episode_time=20.0, report_ceiling=ceiling
            )
            started = time.perf_counter()
            obs = backend.reset(scenario, seed + k, options)
            resets.append(time.perf_counter() - started)
            seq, started = 0, time.perf_counter()
            while not (obs.terminated or obs.truncated):
                seq += 1
                obs = backend.step(seq, 0.0, 0)
            run_ons.append((1 if ceiling else -1) * (time.perf_counter() - started))
    return {"reset_s": sum(resets) / len(resets), "ceiling_run_on_s": sum(run_ons) / count}


@contextmanager
def server() -> Iterator[str]:
    command = [sys.executable, "-m", "sim_server.cli", "--bind", "tcp://127.0.0.1:0",
               "--backend", "highway", "--log-level", "WARNING"]  # fmt: skip
    process = subprocess.Popen(command, stdout=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        yield wait_for_line(process, LISTENING, 60.0)
    finally:
        process.send_signal(signal.SIGTERM)
        process.wait(timeout=30)


def through_bridge(scenario: str, steps: int, seed: int) -> dict[str, float]:
    with server() as address, ZmqChannel(address, timeout_s=120.0) as connection:
        connection.hello()
        options: dict[str, OptionValue] = {"report_ceiling": False}

        def reset(episode_seed: int) -> Observation:
            reply = connection.request(Reset(scenario, episode_seed, options))
            assert isinstance(reply, Observation), reply
            return reply

        def step(seq: int, acceleration: float, lane_change: int) -> Observation:
            reply = connection.request(Step(seq, acceleration, lane_change))
            assert isinstance(reply, Observation), reply
            return reply

        done, elapsed, episodes = drive(reset, step, steps, seed)
    return {"steps": done, "steps_per_s": done / elapsed, "episodes": episodes}


def sumo_in_process(scenario: str, steps: int, seed: int) -> dict[str, float]:
    import tempfile

    from sim_server.backends.sumo.backend import SumoBackend

    with tempfile.TemporaryDirectory() as cache:
        backend = SumoBackend(cache_dir=Path(cache))
        options = scenario_options(backend, scenario, report_ceiling=False)
        try:
            done, elapsed, episodes = drive(
                lambda s: backend.reset(scenario, s, options), backend.step, steps, seed
            )
        finally:
            backend.close()
    return {"steps": done, "steps_per_s": done / elapsed, "episodes": episodes}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", nargs="+", default=["cf", "cflc"])
    parser.add_argument("--steps", type=int, default=3000, help="timed steps per variant")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--sumo", action="store_true", help="also time SumoBackend in-process")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args()
    machine = {"cpus": os.cpu_count(), "python": platform.python_version()}
    results: dict[str, Any] = {"machine": {**machine, "load": os.getloadavg()}, "scenarios": {}}
    for scenario in args.scenarios:
        figures: dict[str, Any] = {
            "inproc": in_process(scenario, args.steps, args.seed),
            "bridge": through_bridge(scenario, args.steps, args.seed),
            **resets_and_run_on(scenario, args.seed),
        }
        if args.sumo:
            figures["sumo_inproc"] = sumo_in_process(scenario, args.steps, args.seed)
        results["scenarios"][scenario] = figures
        if not args.json:
            line = (
                f"{scenario:5s} in-process {figures['inproc']['steps_per_s']:7.0f} steps/s | "
                f"bridge {figures['bridge']['steps_per_s']:7.0f} steps/s | "
                f"reset {figures['reset_s']:.2f} s | "
                f"ceiling run-on {figures['ceiling_run_on_s']:.2f} s"
            )
            if args.sumo:
                line += f" | SUMO in-process {figures['sumo_inproc']['steps_per_s']:7.0f} steps/s"
            print(line, flush=True)
    if args.json:
        print(json.dumps(results, indent=2))
    else:
        print(f"(0.1 s decisions, IDM driver, {args.steps} steps; load {os.getloadavg()})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
