"""RLlib's PPO (new API stack) trained through live sim-servers, one per env runner.

    sim-server --workers 2 --bind tcp://127.0.0.1:5555 &          # ports 5555 and 5556
    python examples/rllib_ppo.py --server tcp://127.0.0.1:5555 --server tcp://127.0.0.1:5556

Each of RLlib's env runners drives its own server (`agent_client.rllib`), so RLlib's own
distributed sampling spreads over the simulators; with ``--ray-address auto`` the same script
runs on a Ray cluster (docs/ray.md). ``--json`` prints the training rate and the mean episode
return of the first and last iteration as one JSON object. Needs
``pip install 'av-bridge[client,rllib]'``.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import ray
from ray.rllib.algorithms.ppo import PPOConfig

from agent_client import rllib


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--server", action="append", required=True, help="one per env runner")
    parser.add_argument("--scenario", default="cf")
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--batch", type=int, default=2000, help="env steps per iteration")
    parser.add_argument("--decision-interval", type=float, default=0.1)
    parser.add_argument("--episode-seconds", type=float, default=60.0)
    parser.add_argument("--ray-address", default=None, help="a running cluster (default: local)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()

    if args.ray_address is None:  # a local Ray on loopback, sized for the env runners
        os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
        ray.init(num_cpus=len(args.server) + 1, include_dashboard=False)
    else:
        ray.init(address=args.ray_address)
    env_config = {
        "servers": args.server,
        "scenario": args.scenario,
        "decision_interval": args.decision_interval,
        "max_episode_time": args.episode_seconds,
    }
    config = (
        PPOConfig()
        .environment(rllib.register(), env_config=env_config)
        .env_runners(num_env_runners=len(args.server), num_envs_per_env_runner=1)
        .training(
            train_batch_size_per_learner=args.batch,
            minibatch_size=min(256, args.batch),
            num_epochs=5,
            lr=3e-4,
            gamma=0.98,
        )
        .rl_module(model_config={"fcnet_hiddens": [64, 64]})
    )
    algo = config.build_algo()
    returns, started, steps = [], time.perf_counter(), 0
    for _ in range(args.iterations):
        result = algo.train()
        runners = result["env_runners"]
        steps = int(
            result.get(
                "num_env_steps_sampled_lifetime", runners.get("num_env_steps_sampled_lifetime", 0)
            )
        )
        returns.append(float(runners.get("episode_return_mean", float("nan"))))
    seconds = time.perf_counter() - started
    algo.stop()
    ray.shutdown()
    summary = {
        "library": "rllib ppo",
        "scenario": args.scenario,
        "env_runners": len(args.server),
        "steps": steps,
        "seconds": round(seconds, 2),
        "env_steps_per_s": round(steps / seconds, 1),
        "return_first_iteration": returns[0],
        "return_last_iteration": returns[-1],
    }
    print(json.dumps(summary) if args.json else summary)


if __name__ == "__main__":
    main()
