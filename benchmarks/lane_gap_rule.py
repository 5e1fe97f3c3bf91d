"""Does the lane gap rule keep the lane changes and drop the requests that cannot be granted?

Drives saved `cflc` policies on the same held-out seeds twice, with the gap rule
(`agent_client.rl.lanes.LaneChoice.gap_rule`) off and on, through a running server, and prints
per policy and rule: lane changes started, refused (by reason), started / instructions,
instructions per episode, average speed and collisions.

    sim-server --bind tcp://127.0.0.1:5555 &
    python benchmarks/lane_gap_rule.py --server tcp://127.0.0.1:5555 runs/A/policy.pt
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent_client.drivers.policy import load_policy_driver
from agent_client.envs.remote_env import RemoteEnv
from agent_client.evaluation.evaluate import evaluate_driver


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("policies", type=Path, nargs="+")
    parser.add_argument("--server", default="tcp://127.0.0.1:5555")
    parser.add_argument("--scenario", default="cflc")
    parser.add_argument("--episodes", type=int, default=12)
    parser.add_argument("--seed", type=int, default=200_000)
    args = parser.parse_args()
    seeds = list(range(args.seed, args.seed + args.episodes))
    env = RemoteEnv(args.server, args.scenario)
    try:
        for path in args.policies:
            for rule in (False, True):
                driver = load_policy_driver(path)
                driver.lanes = dataclasses.replace(driver.lanes, gap_rule=rule)
                records = evaluate_driver(env, driver, seeds)
                started = sum(r.summary.lane_changes_started for r in records)
                refused = sum(r.summary.lane_changes_refused for r in records)
                reasons: Counter[str] = Counter()
                for record in records:
                    reasons.update(record.refusals)
                speed = sum(r.summary.average_speed for r in records) / len(records)
                print(
                    f"{path} gap rule {'on ' if rule else 'off'}: started {started}, refused "
                    f"{refused} {dict(reasons)}, started/instructions "
                    f"{started / max(1, started + refused):.1%}, instructions per episode "
                    f"{(started + refused) / len(records):.1f}, speed {speed:.2f} m/s, "
                    f"collisions {sum(r.summary.collisions for r in records)}",
                    flush=True,
                )
    finally:
        env.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
