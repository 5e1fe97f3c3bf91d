"""TD3 and DDPG for a hybrid action: a continuous acceleration plus a discrete lane choice.

One implementation; DDPG is a configuration of it, as in Stable-Baselines3 (`TD3Config.ddpg`).

- The actor mu(s) outputs the normalised acceleration in [-1, 1] (tanh); scaling to m/s^2 happens
  at the environment boundary, not here.
- The critic Q(s, a_acc) outputs one value per discrete lane choice (P-DQN style: one head per
  discrete action, sharing the continuous parameter). The greedy lane is the best *valid* one
  (`mask`: a choice that cannot happen, e.g. a lane that does not exist, is never taken, never
  explored and never bootstrapped from); exploration of the lane is epsilon-greedy over the
  valid choices. With one lane choice this is exactly DDPG/TD3.
- The update (losses, targets, delays) is `agent_client.rl.update`; the networks are plain
  tensors (`agent_client.rl.networks`); acting reads them as numpy views.

Observation scaling is the caller's job. The caller owns the replay buffer: after each environment
step it runs ``for _ in range(agent.updates_due(n)): agent.update(buffer.sample(batch_size))``
(or `agent.maybe_update(buffer, n)`), which realises `learning_starts` and a fractional
update-to-data ratio `updates_per_step`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from agent_client.errors import UsageError
from agent_client.rl.greedy import NumpyActor, NumpyCritic, all_valid
from agent_client.rl.lanes import choose_lanes
from agent_client.rl.networks import (
    Params,
    actor_forward,
    critics_forward,
    init_actor,
    init_critics,
    numpy_views,
)
from agent_client.rl.noise import NOISE_KINDS, ActionNoise, make_noise
from agent_client.rl.optim import AdamState
from agent_client.rl.policy import POLICY_FORMAT, POLICY_VERSION, Policy
from agent_client.rl.replay import Batch, ReplayBuffer
from agent_client.rl.update import INVALID, METRICS, Hyper, LearnerState, Tensors, make_steps

NETWORKS = (
    "actor",
    "actor_target",
    "critics",
    "critic_targets",
    "actor_average",
    "critics_average",
)
"""The parameter lists of `LearnerState`, as checkpoints hold them."""
SMOOTHING_POOL = 64
"""Batches of target-smoothing noise drawn at once."""
AGENT_FORMAT = "av-bridge-td3-agent"
AGENT_VERSION = 2


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
    deploy_tau: float = 0.005
    """Rate of the slow average of actor and critics that is evaluated and deployed (updated with
    the actor): a smaller value averages over more updates, a steadier policy that lags more.
    At the default (= `tau`) the deployed actor equals the target actor (as before this knob
    existed); a smaller value gives the steadier average without slowing the targets."""
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
    """Probability of a uniformly random choice among the valid lane choices while exploring, at
    every decision. Between two lane decisions only "keep" is valid, so with lane decisions
    every 1 s it asks for a random lane change about every 50 s of driving."""
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
    """Weight of mean(mu(s)^2) in the actor loss, to keep tanh out of saturation. (Centring it
    on the normalised zero acceleration instead of 0 was measured: no faster on cf.)"""
    smoothness: float = 0.0
    """Weight of mean((mu(s) - mu(s'))^2) in the actor loss: the policy's change between
    consecutive states, i.e. its jerk (CAPS, Mysore et al. 2021); 0 disables it."""
    max_grad_norm: float | None = None
    """Clip each network's gradient to this global norm; None disables."""
    critic_loss: str = "mse"
    """Critic regression loss: "mse" or "huber" (delta 1)."""
    compile: bool = True
    """Compile the update step (torch.compile, ~15 s the first time; cached on disk, ~4 s to
    load in each new process): ~3.5x faster updates. Off, the same functions run eagerly (for
    tests and debugging)."""

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
        if not 0.0 < self.deploy_tau <= 1.0:
            raise UsageError(f"deploy_tau must lie in (0, 1], got {self.deploy_tau}")
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


class Agent:
    """The learner: networks, targets, optimisers, exploration and the update step."""

    def __init__(
        self,
        obs_dim: int,
        n_lane_actions: int,
        config: TD3Config | None = None,
        seed: int = 0,
        n_envs: int = 1,
        device: str | torch.device = "cpu",
    ) -> None:
        """`device`: where the networks learn (`resolve_device`); acting stays on the CPU, on
        a copy refreshed after every update call where the device is another."""
        if obs_dim < 1 or n_lane_actions < 1 or n_envs < 1:
            raise ValueError(
                f"need obs_dim, n_lane_actions, n_envs >= 1, got {obs_dim}, {n_lane_actions}, "
                f"{n_envs}"
            )
        self.config = cfg = config if config is not None else TD3Config()
        self.obs_dim = obs_dim
        self.n_lane_actions = n_lane_actions
        seeds = np.random.SeedSequence(seed).generate_state(3 + n_envs)
        init = torch.Generator().manual_seed(int(seeds[0]))
        self.device = torch.device(device)
        actor = [p.to(self.device) for p in init_actor(obs_dim, cfg.hidden_sizes, init)]
        critics = [
            p.to(self.device)
            for p in init_critics(obs_dim, n_lane_actions, cfg.hidden_sizes, cfg.n_critics, init)
        ]
        self.state = LearnerState(
            actor=actor,
            critics=critics,
            actor_target=[p.clone() for p in actor],
            critic_targets=[p.clone() for p in critics],
            actor_adam=AdamState.zeros_like(actor),
            critic_adam=AdamState.zeros_like(critics),
            actor_average=[p.clone() for p in actor],
            critics_average=[p.clone() for p in critics],
        )
        self._on_cpu = self.device.type == "cpu"
        self._acting = (actor, critics) if self._on_cpu else (_cpu_copy(actor), _cpu_copy(critics))
        """The networks acting reads: the learner's own on the CPU, else copies of them."""
        self._act_actor = NumpyActor(numpy_views(self._acting[0]))
        self._act_critic = NumpyCritic(numpy_views(self._acting[1]))
        self._steps = make_steps(_hyper(cfg), cfg.compile)
        # Exploration (lane epsilon) and target smoothing each have their own generator.
        self.rng = np.random.default_rng(int(seeds[1]))
        self.torch_generator = torch.Generator().manual_seed(int(seeds[2]))
        self.noises: list[ActionNoise] = [
            make_noise(cfg.noise, cfg.noise_sigma, int(s), cfg.noise_theta, cfg.noise_dt)
            for s in seeds[3:]
        ]
        self.lane_epsilon = cfg.lane_epsilon
        """Current lane exploration probability; callers may decay it."""
        self._smoothing_pool: torch.Tensor | None = None
        self._smoothing_next = 0
        self.n_updates = 0
        """Critic updates done so far."""
        self.n_transitions = 0
        """Transitions counted by `updates_due`."""
        self._update_credit = 0.0

    @property
    def actor(self) -> Params:
        return self.state.actor

    @property
    def critics(self) -> Params:
        return self.state.critics

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

    def act(
        self, obs: np.ndarray, explore: bool, mask: np.ndarray | None = None
    ) -> tuple[float, int]:
        """(acceleration in [-1, 1], lane index) for one observation; uses env 0's noise."""
        single = np.asarray(obs, dtype=np.float32)
        if single.shape != (self.obs_dim,):
            raise ValueError(
                f"expected one observation of shape ({self.obs_dim},), got {single.shape}"
            )
        masks = None if mask is None else np.asarray(mask, dtype=bool).reshape(1, -1)
        acceleration, lanes = self.act_batch(single[None], explore, masks)
        return float(acceleration[0]), int(lanes[0])

    def act_batch(
        self, obs: np.ndarray, explore: bool, masks: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Actions for N observations (env i uses noise process i): (N,) float32, (N,) int64.

        `masks` (N, n_lane_actions) says which lane choices can happen (default: all).
        """
        batch = _as_batch(obs, self.obs_dim)
        n = len(batch)
        acceleration = self._act_actor(batch)
        if explore:
            if n > len(self.noises):
                raise ValueError(f"{n} observations but the agent has n_envs={len(self.noises)}")
            noise = np.fromiter((self.noises[i].sample() for i in range(n)), np.float32, n)
            np.clip(acceleration + noise, -1.0, 1.0, out=acceleration)
        if self.n_lane_actions == 1:
            return acceleration, np.zeros(n, dtype=np.int64)
        valid = all_valid(n, self.n_lane_actions) if masks is None else np.asarray(masks, bool)
        q = self._act_critic(batch, acceleration)
        rng = self.rng if explore else None
        return acceleration, choose_lanes(q, valid, self.lane_epsilon, rng)

    @torch.no_grad()
    def q_values(self, obs: np.ndarray, acceleration: np.ndarray | float) -> np.ndarray:
        """Q1 per lane choice: (n_lane_actions,) for one observation, (N, n_lane_actions) for N."""
        arr = np.asarray(obs, dtype=np.float32)
        single = arr.ndim == 1
        batch = _as_batch(arr.reshape(1, -1) if single else arr, self.obs_dim)
        acc = np.broadcast_to(np.asarray(acceleration, dtype=np.float32).reshape(-1), (len(batch),))
        q = self._act_critic(batch, np.ascontiguousarray(acc))
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
        due = self.updates_due(n_transitions)
        if not due:
            return None
        return self.update_many([buffer.sample(self.config.batch_size) for _ in range(due)])[-1]

    @torch.no_grad()
    def td_target(self, batch: Batch) -> torch.Tensor:
        """The TD target of a batch (with fresh smoothing noise, as an update would draw)."""
        from agent_client.rl.update import td_target

        return td_target(self.state, self._tensors(batch), self.config.gamma)

    def update(self, batch: Batch, actor: bool = True) -> dict[str, float]:
        """One critic step (and, every `policy_delay`, one actor and target step).

        With ``actor=False`` only the critic and its targets learn: used to evaluate a
        pre-trained actor before letting its gradient loose on it.
        """
        metrics = self._update(batch, actor)
        self._refresh_acting()
        return metrics

    def _update(self, batch: Batch, actor: bool) -> dict[str, float]:
        """`update` without refreshing what acting reads (the caller does, once)."""
        tensors = self._tensors(batch)
        self.n_updates += 1
        delayed = self.n_updates % self.config.policy_delay == 0
        if not delayed:
            step = self._steps.critic
        else:
            step = self._steps.delayed if actor else self._steps.targets_only
        with torch.no_grad(), _flushing_denormals():
            values = step(self.state, tensors).tolist()
        if delayed and actor:
            return dict(zip(METRICS, values, strict=True))
        return _critic_metrics(values)

    def update_many(self, batches: list[Batch], actor: bool = True) -> list[dict[str, float]]:
        """`update` for each batch in turn; TD3's critic-then-delayed pairs run as one compiled
        call, which saves the per-call overhead of the second."""
        metrics: list[dict[str, float]] = []
        if not actor:
            metrics = [self._update(batch, actor=False) for batch in batches]
            self._refresh_acting()
            return metrics
        index = 0
        while index < len(batches):
            pairs = self.config.policy_delay == 2 and (self.n_updates + 1) % 2 == 1
            if pairs and index + 1 < len(batches):
                first, second = self._tensors(batches[index]), self._tensors(batches[index + 1])
                self.n_updates += 2
                with torch.no_grad(), _flushing_denormals():
                    values = self._steps.pair(self.state, first, second).tolist()
                metrics.append(_critic_metrics(values[0]))
                metrics.append(dict(zip(METRICS, values[1], strict=True)))
                index += 2
            else:
                metrics.append(self._update(batches[index], actor=True))
                index += 1
        self._refresh_acting()
        return metrics

    def _refresh_acting(self) -> None:
        """Copy the learned networks into the ones acting reads (nothing to do on the CPU,
        where acting reads the learner's own)."""
        if self._on_cpu:
            return
        with torch.no_grad():
            for copies, learned in zip(
                self._acting, (self.state.actor, self.state.critics), strict=True
            ):
                torch._foreach_copy_(copies, learned)

    def _tensors(self, batch: Batch) -> Tensors:
        n = len(batch.reward)
        if not self._on_cpu:
            batch = batch.to(self.device)
        return Tensors(
            obs=batch.obs,
            acceleration=batch.acceleration,
            lane=batch.lane,
            reward=batch.reward,
            next_obs=batch.next_obs,
            terminated=batch.terminated,
            mask=batch.mask if batch.mask is not None else self._all_valid(n),
            next_mask=batch.next_mask if batch.next_mask is not None else self._all_valid(n),
            smoothing=self._smoothing(n),
        )

    def _smoothing(self, n: int) -> torch.Tensor:
        """TD3's clipped target-policy noise for a batch of `n`, drawn `SMOOTHING_POOL` batches
        at a time (one generator call instead of one per update)."""
        cfg = self.config
        if cfg.target_noise <= 0:
            return torch.zeros((n, 1), device=self.device)
        pool = self._smoothing_pool
        if pool is None or self._smoothing_next >= len(pool) or pool.shape[1] != n:
            noise = torch.randn((SMOOTHING_POOL, n, 1), generator=self.torch_generator)
            pool = (noise * cfg.target_noise).clamp(-cfg.target_noise_clip, cfg.target_noise_clip)
            self._smoothing_pool, self._smoothing_next = pool.to(self.device), 0
        self._smoothing_next += 1
        return pool[self._smoothing_next - 1]

    def _all_valid(self, n: int) -> torch.Tensor:
        return torch.ones((n, self.n_lane_actions), dtype=torch.bool, device=self.device)

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
        params = [p.detach().clone().requires_grad_(True) for p in self.state.actor]
        optimizer = torch.optim.Adam(params, lr=1e-3)
        loss = torch.zeros(())
        for _ in range(epochs):
            order = torch.from_numpy(self.rng.permutation(len(obs_t))).to(self.device)
            for start in range(0, len(order), batch_size):
                index = order[start : start + batch_size]
                loss = F.mse_loss(actor_forward(params, obs_t[index]), target[index])
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
        with torch.no_grad():
            for position, fitted in enumerate(params):
                for copy in (self.state.actor, self.state.actor_target, self.state.actor_average):
                    copy[position].copy_(fitted)
        self._refresh_acting()
        return float(loss.detach())

    def clone_lanes(
        self,
        obs: np.ndarray,
        acceleration: np.ndarray,
        lanes: np.ndarray,
        masks: np.ndarray,
        epochs: int,
        margin: float = 0.5,
        batch_size: int = 256,
    ) -> float:
        """Make the demonstrated lane choices the critics' best: a large-margin loss (DQfD,
        Hester et al. 2018), max over the valid choices of Q + `margin` [choice differs] minus
        Q of the demonstrated one, on the demonstrations' states and accelerations. Run after
        the critics learned the demonstrations' values, so that the policy starts choosing the
        demonstrator's lanes and TD learning moves it away only where another choice is worth
        more. Returns the last loss (0: every demonstrated choice leads by the margin)."""
        device = self.device
        obs_t = torch.as_tensor(np.asarray(obs, dtype=np.float32), device=device)
        acc_t = torch.as_tensor(
            np.asarray(acceleration, dtype=np.float32).reshape(-1, 1), device=device
        )
        lane_t = torch.as_tensor(np.asarray(lanes, dtype=np.int64), device=device)
        mask_t = torch.as_tensor(np.asarray(masks, dtype=bool), device=device)
        params = [p.detach().clone().requires_grad_(True) for p in self.state.critics]
        optimizer = torch.optim.Adam(params, lr=1e-3)
        loss = torch.zeros(())
        for _ in range(epochs):
            order = torch.from_numpy(self.rng.permutation(len(obs_t))).to(device)
            for start in range(0, len(order), batch_size):
                index = order[start : start + batch_size]
                q = critics_forward(params, obs_t[index], acc_t[index])  # (C, B, K)
                taken = lane_t[index].view(1, -1, 1).expand(q.shape[0], -1, 1)
                demo = q.gather(2, taken).squeeze(2)
                bonus = torch.full_like(q, margin).scatter(2, taken, 0.0)
                best = torch.where(mask_t[index], q + bonus, INVALID).max(2).values
                loss = (best - demo).mean()
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
        with torch.no_grad():
            for position, fitted in enumerate(params):
                for copy in (
                    self.state.critics,
                    self.state.critic_targets,
                    self.state.critics_average,
                ):
                    copy[position].copy_(fitted)
        self._refresh_acting()
        return float(loss.detach())

    # ----------------------------------------------------------- checkpoints

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume training bit for bit (safe types only)."""
        s = self.state
        return {
            "format": AGENT_FORMAT,
            "version": AGENT_VERSION,
            "obs_dim": self.obs_dim,
            "n_lane_actions": self.n_lane_actions,
            "config": self.config.to_dict(),
            "actor": _cpu_copy(s.actor),
            "actor_target": _cpu_copy(s.actor_target),
            "critics": _cpu_copy(s.critics),
            "critic_targets": _cpu_copy(s.critic_targets),
            "actor_average": _cpu_copy(s.actor_average),
            "critics_average": _cpu_copy(s.critics_average),
            "actor_adam": _cpu_state(s.actor_adam.state_dict()),
            "critic_adam": _cpu_state(s.critic_adam.state_dict()),
            "n_updates": self.n_updates,
            "n_transitions": self.n_transitions,
            "update_credit": self._update_credit,
            "lane_epsilon": self.lane_epsilon,
            "rng": self.rng.bit_generator.state,
            "torch_generator": self.torch_generator.get_state(),
            "smoothing_pool": None if self._smoothing_pool is None else self._smoothing_pool.cpu(),
            "smoothing_next": self._smoothing_next,
            "noises": [noise.state_dict() for noise in self.noises],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore `state_dict()`; observation size, lane choices and networks must match."""
        if state.get("format") != AGENT_FORMAT or state.get("version") != AGENT_VERSION:
            raise ValueError(
                f"not a {AGENT_FORMAT} v{AGENT_VERSION} state: "
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
        s = self.state
        with torch.no_grad():
            for name in NETWORKS:
                for tensor, saved_tensor in zip(getattr(s, name), state[name], strict=True):
                    tensor.copy_(saved_tensor)  # in place: the numpy views stay valid
        s.actor_adam.load_state_dict(state["actor_adam"])
        s.critic_adam.load_state_dict(state["critic_adam"])
        self.n_updates = int(state["n_updates"])
        self.n_transitions = int(state["n_transitions"])
        self._update_credit = float(state["update_credit"])
        self.lane_epsilon = float(state["lane_epsilon"])
        self.rng.bit_generator.state = state["rng"]
        self.torch_generator.set_state(state["torch_generator"])
        pool = state["smoothing_pool"]
        self._smoothing_pool = None if pool is None else pool.to(self.device)
        self._smoothing_next = int(state["smoothing_next"])
        for noise, noise_state in zip(self.noises, state["noises"], strict=True):
            noise.load_state_dict(noise_state)
        self._refresh_acting()

    @classmethod
    def from_state_dict(
        cls, state: dict[str, Any], n_envs: int | None = None, device: str | torch.device = "cpu"
    ) -> Agent:
        """An agent rebuilt with the checkpoint's own configuration, then restored."""
        n = len(state["noises"]) if n_envs is None else n_envs
        config = TD3Config.from_dict(state["config"])
        agent = cls(state["obs_dim"], state["n_lane_actions"], config, n_envs=n, device=device)
        agent.load_state_dict(state)
        return agent

    def policy_state_dict(self, averaged: bool = False) -> dict[str, Any]:
        """What a deployed greedy `Policy` needs: the actor, and critic 1 if lanes are chosen.

        ``averaged=True`` takes the slow averages (`deploy_tau`) instead of the online networks.
        """
        actor, critics = self._deployed(averaged)
        state: dict[str, Any] = {
            "format": POLICY_FORMAT,
            "version": POLICY_VERSION,
            "obs_dim": self.obs_dim,
            "n_lane_actions": self.n_lane_actions,
            "hidden_sizes": list(self.config.hidden_sizes),
            "actor": _cpu_copy(actor),
        }
        if self.n_lane_actions > 1:
            state["critic"] = _cpu_copy([p[:1] for p in critics])
        return state

    def policy(self, averaged: bool = False) -> Policy:
        """A greedy `Policy` on a copy of this agent's (online or target) networks."""
        return Policy.from_state_dict(self.policy_state_dict(averaged))

    def _deployed(self, averaged: bool) -> tuple[Params, Params]:
        s = self.state
        return (s.actor_average, s.critics_average) if averaged else (s.actor, s.critics)


def parse_device(name: str) -> torch.device | None:
    """The device a name asks for (None: ``auto``); a name that is none of ``auto``, ``cpu``,
    ``cuda`` or ``cuda:N`` is a `UsageError`."""
    if name == "auto":
        return None
    try:
        device = torch.device(name)
    except RuntimeError as exc:
        raise UsageError(f"device {name!r} is not one of: auto, cpu, cuda, cuda:N") from exc
    if device.type not in ("cpu", "cuda"):
        raise UsageError(f"device {name!r} is not one of: auto, cpu, cuda, cuda:N")
    return device


def resolve_device(name: str) -> torch.device:
    """Where the learner's networks go: ``auto`` (a CUDA GPU if torch sees one, else the CPU),
    ``cpu``, ``cuda`` or ``cuda:N``; one torch cannot use here is a `UsageError`."""
    device = parse_device(name)
    if device is None:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise UsageError(
                f"device {name!r}: torch sees no CUDA GPU here (torch {torch.__version__}; "
                "a CPU-only build, or no driver); use --device cpu or auto"
            )
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise UsageError(f"device {name!r}: there are {torch.cuda.device_count()} GPUs")
    return device


def _cpu_copy(tensors: list[torch.Tensor]) -> list[torch.Tensor]:
    """Detached copies on the CPU (for checkpoints, policies and acting)."""
    return [t.detach().to("cpu", copy=True) for t in tensors]


def _cpu_state(state: dict[str, Any]) -> dict[str, Any]:
    """An optimiser's state with every tensor copied to the CPU."""
    return {
        key: _cpu_copy(value) if isinstance(value, list) else value.detach().to("cpu", copy=True)
        for key, value in state.items()
    }


@contextmanager
def _flushing_denormals() -> Iterator[None]:
    """Flush denormal numbers to zero for the duration of an update (this thread's FTZ/DAZ).

    Adam's second moments of rarely used weights decay into denormals, which the CPU computes
    many times slower: without this, updates slow down as training goes on
    (docs/learner-design.md, "Speed: a learner that keeps up with its simulator"). Zero
    instead of 1e-39 changes no result that matters.
    """
    torch.set_flush_denormal(True)
    try:
        yield
    finally:
        torch.set_flush_denormal(False)


def _critic_metrics(values: list[float]) -> dict[str, float]:
    """The metrics of a critic-only update (the actor's are not computed)."""
    return dict(zip(METRICS[:4], values[:4], strict=True))


def _hyper(cfg: TD3Config) -> Hyper:
    return Hyper(
        gamma=cfg.gamma,
        tau=cfg.tau,
        deploy_tau=cfg.deploy_tau,
        actor_lr=cfg.actor_lr,
        critic_lr=cfg.critic_lr,
        actor_l2=cfg.actor_l2,
        action_l2=cfg.action_l2,
        smoothness=cfg.smoothness,
        max_grad_norm=cfg.max_grad_norm,
        huber=cfg.critic_loss == "huber",
    )


def _as_batch(obs: np.ndarray, obs_dim: int) -> np.ndarray:
    arr = np.asarray(obs, dtype=np.float32)
    if arr.ndim != 2 or arr.shape[1] != obs_dim:
        raise ValueError(f"expected observations of shape (N, {obs_dim}), got {arr.shape}")
    return arr
