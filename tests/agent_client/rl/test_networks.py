"""The functional networks: numpy acting equals torch, Adam equals torch.optim.Adam."""

from __future__ import annotations

import numpy as np
import torch

from agent_client.rl.greedy import NumpyActor, NumpyCritic
from agent_client.rl.networks import (
    actor_forward,
    critics_forward,
    first_critic,
    init_actor,
    init_critics,
    numpy_views,
)
from agent_client.rl.optim import AdamState, adam_, clip_grad_norm_


def test_numpy_acting_is_the_torch_forward_and_follows_updates() -> None:
    generator = torch.Generator().manual_seed(0)
    actor, critics = init_actor(5, (16, 16), generator), init_critics(5, 3, (16, 16), 2, generator)
    obs = torch.randn(7, 5, generator=generator)
    numpy_actor = NumpyActor(numpy_views(actor))
    numpy_critic = NumpyCritic(numpy_views(critics))
    acceleration = actor_forward(actor, obs)
    np.testing.assert_allclose(numpy_actor(obs.numpy()), acceleration[:, 0].numpy(), rtol=1e-5)
    q = critics_forward(first_critic(critics), obs, acceleration)[0]
    np.testing.assert_allclose(
        numpy_critic(obs.numpy(), acceleration[:, 0].numpy()), q.numpy(), rtol=1e-5, atol=1e-6
    )
    with torch.no_grad():
        actor[-1].add_(1.0)  # an in-place update, as the optimiser makes
    np.testing.assert_allclose(
        numpy_actor(obs.numpy()), actor_forward(actor, obs)[:, 0].numpy(), rtol=1e-5
    )


def test_critics_of_an_ensemble_differ_and_start_near_zero_actions() -> None:
    generator = torch.Generator().manual_seed(1)
    critics = init_critics(4, 3, (8,), 2, generator)
    assert critics[0].shape == (2, 5, 8)
    assert not torch.equal(critics[0][0], critics[0][1])
    actor = init_actor(4, (8,), generator)
    assert actor[-2].abs().max() <= 3e-3  # the small last layer of Lillicrap et al.


def test_adam_and_clipping_match_torch() -> None:
    torch.manual_seed(0)
    mine = [torch.randn(4, 3), torch.randn(3)]
    theirs = [p.clone().requires_grad_(True) for p in mine]
    optimiser = torch.optim.Adam(theirs, lr=1e-2)
    state = AdamState.zeros_like(mine)
    for step in range(5):
        grads = [torch.randn(4, 3) * (step + 1), torch.randn(3)]
        for p, g in zip(theirs, grads, strict=True):
            p.grad = g.clone()
        torch.nn.utils.clip_grad_norm_(theirs, 1.0)
        optimiser.step()
        norm = clip_grad_norm_(grads, 1.0)
        adam_(mine, grads, state, 1e-2)
        assert norm > 0
    for a, b in zip(mine, theirs, strict=True):
        torch.testing.assert_close(a, b.detach(), rtol=1e-5, atol=1e-7)
    assert state.step.item() == 5.0
