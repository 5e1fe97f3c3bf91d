"""Adam and gradient clipping as in-place `torch._foreach_*` operations on lists of tensors.

The same arithmetic as `torch.optim.Adam` (no weight decay, no amsgrad) and
`torch.nn.utils.clip_grad_norm_`, written as plain functions so that they can be traced into
one compiled update step. The step count is a tensor: a Python number that changes at every
call would make the compiler specialise, and recompile, every time.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from agent_client.rl.networks import Params

BETA1 = 0.9
BETA2 = 0.999
EPSILON = 1e-8


@dataclass
class AdamState:
    """First and second moment estimates of one network's parameters, and the step count."""

    exp_avg: Params
    exp_avg_sq: Params
    step: torch.Tensor

    @classmethod
    def zeros_like(cls, params: Params) -> AdamState:
        return cls(
            [torch.zeros_like(p) for p in params],
            [torch.zeros_like(p) for p in params],
            torch.zeros((), device=params[0].device),
        )

    def state_dict(self) -> dict[str, object]:
        return {"exp_avg": self.exp_avg, "exp_avg_sq": self.exp_avg_sq, "step": self.step}

    def load_state_dict(self, state: dict[str, object]) -> None:
        for mine, theirs in (
            (self.exp_avg, state["exp_avg"]),
            (self.exp_avg_sq, state["exp_avg_sq"]),
        ):
            assert isinstance(theirs, list)
            for tensor, saved in zip(mine, theirs, strict=True):
                tensor.copy_(saved)
        step = state["step"]
        assert isinstance(step, torch.Tensor)
        self.step.copy_(step)


def adam_(params: Params, grads: Params, state: AdamState, lr: float) -> None:
    """One Adam step on `params`, in place."""
    state.step.add_(1.0)
    torch._foreach_lerp_(state.exp_avg, grads, 1.0 - BETA1)
    torch._foreach_mul_(state.exp_avg_sq, BETA2)
    torch._foreach_addcmul_(state.exp_avg_sq, grads, grads, 1.0 - BETA2)
    correction1 = 1.0 - BETA1**state.step
    correction2 = 1.0 - BETA2**state.step
    denominator = torch._foreach_sqrt(state.exp_avg_sq)
    torch._foreach_div_(denominator, torch.sqrt(correction2))
    torch._foreach_add_(denominator, EPSILON)
    update = torch._foreach_div(state.exp_avg, denominator)
    torch._foreach_mul_(update, -lr / correction1)
    torch._foreach_add_(params, update)


def clip_grad_norm_(grads: Params, max_norm: float | None) -> torch.Tensor:
    """Scale `grads` in place to a global norm of at most `max_norm`; returns the norm before."""
    norm = torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in grads]))
    if max_norm is not None:
        torch._foreach_mul_(grads, torch.clamp(max_norm / (norm + 1e-6), max=1.0))
    return norm


def soft_update_(targets: Params, online: Params, tau: float) -> None:
    """Polyak averaging: target <- target + tau * (online - target)."""
    torch._foreach_lerp_(targets, online, tau)
