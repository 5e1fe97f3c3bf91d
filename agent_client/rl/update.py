"""One TD3 (or DDPG) update step as pure functions of tensors, compiled as one graph.

- TD target: r + gamma (1 - terminated) max_{k valid at s'} min_i Q'_i(s', mu'(s') + noise)_k,
  with the clipped smoothing noise drawn by the caller (0 for DDPG). Truncated transitions are
  stored with terminated = 0, so they still bootstrap.
- Critic loss: MSE (or Huber) between Q_i(s, a)[k taken] and the target, summed over critics.
- Actor loss: -mean(max_{k valid at s} Q_1(s, mu(s))_k) + actor_l2 sum(theta^2)
  + action_l2 mean(mu^2) + smoothness mean((mu(s) - mu(s'))^2). The L2 term on the actor's
  parameters is the paper's "regularise the action network" (§4.3.1); the action term keeps
  tanh out of saturation; the smoothness term is CAPS's temporal term (Mysore et al. 2021): the
  policy's change between consecutive states is its jerk, which the evaluation bounds.
- Gradients come from `torch.func.grad_and_value`, Adam and the soft updates are in-place
  foreach operations (`agent_client.rl.optim`): nothing breaks the graph, so `torch.compile`
  turns a step into one C++ kernel set instead of a few hundred dispatched operations.

A step returns its metrics as one tensor (`METRICS` order), read once per update.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch.func import grad_and_value

from agent_client.rl.networks import Params, actor_forward, critics_forward, first_critic
from agent_client.rl.optim import AdamState, adam_, clip_grad_norm_, soft_update_

INVALID = -1e9
"""The value a masked lane choice gets before a max: never chosen while another is valid."""

METRICS = (
    "critic_loss",
    "q_mean",
    "target_mean",
    "critic_grad_norm",
    "actor_loss",
    "actor_grad_norm",
    "mu_abs_mean",
)


@dataclass(frozen=True)
class Hyper:
    """The constants of the update (fixed for a run, so the compiled graph can fold them)."""

    gamma: float
    tau: float
    deploy_tau: float
    actor_lr: float
    critic_lr: float
    actor_l2: float
    action_l2: float
    smoothness: float
    max_grad_norm: float | None
    huber: bool


@dataclass
class LearnerState:
    """Everything an update changes: networks, targets and the optimisers' moments."""

    actor: Params
    critics: Params
    actor_target: Params
    critic_targets: Params
    actor_adam: AdamState
    critic_adam: AdamState
    actor_average: Params
    """A slow exponential average of the actor (and below of the critics): the deployed and
    evaluated policy, steadier than the networks being trained."""
    critics_average: Params


@dataclass(frozen=True)
class Tensors:
    """A minibatch as the update reads it (see `agent_client.rl.replay.Batch`)."""

    obs: torch.Tensor
    acceleration: torch.Tensor
    lane: torch.Tensor
    reward: torch.Tensor
    next_obs: torch.Tensor
    terminated: torch.Tensor
    mask: torch.Tensor
    next_mask: torch.Tensor
    smoothing: torch.Tensor
    """(B, 1): the clipped target-policy smoothing noise (zeros for DDPG)."""


def td_target(state: LearnerState, batch: Tensors, gamma: float) -> torch.Tensor:
    next_acceleration = (actor_forward(state.actor_target, batch.next_obs) + batch.smoothing).clamp(
        -1.0, 1.0
    )
    q_next = critics_forward(state.critic_targets, batch.next_obs, next_acceleration).min(0).values
    v_next = torch.where(batch.next_mask, q_next, INVALID).max(1).values
    return batch.reward + gamma * (1.0 - batch.terminated) * v_next


def critic_loss(
    critics: Params, batch: Tensors, target: torch.Tensor, huber: bool
) -> tuple[torch.Tensor, torch.Tensor]:
    q = critics_forward(critics, batch.obs, batch.acceleration)
    taken = q.gather(2, batch.lane.view(1, -1, 1).expand(q.shape[0], -1, 1)).squeeze(2)
    expanded = target.expand_as(taken)
    errors = F.huber_loss(taken, expanded, reduction="none") if huber else (taken - expanded) ** 2
    return errors.mean(1).sum(), taken[0].mean()


def actor_loss(
    actor: Params, critics: Params, batch: Tensors, hyper: Hyper
) -> tuple[torch.Tensor, torch.Tensor]:
    mu = actor_forward(actor, batch.obs)
    q = critics_forward(first_critic(critics), batch.obs, mu)[0]
    loss = -torch.where(batch.mask, q, INVALID).max(1).values.mean()
    if hyper.actor_l2 > 0:
        loss = loss + hyper.actor_l2 * torch.stack([(p * p).sum() for p in actor]).sum()
    if hyper.action_l2 > 0:
        loss = loss + hyper.action_l2 * (mu * mu).mean()
    if hyper.smoothness > 0:
        change = mu - actor_forward(actor, batch.next_obs)
        loss = loss + hyper.smoothness * ((1.0 - batch.terminated) * change[:, 0] ** 2).mean()
    return loss, mu.abs().mean()


_critic_grad = grad_and_value(critic_loss, has_aux=True)
_actor_grad = grad_and_value(actor_loss, has_aux=True)


def critic_step(state: LearnerState, batch: Tensors, hyper: Hyper) -> torch.Tensor:
    """One critic update; returns the `METRICS` (the actor's as zeros)."""
    target = td_target(state, batch, hyper.gamma)
    grads, (loss, q_mean) = _critic_grad(state.critics, batch, target, hyper.huber)
    grads = list(grads)
    norm = clip_grad_norm_(grads, hyper.max_grad_norm)
    adam_(state.critics, grads, state.critic_adam, hyper.critic_lr)
    zero = loss.new_zeros(())
    return torch.stack([loss, q_mean, target.mean(), norm, zero, zero, zero])


def delayed_step(
    state: LearnerState, batch: Tensors, hyper: Hyper, train_actor: bool
) -> torch.Tensor:
    """A critic update, then (if `train_actor`) an actor update, then every soft target update."""
    metrics = critic_step(state, batch, hyper)
    if train_actor:
        grads, (loss, mu_abs) = _actor_grad(state.actor, state.critics, batch, hyper)
        grads = list(grads)
        norm = clip_grad_norm_(grads, hyper.max_grad_norm)
        adam_(state.actor, grads, state.actor_adam, hyper.actor_lr)
        soft_update_(state.actor_target, state.actor, hyper.tau)
        soft_update_(state.actor_average, state.actor, hyper.deploy_tau)
        soft_update_(state.critics_average, state.critics, hyper.deploy_tau)
        metrics = torch.cat([metrics[:4], torch.stack([loss, norm, mu_abs])])
    soft_update_(state.critic_targets, state.critics, hyper.tau)
    return metrics


StepFn = Callable[[LearnerState, Tensors], torch.Tensor]
PairFn = Callable[[LearnerState, Tensors, Tensors], torch.Tensor]


@dataclass(frozen=True)
class Steps:
    """The three kinds of update, bound to their constants, compiled or eager."""

    critic: StepFn
    """Critic only (TD3 between two delayed updates)."""
    delayed: StepFn
    """Critic, actor and targets (every `policy_delay`-th update)."""
    targets_only: StepFn
    """Critic and targets without the actor (critic-only pre-training)."""
    pair: PairFn
    """A critic update then a delayed one, in one call (TD3 with two updates due at once)."""


def make_steps(hyper: Hyper, compile_steps: bool) -> Steps:
    """The update functions; with `compile_steps` each is compiled on its first call."""

    def critic(state: LearnerState, batch: Tensors) -> torch.Tensor:
        return critic_step(state, batch, hyper)

    def delayed(state: LearnerState, batch: Tensors) -> torch.Tensor:
        return delayed_step(state, batch, hyper, train_actor=True)

    def targets_only(state: LearnerState, batch: Tensors) -> torch.Tensor:
        return delayed_step(state, batch, hyper, train_actor=False)

    def pair(state: LearnerState, first: Tensors, second: Tensors) -> torch.Tensor:
        metrics = critic_step(state, first, hyper)
        return torch.stack([metrics, delayed_step(state, second, hyper, train_actor=True)])

    if not compile_steps:
        return Steps(critic, delayed, targets_only, pair)
    options: dict[str, Any] = {
        "dynamic": False,
        "fullgraph": True,
        # The kernels' Python wrapper written as C++: ~70 us less per update, ~7 s more to
        # compile the first time (then cached on disk).
        "options": {"cpp_wrapper": True},
    }
    return Steps(
        torch.compile(critic, **options),
        torch.compile(delayed, **options),
        torch.compile(targets_only, **options),
        torch.compile(pair, **options),
    )
