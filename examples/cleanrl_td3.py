"""A CleanRL-style single-file TD3 trained through a live sim-server: read it top to bottom.

    sim-server --bind tcp://127.0.0.1:5555 &
    python examples/cleanrl_td3.py --server tcp://127.0.0.1:5555 --total-timesteps 20000

Only gymnasium, numpy and torch: the env comes from ``gymnasium.make("av_bridge/Remote-v0")``
(a flat `Box` action, finite observation bounds rescaled to [-1, 1]); networks, replay buffer,
update and loop follow CleanRL's ``td3_continuous_action.py``. ``--json`` prints the greedy
return on held-out seeds before and after training and the training rate as one JSON object.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch
import torch.nn.functional as F
from gymnasium.wrappers import RescaleObservation
from torch import nn

import agent_client  # noqa: F401  (registers av_bridge/Remote-v0 with gymnasium)


@dataclass
class Args:
    server: str = "tcp://127.0.0.1:5555"
    """the sim-server's address"""
    scenario: str = "cf"
    """cf (one lane: Box(1)) or cflc (three lanes: Box(2), acceleration and lane choice)"""
    seed: int = 0
    total_timesteps: int = 20_000
    learning_starts: int = 1_000
    buffer_size: int = 100_000
    batch_size: int = 256
    gamma: float = 0.99
    tau: float = 0.005
    learning_rate: float = 3e-4
    exploration_noise: float = 0.1
    policy_noise: float = 0.2
    noise_clip: float = 0.5
    policy_frequency: int = 2
    decision_interval: float = 0.1
    """s per decision (a scenario option sent with every reset)"""
    episode_seconds: float = 60.0
    """max_episode_time of every episode"""
    eval_episodes: int = 3
    json: bool = False
    """print one JSON object"""


def parse_args() -> Args:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    for name, default in vars(Args()).items():
        flag = "--" + name.replace("_", "-")
        if isinstance(default, bool):
            parser.add_argument(flag, action="store_true")
        else:
            parser.add_argument(flag, type=type(default), default=default)
    return Args(**vars(parser.parse_args()))


def make_env(args: Args) -> gym.Env:
    env = gym.make(
        "av_bridge/Remote-v0",
        server=args.server,
        scenario=args.scenario,
        decision_interval=args.decision_interval,
        max_episode_time=args.episode_seconds,
    )
    shape = env.observation_space.shape
    return RescaleObservation(env, np.full(shape, -1, np.float32), np.full(shape, 1, np.float32))


class QNetwork(nn.Module):
    def __init__(self, obs_dim: int, act_dim: int) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(obs_dim + act_dim, 64), nn.ReLU(), nn.Linear(64, 64), nn.ReLU(),
            nn.Linear(64, 1),
        )  # fmt: skip

    def forward(self, x: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([x, a], 1))


class Actor(nn.Module):
    def __init__(self, obs_dim: int, act_dim: int) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(obs_dim, 64), nn.ReLU(), nn.Linear(64, 64), nn.ReLU(),
            nn.Linear(64, act_dim), nn.Tanh(),
        )  # fmt: skip

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)  # the env's action box is [-1, 1]: no scale or bias


class ReplayBuffer:
    def __init__(self, size: int, obs_dim: int, act_dim: int, seed: int) -> None:
        self.obs = np.zeros((size, obs_dim), np.float32)
        self.next_obs = np.zeros((size, obs_dim), np.float32)
        self.actions = np.zeros((size, act_dim), np.float32)
        self.rewards = np.zeros((size, 1), np.float32)
        self.terminated = np.zeros((size, 1), np.float32)  # not truncated: a time limit bootstraps
        self.size, self.n, self.pos = size, 0, 0
        self.rng = np.random.default_rng(seed)

    def add(self, obs: np.ndarray, next_obs: np.ndarray, action: np.ndarray, reward: float,
            terminated: bool) -> None:  # fmt: skip
        i = self.pos
        self.obs[i], self.next_obs[i], self.actions[i] = obs, next_obs, action
        self.rewards[i], self.terminated[i] = reward, terminated
        self.pos, self.n = (i + 1) % self.size, min(self.n + 1, self.size)

    def sample(self, batch: int) -> tuple[torch.Tensor, ...]:
        i = self.rng.integers(0, self.n, batch)
        arrays = (self.obs, self.actions, self.next_obs, self.rewards, self.terminated)
        return tuple(torch.from_numpy(a[i]) for a in arrays)


def greedy_return(actor: Actor, env: gym.Env, seeds: list[int]) -> float:
    returns = []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        total, done = 0.0, False
        while not done:
            with torch.no_grad():
                action = actor(torch.as_tensor(obs[None], dtype=torch.float32))[0].numpy()
            obs, reward, terminated, truncated, _ = env.step(action)
            total, done = total + float(reward), terminated or truncated
        returns.append(total)
    return float(np.mean(returns))


def main() -> None:
    args = parse_args()
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)
    rng = np.random.default_rng(args.seed)
    env = make_env(args)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]

    actor, actor_target = Actor(obs_dim, act_dim), Actor(obs_dim, act_dim)
    qf1, qf2 = QNetwork(obs_dim, act_dim), QNetwork(obs_dim, act_dim)
    qf1_target, qf2_target = QNetwork(obs_dim, act_dim), QNetwork(obs_dim, act_dim)
    actor_target.load_state_dict(actor.state_dict())
    qf1_target.load_state_dict(qf1.state_dict())
    qf2_target.load_state_dict(qf2.state_dict())
    q_optimizer = torch.optim.Adam([*qf1.parameters(), *qf2.parameters()], lr=args.learning_rate)
    actor_optimizer = torch.optim.Adam(actor.parameters(), lr=args.learning_rate)
    rb = ReplayBuffer(args.buffer_size, obs_dim, act_dim, args.seed)

    seeds = [10_000 + i for i in range(args.eval_episodes)]
    before = greedy_return(actor, env, seeds)
    started = time.perf_counter()
    obs, _ = env.reset(seed=args.seed)
    updates = 0
    for global_step in range(args.total_timesteps):
        if global_step < args.learning_starts:
            action = env.action_space.sample()
        else:
            with torch.no_grad():
                action = actor(torch.as_tensor(obs[None], dtype=torch.float32))[0].numpy()
            action = np.clip(action + rng.normal(0, args.exploration_noise, act_dim), -1, 1)
        next_obs, reward, terminated, truncated, _ = env.step(action.astype(np.float32))
        rb.add(obs, next_obs, action, float(reward), terminated)
        obs = next_obs
        if terminated or truncated:
            obs, _ = env.reset()

        if global_step < args.learning_starts:
            continue
        b_obs, b_actions, b_next_obs, b_rewards, b_terminated = rb.sample(args.batch_size)
        with torch.no_grad():
            clipped = (torch.randn_like(b_actions) * args.policy_noise).clamp(
                -args.noise_clip, args.noise_clip
            )
            next_actions = (actor_target(b_next_obs) + clipped).clamp(-1, 1)
            next_q = torch.min(
                qf1_target(b_next_obs, next_actions), qf2_target(b_next_obs, next_actions)
            )
            target = b_rewards + (1 - b_terminated) * args.gamma * next_q
        qf_loss = F.mse_loss(qf1(b_obs, b_actions), target) + F.mse_loss(
            qf2(b_obs, b_actions), target
        )
        q_optimizer.zero_grad()
        qf_loss.backward()
        q_optimizer.step()
        updates += 1

        if global_step % args.policy_frequency == 0:
            actor_loss = -qf1(b_obs, actor(b_obs)).mean()
            actor_optimizer.zero_grad()
            actor_loss.backward()
            actor_optimizer.step()
            with torch.no_grad():
                pairs = [(actor, actor_target), (qf1, qf1_target), (qf2, qf2_target)]
                for net, target_net in pairs:
                    for p, tp in zip(net.parameters(), target_net.parameters(), strict=True):
                        tp.lerp_(p, args.tau)

    seconds = time.perf_counter() - started
    after = greedy_return(actor, env, seeds)
    env.close()
    result = {
        "library": "cleanrl-style td3",
        "scenario": args.scenario,
        "steps": args.total_timesteps,
        "seconds": round(seconds, 2),
        "env_steps_per_s": round(args.total_timesteps / seconds, 1),
        "updates_per_s": round(updates / seconds, 1),
        "return_before": round(before, 3),
        "return_after": round(after, 3),
    }
    print(json.dumps(result) if args.json else result)


if __name__ == "__main__":
    main()
