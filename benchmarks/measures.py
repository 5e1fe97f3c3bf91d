"""What the measurement options cost: a SUMO step with ``ssm`` and ``report_traffic`` on and off.

Drives the same seeds of a scenario in this process through `SumoBackend` (libsumo) four ways,
interleaved round by round so that the machine's load falls on all of them alike, with the
client's IDM as the driver: plain, ``ssm`` (SUMO's SSM device on the ego, and the reload at the
end of the episode that writes its log out), ``report_traffic`` (every other vehicle on every
observation, encoded as a frame), and both. Prints the mean time per step (simulation, the
backend's reads, encoding the observation) and per episode end, their ratios to plain, and the
frame sizes; writes benchmarks/results/measures_SCENARIO.json.

    python benchmarks/measures.py                    # cf, 3 seeds x 3 rounds
    python benchmarks/measures.py --scenario cflc --seeds 2 --rounds 2
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
RESULTS = ROOT / "benchmarks" / "results"

from agent_client.drivers.idm import IDMDriver
from protocol.codec import encode
from sim_server.backends.options import merge_options
from sim_server.backends.sumo.backend import SumoBackend

VARIANTS: dict[str, dict[str, Any]] = {
    "plain": {},
    "ssm": {"ssm": True},
    "traffic": {"report_traffic": True},
    "both": {"ssm": True, "report_traffic": True},
}


def episode(
    backend: SumoBackend, scenario: str, seed: int, extra: dict[str, Any]
) -> dict[str, float]:
    """One episode: seconds stepping, seconds in the last step (the end), steps, frame bytes."""
    info = {s.name: s for s in backend.scenarios()}[scenario]
    options = merge_options(info, {"report_ceiling": False, "max_episode_time": 120.0, **extra})
    driver = IDMDriver()
    obs = backend.reset(scenario, seed, options)
    steps, stepping, frames, last = 0, 0.0, 0, 0.0
    while not (obs.terminated or obs.truncated):
        acceleration, lane_change = driver.act(obs)
        start = time.perf_counter()
        obs = backend.step(obs.seq + 1, acceleration, lane_change)
        frame = encode(obs)
        spent = time.perf_counter() - start
        stepping += spent
        frames += len(frame)
        steps += 1
        last = spent
    return {"seconds": stepping - last, "end_s": last, "steps": steps - 1, "bytes": frames / steps}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="cf")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    results: dict[str, list[dict[str, float]]] = {name: [] for name in VARIANTS}
    with tempfile.TemporaryDirectory() as cache:
        backend = SumoBackend(cache_dir=Path(cache))
        try:
            episode(backend, args.scenario, 0, {})  # build the scenario's files once
            for round_ in range(args.rounds):
                for seed in range(1, args.seeds + 1):
                    for name, extra in VARIANTS.items():
                        results[name].append(episode(backend, args.scenario, seed, extra))
                print(f"round {round_ + 1}/{args.rounds} done", flush=True)
        finally:
            backend.close()
    summary: dict[str, dict[str, float]] = {}
    for name, runs in results.items():
        steps = sum(r["steps"] for r in runs)
        summary[name] = {
            "ms_per_step": 1000 * sum(r["seconds"] for r in runs) / steps,
            "ms_episode_end": 1000 * statistics.mean(r["end_s"] for r in runs),
            "frame_bytes": statistics.mean(r["bytes"] for r in runs),
            "steps": steps,
        }
    plain = summary["plain"]
    print(f"{args.scenario}, {args.seeds} seeds x {args.rounds} rounds, IDM driver, libsumo:")
    for name, figures in summary.items():
        ratio = figures["ms_per_step"] / plain["ms_per_step"]
        figures["step_ratio_to_plain"] = ratio
        print(
            f"  {name:8s} {figures['ms_per_step']:.3f} ms/step ({ratio:.2f}x plain), "
            f"episode end {figures['ms_episode_end']:.1f} ms, frame {figures['frame_bytes']:.0f} B"
        )
    RESULTS.mkdir(parents=True, exist_ok=True)
    out = RESULTS / f"measures_{args.scenario}.json"
    out.write_text(json.dumps({"args": vars(args), "variants": summary}, indent=2) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
