"""The networks as plain tensors: an MLP actor and an ensemble of MLP critics.

Functional on purpose: the parameters are lists of tensors and the forward passes pure
functions, so that a whole update step can be differentiated with `torch.func` and compiled as
one graph (`agent_client.rl.td3`). The critics of an ensemble (TD3's twin) have their weights
stacked and run as one batched matrix product. Acting reads the same weights as numpy views
(`numpy_views`, `agent_client.rl.greedy`), so the per-step path needs no torch call at all.

Layout: a layer is (W, b) with W of shape (in, out) (stacked: (n, in, out), b (n, 1, out)), so
that ``x @ W + b`` is the layer; ReLU between layers, tanh after the actor's last one.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import numpy as np
import torch

Params = list[torch.Tensor]
"""The weights and biases of one network (or ensemble), layer by layer: [W1, b1, W2, b2, ...]."""

ACTOR_LAST_LAYER_BOUND = 3e-3
"""Lillicrap et al.: a small last layer starts the policy near 0, away from tanh saturation."""


def _layer(
    fan_in: int, fan_out: int, generator: torch.Generator, ensemble: int | None, bound: float
) -> Params:
    weight_shape = (fan_in, fan_out) if ensemble is None else (ensemble, fan_in, fan_out)
    bias_shape = (fan_out,) if ensemble is None else (ensemble, 1, fan_out)
    return [
        torch.empty(weight_shape).uniform_(-bound, bound, generator=generator),
        torch.empty(bias_shape).uniform_(-bound, bound, generator=generator),
    ]


def _mlp(
    sizes: Sequence[int], generator: torch.Generator, ensemble: int | None, last_bound: float | None
) -> Params:
    """PyTorch's default Linear initialisation (uniform, bound 1/sqrt(fan_in)) for every layer."""
    params: Params = []
    for index, (fan_in, fan_out) in enumerate(itertools.pairwise(sizes)):
        last = index == len(sizes) - 2
        bound = last_bound if last and last_bound is not None else 1.0 / math.sqrt(fan_in)
        params += _layer(fan_in, fan_out, generator, ensemble, bound)
    return params


def init_actor(obs_dim: int, hidden: Sequence[int], generator: torch.Generator) -> Params:
    """mu(s): observation -> normalised acceleration in [-1, 1]."""
    return _mlp([obs_dim, *hidden, 1], generator, None, ACTOR_LAST_LAYER_BOUND)


def init_critics(
    obs_dim: int, n_lanes: int, hidden: Sequence[int], n_critics: int, generator: torch.Generator
) -> Params:
    """Q_i(s, a_acc) for i < n_critics: one value per lane choice (P-DQN style heads)."""
    return _mlp([obs_dim + 1, *hidden, n_lanes], generator, n_critics, None)


def actor_forward(params: Params, obs: torch.Tensor) -> torch.Tensor:
    """(B, obs_dim) -> (B, 1) normalised accelerations."""
    h = obs
    for i in range(0, len(params) - 2, 2):
        h = torch.relu(torch.addmm(params[i + 1], h, params[i]))
    return torch.tanh(torch.addmm(params[-1], h, params[-2]))


def critics_forward(params: Params, obs: torch.Tensor, acceleration: torch.Tensor) -> torch.Tensor:
    """(B, obs_dim), (B, 1) -> (n_critics, B, n_lanes)."""
    ensemble = params[0].shape[0]
    h = torch.cat([obs, acceleration], dim=1).expand(ensemble, -1, -1)
    for i in range(0, len(params) - 2, 2):
        h = torch.relu(torch.baddbmm(params[i + 1], h, params[i]))
    return torch.baddbmm(params[-1], h, params[-2])


def first_critic(params: Params) -> Params:
    """The first critic of an ensemble, still stacked (an ensemble of one)."""
    return [p[:1] for p in params]


def numpy_views(params: Params) -> list[np.ndarray]:
    """The tensors as numpy arrays sharing their memory: acting through them
    (`agent_client.rl.greedy`) follows the optimiser's in-place updates without a copy."""
    return [p.detach().numpy() for p in params]
