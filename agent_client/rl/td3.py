"""DDPG and TD3 for a hybrid action: a continuous acceleration plus a discrete lane choice.

Design (one implementation; TD3 is a configuration of it, as in Stable-Baselines3):

- The actor mu(s) outputs the normalised acceleration in [-1, 1] (tanh); scaling to m/s^2 happens
  at the environment boundary, not here.
- The critic Q(s, a_acc) outputs one value per discrete lane choice (P-DQN style: one head per
  discrete action, sharing the continuous parameter). The greedy lane is argmax_k Q1(s, a_acc)_k
  for the acceleration actually applied; exploration of the lane is epsilon-greedy. With
  `n_lane_actions == 1` this is exactly DDPG/TD3.
- TD target: r + gamma (1 - terminated) max_k min_i Qtarget_i(s', mu_target(s') [+ smoothing])_k.
  Truncated transitions are stored with terminated = 0, so they still bootstrap.
- Critic loss: MSE or Huber between Q_i(s, a_acc)[k_taken] and the target, summed over critics.
- Actor loss: -mean(max_k Q1(s, mu(s))_k) + actor_l2 * sum(theta^2) + action_l2 * mean(mu(s)^2).
  The L2 term on the actor's parameters is the paper's "regularise the action network" (§4.3.1);
  the action term (as in OpenAI's HER) discourages a saturated tanh.
- The actor and all targets are updated every `policy_delay` critic updates (1: DDPG, 2: TD3).

Observation scaling is the caller's job. The caller owns the replay buffer: after each environment
step it runs `for _ in range(agent.updates_due(n)): agent.update(buffer.sample(batch_size))`
(or `agent.maybe_update(buffer, n)`), which realises `learning_starts` and a fractional
update-to-data ratio `updates_per_step`.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from agent_client.errors import UsageError
from agent_client.rl.noise import NOISE_KINDS, ActionNoise, make_noise
from agent_client.rl.replay import Batch, ReplayBuffer

_AGENT_FORMAT = "av-bridge-ddpg-agent"
_POLICY_FORMAT = "av-bridge-ddpg-policy"
_FORMAT_VERSION = 1


@dataclass(frozen=True)
class TD3Config:
    """Every hyper-parameter of the learner; `TD3Config.td3()` switches on the TD3 trio."""

    hidden_sizes: tuple[int, ...] = (64, 64)
    """Hidden layer widths of actor and critic (ReLU)."""
    actor_lr: float = 1e-4
    """Adam learning rate of the actor."""
    critic_lr: float = 1e-3
    """Adam learning rate of the critic(s)."""
    gamma: float = 0.99
    """Discount factor."""
    tau: float = 0.005
    """Soft target update rate: target <- tau * online + (1 - tau) * target."""
    batch_size: int = 256
    """Minibatch size the caller samples per update."""
    buffer_size: int = 300_000
    """Replay capacity in transitions."""
    learning_starts: int = 10_000
    """Transitions to collect before the first update."""
    updates_per_step: float = 1.0
    """Gradient updates per collected transition; 0.5 means one update every two steps."""
    noise: str = "gaussian"
    """Exploration noise on the normalised acceleration: "gaussian" or "ou"."""
    noise_sigma: float = 0.1
    """Standard deviation (Gaussian) or diffusion (OU) of the acceleration noise."""
    noise_theta: float = 0.15
    """OU mean-reversion rate."""
    noise_dt: float = 1e-2
    """OU time step."""
    lane_epsilon: float = 0.03
    """Probability of a uniformly random lane choice while exploring (per decision: at 0.1 s,
    0.03 asks for a lane change about every 5 s: two of the three random choices change)."""
    n_critics: int = 1
    """1 for DDPG, 2 for TD3's clipped double Q."""
    policy_delay: int = 1
    """Critic updates per actor and target update (TD3: 2)."""
    target_noise: float = 0.0
    """Std of TD3's target policy smoothing noise; 0 disables it."""
    target_noise_clip: float = 0.5
    """Clip of the target policy smoothing noise."""
    actor_l2: float = 1e-4
    """Weight of sum(actor parameters^2) in the actor loss (the paper's regularisation)."""
    action_l2: float = 0.0
    """Weight of mean(mu(s)^2) in the actor loss, to keep tanh out of saturation."""
    max_grad_norm: float | None = None
    """Clip each network's gradient to this global norm; None disables."""
    critic_loss: str = "mse"
    """Critic regression loss: "mse" or "huber" (delta 1)."""

    def __post_init__(self) -> None:
        if not self.hidden_sizes or any(h < 1 for h in self.hidden_sizes):
            raise UsageError(f"hidden_sizes must be positive widths, got {self.hidden_sizes}")
        if self.n_critics not in (1, 2):
            raise UsageError(f"n_critics must be 1 or 2, got {self.n_critics}")
        if self.policy_delay < 1:
            raise UsageError(f"policy_delay must be >= 1, got {self.policy_delay}")
        if self.critic_loss not in ("mse", "huber"):
            raise UsageError(f"critic_loss must be 'mse' or 'huber', got {self.critic_loss!r}")
        if self.noise not in NOISE_KINDS:
            raise UsageError(f"noise must be one of {NOISE_KINDS}, got {self.noise!r}")
        if not 0.0 <= self.lane_epsilon <= 1.0:
            raise UsageError(f"lane_epsilon must lie in [0, 1], got {self.lane_epsilon}")
        if not 0.0 < self.tau <= 1.0:
            raise UsageError(f"tau must lie in (0, 1], got {self.tau}")
        if self.updates_per_step <= 0:
            raise UsageError(f"updates_per_step must be > 0, got {self.updates_per_step}")
        if self.max_grad_norm is not None and self.max_grad_norm <= 0:
            raise UsageError(f"max_grad_norm must be > 0 or None, got {self.max_grad_norm}")

    @classmethod
    def ddpg(cls, **overrides: Any) -> TD3Config:
        """DDPG: one critic, no policy delay, no target smoothing."""
        return cls(**{"n_critics": 1, "policy_delay": 1, "target_noise": 0.0, **overrides})

    @classmethod
    def td3(cls, **overrides: Any) -> TD3Config:
        """TD3 (Fujimoto et al. 2018): twin critics, delay 2, target smoothing 0.2 (clip 0.5)."""
        return cls(**{"n_critics": 2, "policy_delay": 2, "target_noise": 0.2, **overrides})

    @property
    def algo(self) -> str:
        """ "ddpg", "td3" or "custom" for a mix of the two."""
        if (self.n_critics, self.policy_delay, self.target_noise) == (1, 1, 0.0):
            return "ddpg"
        if self.n_critics == 2 and self.policy_delay > 1 and self.target_noise > 0:
            return "td3"
        return "custom"

    def to_dict(self) -> dict[str, Any]:
        """Plain python values (safe for `torch.load(weights_only=True)`)."""
        d = dataclasses.asdict(self)
        d["hidden_sizes"] = list(self.hidden_sizes)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TD3Config:
        known = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(d) - set(known))
        if unknown:
            raise UsageError(f"unknown learner setting {unknown[0]!r}; known: {', '.join(known)}")
        return cls(**{**d, "hidden_sizes": tuple(d.get("hidden_sizes", cls.hidden_sizes))})


def _mlp(in_dim: int, hidden_sizes: tuple[int, ...], out_dim: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for width in hidden_sizes:
        layers += [nn.Linear(in_dim, width), nn.ReLU()]
        in_dim = width
    layers.append(nn.Linear(in_dim, out_dim))
    return nn.Sequential(*layers)


class Actor(nn.Module):
    """mu(s): observation -> normalised acceleration in [-1, 1], shape (B, 1)."""

    def __init__(self, obs_dim: int, hidden_sizes: tuple[int, ...]) -> None:
        super().__init__()
        self.net = _mlp(obs_dim, hidden_sizes, 1)
        last = self.net[-1]
        assert isinstance(last, nn.Linear)
        # Lillicrap et al.: a small last layer starts the policy near 0, away from tanh saturation.
        nn.init.uniform_(last.weight, -3e-3, 3e-3)
        nn.init.uniform_(last.bias, -3e-3, 3e-3)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.net(obs))


class Critic(nn.Module):
    """Q(s, a_acc): one value per discrete lane choice, shape (B, n_lane_actions)."""

    def __init__(self, obs_dim: int, n_lane_actions: int, hidden_sizes: tuple[int, ...]) -> None:
        super().__init__()
        self.net = _mlp(obs_dim + 1, hidden_sizes, n_lane_actions)

    def forward(self, obs: torch.Tensor, acceleration: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([obs, acceleration], dim=1))


def _as_batch(obs: np.ndarray, obs_dim: int, device: torch.device) -> torch.Tensor:
    arr = np.asarray(obs, dtype=np.float32)
    if arr.ndim != 2 or arr.shape[1] != obs_dim:
        raise ValueError(f"expected observations of shape (N, {obs_dim}), got {arr.shape}")
    return torch.from_numpy(arr).to(device)


def _as_single(obs: np.ndarray, obs_dim: int, device: torch.device) -> torch.Tensor:
    arr = np.asarray(obs, dtype=np.float32)
    if arr.shape != (obs_dim,):
        raise ValueError(f"expected one observation of shape ({obs_dim},), got {arr.shape}")
    return torch.from_numpy(arr).to(device).unsqueeze(0)


class Policy:
    """The deployable greedy policy: actor for the acceleration, critic 1 for the lane."""

    def __init__(
        self, actor: Actor, critic: Critic | None, obs_dim: int, n_lane_actions: int
    ) -> None:
        if n_lane_actions > 1 and critic is None:
            raise ValueError("a policy with several lane choices needs the critic")
        self.actor = actor
        self.critic = critic
        self.obs_dim = obs_dim
        self.n_lane_actions = n_lane_actions
        self.device = next(actor.parameters()).device

    @classmethod
    def from_state_dict(cls, state: dict[str, Any], device: str | torch.device = "cpu") -> Policy:
        """Build from `Agent.policy_state_dict()` (loaded with weights_only=True)."""
        if state.get("format") != _POLICY_FORMAT or state.get("version") != _FORMAT_VERSION:
            raise ValueError(
                f"not a {_POLICY_FORMAT} v{_FORMAT_VERSION} state: "
                f"{state.get('format')!r} v{state.get('version')!r}"
            )
        obs_dim, n_lane = int(state["obs_dim"]), int(state["n_lane_actions"])
        hidden = tuple(int(h) for h in state["hidden_sizes"])
        actor = Actor(obs_dim, hidden).to(device)
        actor.load_state_dict(state["actor"])
        critic = None
        if n_lane > 1:
            critic = Critic(obs_dim, n_lane, hidden).to(device)
            critic.load_state_dict(state["critic"])
        return cls(actor, critic, obs_dim, n_lane)

    @torch.no_grad()
    def act(self, obs: np.ndarray) -> tuple[float, int]:
        """Greedy (acceleration in [-1, 1], lane index) for one observation."""
        obs_t = _as_single(obs, self.obs_dim, self.device)
        acc = self.actor(obs_t)
        if self.critic is None:
            return float(acc[0, 0]), 0
        return float(acc[0, 0]), int(self.critic(obs_t, acc).argmax(dim=1)[0])

    @torch.no_grad()
    def act_batch(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Greedy actions for N observations: accelerations (N,) float32, lanes (N,) int64."""
        obs_t = _as_batch(obs, self.obs_dim, self.device)
        acc = self.actor(obs_t)
        if self.critic is None:
            lanes = np.zeros(len(obs_t), dtype=np.int64)
        else:
            lanes = self.critic(obs_t, acc).argmax(dim=1).cpu().numpy()
        return acc[:, 0].cpu().numpy(), lanes


class Agent:
    """The learner: networks, targets, optimisers, exploration and the update step."""

    def __init__(
        self,
        obs_dim: int,
        n_lane_actions: int,
        config: TD3Config | None = None,
        seed: int = 0,
        device: str | torch.device = "cpu",
        n_envs: int = 1,
    ) -> None:
        if obs_dim < 1 or n_lane_actions < 1 or n_envs < 1:
            raise ValueError(
                f"need obs_dim, n_lane_actions, n_envs >= 1, got {obs_dim}, {n_lane_actions}, "
                f"{n_envs}"
            )
        self.config = cfg = config if config is not None else TD3Config()
        self.obs_dim = obs_dim
        self.n_lane_actions = n_lane_actions
        self.device = torch.device(device)
        seeds = np.random.SeedSequence(seed).generate_state(3 + n_envs)
        # Weight initialisation draws from a private, seeded stream; the global torch RNG is left as
        # the caller had it.
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(int(seeds[0]))
            self.actor = Actor(obs_dim, cfg.hidden_sizes).to(self.device)
            self.critics = nn.ModuleList(
                Critic(obs_dim, n_lane_actions, cfg.hidden_sizes) for _ in range(cfg.n_critics)
            ).to(self.device)
        self.actor_target = copy.deepcopy(self.actor).requires_grad_(False)
        self.critic_targets = copy.deepcopy(self.critics).requires_grad_(False)
        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=cfg.actor_lr)
        self.critic_optimizer = torch.optim.Adam(self.critics.parameters(), lr=cfg.critic_lr)
        # Exploration (lane epsilon) and target smoothing each have their own generator.
        self.rng = np.random.default_rng(int(seeds[1]))
        self.torch_generator = torch.Generator().manual_seed(int(seeds[2]))
        self.noises: list[ActionNoise] = [
            make_noise(cfg.noise, cfg.noise_sigma, int(s), cfg.noise_theta, cfg.noise_dt)
            for s in seeds[3:]
        ]
        self.lane_epsilon = cfg.lane_epsilon
        """Current lane exploration probability; callers may decay it."""
        self.n_updates = 0
        """Critic updates done so far."""
        self.n_transitions = 0
        """Transitions counted by `updates_due`."""
        self._update_credit = 0.0

    # ---------------------------------------------------------------- acting

    @property
    def noise_scale(self) -> float:
        """Multiplier of the acceleration noise (shared by all environments)."""
        return self.noises[0].scale

    @noise_scale.setter
    def noise_scale(self, value: float) -> None:
        for noise in self.noises:
            noise.scale = float(value)

    def reset_noise(self, env_index: int | None = None) -> None:
        """Reset the noise process of one environment (or all) at an episode start."""
        targets = self.noises if env_index is None else [self.noises[env_index]]
        for noise in targets:
            noise.reset()

    @torch.no_grad()
    def act(self, obs: np.ndarray, explore: bool) -> tuple[float, int]:
        """(acceleration in [-1, 1], lane index) for one observation; uses env 0's noise."""
        obs_t = _as_single(obs, self.obs_dim, self.device)
        acc = float(self.actor(obs_t)[0, 0])
        if explore:
            acc = min(1.0, max(-1.0, acc + self.noises[0].sample()))
        if self.n_lane_actions == 1:
            return acc, 0
        if explore and self.rng.random() < self.lane_epsilon:
            return acc, int(self.rng.integers(self.n_lane_actions))
        acc_t = torch.tensor([[acc]], dtype=torch.float32, device=self.device)
        return acc, int(self.critics[0](obs_t, acc_t).argmax(dim=1)[0])

    @torch.no_grad()
    def act_batch(self, obs: np.ndarray, explore: bool) -> tuple[np.ndarray, np.ndarray]:
        """Actions for N observations (env i uses noise process i): (N,) float32, (N,) int64."""
        obs_t = _as_batch(obs, self.obs_dim, self.device)
        n = len(obs_t)
        acc_t = self.actor(obs_t)
        if explore:
            if n > len(self.noises):
                raise ValueError(f"{n} observations but the agent has n_envs={len(self.noises)}")
            noise = torch.tensor([[self.noises[i].sample()] for i in range(n)], dtype=torch.float32)
            acc_t = (acc_t + noise.to(self.device)).clamp(-1.0, 1.0)
        if self.n_lane_actions == 1:
            lanes = np.zeros(n, dtype=np.int64)
        else:
            lanes = self.critics[0](obs_t, acc_t).argmax(dim=1).cpu().numpy()
            if explore:
                random = self.rng.random(n) < self.lane_epsilon
                lanes[random] = self.rng.integers(self.n_lane_actions, size=int(random.sum()))
        return acc_t[:, 0].cpu().numpy(), lanes

    @torch.no_grad()
    def q_values(self, obs: np.ndarray, acceleration: np.ndarray | float) -> np.ndarray:
        """Q1 per lane choice: (n_lane_actions,) for one observation, (N, n_lane_actions) for N."""
        arr = np.asarray(obs, dtype=np.float32)
        single = arr.ndim == 1
        obs_t = _as_batch(arr.reshape(1, -1) if single else arr, self.obs_dim, self.device)
        acc = np.asarray(acceleration, dtype=np.float32).reshape(-1, 1)
        acc_t = torch.from_numpy(np.broadcast_to(acc, (len(obs_t), 1)).copy()).to(self.device)
        q = self.critics[0](obs_t, acc_t).cpu().numpy()
        return q[0] if single else q

    # -------------------------------------------------------------- learning

    def updates_due(self, n_transitions: int = 1) -> int:
        """Count `n_transitions` new transitions; return how many updates to run now."""
        self.n_transitions += n_transitions
        if self.n_transitions < self.config.learning_starts:
            return 0
        self._update_credit += n_transitions * self.config.updates_per_step
        n = int(self._update_credit + 1e-9)  # 1e-9: 10 * 0.1 must make one update
        self._update_credit -= n
        return n

    def maybe_update(self, buffer: ReplayBuffer, n_transitions: int = 1) -> dict[str, float] | None:
        """`updates_due` then that many updates from `buffer`; the last update's metrics or None."""
        metrics = None
        for _ in range(self.updates_due(n_transitions)):
            metrics = self.update(buffer.sample(self.config.batch_size))
        return metrics

    @torch.no_grad()
    def td_target(self, batch: Batch) -> torch.Tensor:
        """r + gamma (1 - terminated) max_k min_i Qtarget_i(s', mu_target(s') + smoothing)_k."""
        cfg = self.config
        next_acc = self.actor_target(batch.next_obs)
        if cfg.target_noise > 0:
            noise = torch.randn(next_acc.shape, generator=self.torch_generator)
            noise = (noise * cfg.target_noise).clamp(-cfg.target_noise_clip, cfg.target_noise_clip)
            next_acc = (next_acc + noise.to(self.device)).clamp(-1.0, 1.0)
        q_next = torch.stack([c(batch.next_obs, next_acc) for c in self.critic_targets])
        v_next = q_next.min(dim=0).values.max(dim=1).values
        return batch.reward + cfg.gamma * (1.0 - batch.terminated) * v_next

    def update(self, batch: Batch, actor: bool = True) -> dict[str, float]:
        """One critic step (and, every `policy_delay`, one actor and target step).

        With ``actor=False`` only the critic and its targets learn: used to evaluate a
        pre-trained actor before letting its gradient loose on it.
        """
        cfg = self.config
        batch = batch.to(self.device)
        target = self.td_target(batch)
        lane = batch.lane.unsqueeze(1)
        q_taken = [
            c(batch.obs, batch.acceleration).gather(1, lane).squeeze(1) for c in self.critics
        ]
        loss_fn = F.mse_loss if cfg.critic_loss == "mse" else F.huber_loss
        critic_loss = torch.stack([loss_fn(q, target) for q in q_taken]).sum()
        self.critic_optimizer.zero_grad(set_to_none=True)
        critic_loss.backward()
        critic_grad_norm = self._clip(self.critics.parameters())
        self.critic_optimizer.step()
        self.n_updates += 1
        metrics = {
            "critic_loss": float(critic_loss.detach()),
            "q_mean": float(q_taken[0].detach().mean()),
            "target_mean": float(target.mean()),
            "critic_grad_norm": critic_grad_norm,
        }
        if self.n_updates % cfg.policy_delay == 0:
            if actor:
                metrics.update(self._update_actor(batch.obs))
                self._soft_update(self.actor, self.actor_target)
            self._soft_update(self.critics, self.critic_targets)
        return metrics

    def behaviour_clone(
        self, obs: np.ndarray, acceleration: np.ndarray, epochs: int, batch_size: int = 256
    ) -> float:
        """Fit the actor to demonstrated normalised accelerations (MSE); returns the last loss.

        The paper's "primary trained parameter" (§4.3.2): start from an imitation of a
        calibrated driver instead of from zero. The target actor is synchronised afterwards.
        """
        obs_t = torch.as_tensor(np.asarray(obs, dtype=np.float32), device=self.device)
        target = torch.as_tensor(
            np.asarray(acceleration, dtype=np.float32).reshape(-1, 1), device=self.device
        )
        optimizer = torch.optim.Adam(self.actor.parameters(), lr=1e-3)
        loss = torch.zeros(())
        for _ in range(epochs):
            order = torch.from_numpy(self.rng.permutation(len(obs_t)))
            for start in range(0, len(order), batch_size):
                index = order[start : start + batch_size]
                loss = F.mse_loss(self.actor(obs_t[index]), target[index])
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
        self.actor_target.load_state_dict(self.actor.state_dict())
        return float(loss.detach())

    def _update_actor(self, obs: torch.Tensor) -> dict[str, float]:
        cfg = self.config
        mu = self.actor(obs)
        actor_loss = -self.critics[0](obs, mu).max(dim=1).values.mean()
        if cfg.actor_l2 > 0:
            squares = torch.stack([p.square().sum() for p in self.actor.parameters()])
            actor_loss = actor_loss + cfg.actor_l2 * squares.sum()
        if cfg.action_l2 > 0:
            actor_loss = actor_loss + cfg.action_l2 * mu.square().mean()
        self.actor_optimizer.zero_grad(set_to_none=True)
        actor_loss.backward(inputs=list(self.actor.parameters()))  # no critic weight gradients
        actor_grad_norm = self._clip(self.actor.parameters())
        self.actor_optimizer.step()
        return {
            "actor_loss": float(actor_loss.detach()),
            "actor_grad_norm": actor_grad_norm,
            "mu_abs_mean": float(mu.detach().abs().mean()),
        }

    def _clip(self, params: Any) -> float:
        max_norm = self.config.max_grad_norm
        norm = nn.utils.clip_grad_norm_(list(params), math.inf if max_norm is None else max_norm)
        return float(norm)

    @torch.no_grad()
    def _soft_update(self, online: nn.Module, target: nn.Module) -> None:
        tau = self.config.tau
        for p, tp in zip(online.parameters(), target.parameters(), strict=True):
            tp.lerp_(p, tau)

    # ----------------------------------------------------------- checkpoints

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume training bit for bit (safe types only)."""
        return {
            "format": _AGENT_FORMAT,
            "version": _FORMAT_VERSION,
            "obs_dim": self.obs_dim,
            "n_lane_actions": self.n_lane_actions,
            "config": self.config.to_dict(),
            "actor": self.actor.state_dict(),
            "actor_target": self.actor_target.state_dict(),
            "critics": self.critics.state_dict(),
            "critic_targets": self.critic_targets.state_dict(),
            "actor_optimizer": self.actor_optimizer.state_dict(),
            "critic_optimizer": self.critic_optimizer.state_dict(),
            "n_updates": self.n_updates,
            "n_transitions": self.n_transitions,
            "update_credit": self._update_credit,
            "lane_epsilon": self.lane_epsilon,
            "rng": self.rng.bit_generator.state,
            "torch_generator": self.torch_generator.get_state(),
            "noises": [noise.state_dict() for noise in self.noises],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore `state_dict()`; observation size, lane choices and networks must match."""
        if state.get("format") != _AGENT_FORMAT or state.get("version") != _FORMAT_VERSION:
            raise ValueError(
                f"not a {_AGENT_FORMAT} v{_FORMAT_VERSION} state: "
                f"{state.get('format')!r} v{state.get('version')!r}"
            )
        saved = TD3Config.from_dict(state["config"])
        mine = (self.obs_dim, self.n_lane_actions, self.config.hidden_sizes, self.config.n_critics)
        theirs = (state["obs_dim"], state["n_lane_actions"], saved.hidden_sizes, saved.n_critics)
        if mine != theirs:
            raise ValueError(
                "checkpoint does not fit this agent: (obs_dim, n_lane_actions, hidden_sizes, "
                f"n_critics) saved {theirs}, here {mine}"
            )
        if len(state["noises"]) != len(self.noises):
            raise ValueError(f"checkpoint has {len(state['noises'])} noise processes, need n_envs")
        self.actor.load_state_dict(state["actor"])
        self.actor_target.load_state_dict(state["actor_target"])
        self.critics.load_state_dict(state["critics"])
        self.critic_targets.load_state_dict(state["critic_targets"])
        self.actor_optimizer.load_state_dict(state["actor_optimizer"])
        self.critic_optimizer.load_state_dict(state["critic_optimizer"])
        self.n_updates = int(state["n_updates"])
        self.n_transitions = int(state["n_transitions"])
        self._update_credit = float(state["update_credit"])
        self.lane_epsilon = float(state["lane_epsilon"])
        self.rng.bit_generator.state = state["rng"]
        self.torch_generator.set_state(state["torch_generator"])
        for noise, noise_state in zip(self.noises, state["noises"], strict=True):
            noise.load_state_dict(noise_state)

    @classmethod
    def from_state_dict(
        cls, state: dict[str, Any], device: str | torch.device = "cpu", n_envs: int | None = None
    ) -> Agent:
        """An agent rebuilt with the checkpoint's own configuration, then restored."""
        n = len(state["noises"]) if n_envs is None else n_envs
        config = TD3Config.from_dict(state["config"])
        agent = cls(state["obs_dim"], state["n_lane_actions"], config, device=device, n_envs=n)
        agent.load_state_dict(state)
        return agent

    def policy_state_dict(self, averaged: bool = False) -> dict[str, Any]:
        """What a deployed greedy `Policy` needs: the actor, and critic 1 if lanes are chosen.

        ``averaged=True`` takes the target (Polyak-averaged) networks instead of the online ones.
        """
        actor, critic = self._deployed(averaged)
        state: dict[str, Any] = {
            "format": _POLICY_FORMAT,
            "version": _FORMAT_VERSION,
            "obs_dim": self.obs_dim,
            "n_lane_actions": self.n_lane_actions,
            "hidden_sizes": list(self.config.hidden_sizes),
            "actor": actor.state_dict(),
        }
        if self.n_lane_actions > 1:
            state["critic"] = critic.state_dict()
        return state

    def policy(self, averaged: bool = False) -> Policy:
        """A greedy `Policy` sharing this agent's (online or target) networks, no copy."""
        actor, critic = self._deployed(averaged)
        return Policy(actor, critic if self.n_lane_actions > 1 else None, self.obs_dim,
                      self.n_lane_actions)  # fmt: skip

    def _deployed(self, averaged: bool) -> tuple[Actor, Critic]:
        actor = self.actor_target if averaged else self.actor
        critic = (self.critic_targets if averaged else self.critics)[0]
        assert isinstance(critic, Critic)
        return actor, critic
