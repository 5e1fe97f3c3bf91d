"""Stable-Baselines3's TD3 (or SAC) trained through a live sim-server, with no adapter.

    sim-server --bind tcp://127.0.0.1:5555 &
    python examples/sb3_td3.py --server tcp://127.0.0.1:5555 --scenario cf --steps 20000

`gymnasium.make("av_bridge/Remote-v0", ...)` gives a flat `Box` action (acceleration on `cf`,
acceleration + lane choice on `cflc`) and finite observation bounds, which `RescaleObservation`
maps onto [-1, 1]. Prints the greedy return on held-out seeds before and after training and the
training rate; ``--json`` prints them as one JSON object (the test suite and the benchmark
read it). Needs ``pip install 'av-bridge[client,sb3]'``.
"""

from __future__ import annotations

import argparse
import json
import time

import gymnasium
import numpy as np
import torch
from gymnasium.wrappers import RescaleObservation
from stable_baselines3 import SAC, TD3
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.noise import NormalActionNoise

import agent_client  # noqa: F401  (registers av_bridge/Remote-v0 with gymnasium)


def make_env(args: argparse.Namespace) -> gymnasium.Env:
    env = gymnasium.make(
        "av_bridge/Remote-v0",
        server=args.server,
        scenario=args.scenario,
        max_episode_time=args.episode_seconds,
        decision_interval=args.decision_interval,
    )
    shape = env.observation_space.shape
    low, high = np.full(shape, -1.0, np.float32), np.full(shape, 1.0, np.float32)
    return RescaleObservation(env, low, high)


def greedy_return(model: BaseAlgorithm, env: gymnasium.Env, seeds: list[int]) -> float:
    """Mean undiscounted return of the deterministic policy over `seeds`."""
    returns = []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        total, done = 0.0, False
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, reward, terminated, truncated, _ = env.step(action)
            total, done = total + float(reward), terminated or truncated
        returns.append(total)
    return float(np.mean(returns))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--server", default="tcp://127.0.0.1:5555")
    parser.add_argument("--scenario", default="cf")
    parser.add_argument("--algo", choices=("td3", "sac"), default="td3")
    parser.add_argument("--steps", type=int, default=20_000, help="training env steps")
    parser.add_argument("--learning-starts", type=int, default=1000)
    parser.add_argument("--episode-seconds", type=float, default=60.0, help="max_episode_time")
    parser.add_argument("--decision-interval", type=float, default=0.1, help="s per decision")
    parser.add_argument("--eval-episodes", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args()
    torch.set_num_threads(1)

    env = make_env(args)
    algo = {"td3": TD3, "sac": SAC}[args.algo]
    extra = {}
    if args.algo == "td3":
        width = env.action_space.shape[0]
        extra["action_noise"] = NormalActionNoise(np.zeros(width), np.full(width, 0.2))
    model = algo(
        "MlpPolicy",
        env,
        learning_starts=args.learning_starts,
        policy_kwargs={"net_arch": [64, 64]},
        seed=args.seed,
        verbose=0,
        **extra,
    )
    seeds = [10_000 + i for i in range(args.eval_episodes)]
    before = greedy_return(model, env, seeds)
    started = time.perf_counter()
    model.learn(total_timesteps=args.steps)
    seconds = time.perf_counter() - started
    after = greedy_return(model, env, seeds)
    env.close()
    result = {
        "library": f"stable-baselines3 {args.algo}",
        "scenario": args.scenario,
        "steps": args.steps,
        "seconds": round(seconds, 2),
        "env_steps_per_s": round(args.steps / seconds, 1),
        "updates_per_s": round(max(args.steps - args.learning_starts, 0) / seconds, 1),
        "return_before": round(before, 3),
        "return_after": round(after, 3),
    }
    if args.json:
        print(json.dumps(result))
    else:
        print(
            f"{result['library']} on {args.scenario}: greedy return {before:.2f} -> {after:.2f} "
            f"after {args.steps} steps in {seconds:.1f} s ({result['env_steps_per_s']} steps/s)"
        )


if __name__ == "__main__":
    main()
