"""The actor loss's regularisers (`agent_client.rl.update.actor_loss`), term by term."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from agent_client.rl.networks import init_actor, init_critics
from agent_client.rl.update import Hyper, Tensors, actor_loss

B, OBS, LANES = 16, 4, 3
PLAIN = Hyper(
    gamma=0.98, tau=0.005, deploy_tau=0.005, actor_lr=1e-4, critic_lr=1e-3, actor_l2=0.0,
    action_l2=0.0, smoothness=0.0, max_grad_norm=None, huber=False,
)  # fmt: skip


def batch(terminated: float = 0.0) -> Tensors:
    g = torch.Generator().manual_seed(1)
    obs = torch.randn(B, OBS, generator=g)
    return Tensors(
        obs=obs, acceleration=torch.zeros(B, 1), lane=torch.zeros(B, dtype=torch.long),
        reward=torch.zeros(B), next_obs=torch.randn(B, OBS, generator=g),
        terminated=torch.full((B,), terminated), mask=torch.ones(B, LANES, dtype=torch.bool),
        next_mask=torch.ones(B, LANES, dtype=torch.bool), smoothing=torch.zeros(B, 1),
    )  # fmt: skip


def networks() -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    g = torch.Generator().manual_seed(0)
    return init_actor(OBS, [8], g), init_critics(OBS, LANES, [8], 2, g)


def constant_actor(actor: list[torch.Tensor], u: float) -> list[torch.Tensor]:
    """The same actor whose output is `u` everywhere (last layer: zero weights, atanh bias)."""
    out = [p.clone() for p in actor]
    out[-2].zero_()
    out[-1].fill_(float(torch.atanh(torch.tensor(u))))
    return out


def extra(
    hyper: Hyper, actor: list[torch.Tensor], critics: list[torch.Tensor], b: Tensors
) -> float:
    """What the regularisers of `hyper` add to the plain loss."""
    return float(actor_loss(actor, critics, b, hyper)[0] - actor_loss(actor, critics, b, PLAIN)[0])


def test_the_action_cost_is_the_mean_squared_normalised_action() -> None:
    actor, critics = networks()
    hyper = dataclasses.replace(PLAIN, action_l2=0.1)
    assert extra(hyper, constant_actor(actor, 0.0), critics, batch()) == pytest.approx(
        0.0, abs=1e-6
    )
    braking = constant_actor(actor, -0.5)
    assert extra(hyper, braking, critics, batch()) == pytest.approx(0.1 * 0.25)


def test_the_smoothness_term_is_the_policys_change_and_not_across_a_terminal_step() -> None:
    actor, critics = networks()
    hyper = dataclasses.replace(PLAIN, smoothness=5.0)
    assert extra(hyper, constant_actor(actor, 0.2), critics, batch()) == pytest.approx(0.0)
    assert extra(hyper, actor, critics, batch()) > 0.0
    assert extra(hyper, actor, critics, batch(terminated=1.0)) == pytest.approx(0.0)
