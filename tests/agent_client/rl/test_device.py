"""Where the learner's networks learn (`--device`): chosen, refused with a reason, and an
update that keeps every tensor on its device. No GPU here: the update runs on torch's meta
device, where any tensor left on the CPU is an error, as it would be on a GPU."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from agent_client.errors import UsageError
from agent_client.rl.greedy import NumpyActor, NumpyCritic
from agent_client.rl.networks import actor_forward, numpy_views
from agent_client.rl.optim import AdamState
from agent_client.rl.replay import Batch, ReplayBuffer
from agent_client.rl.td3 import Agent, TD3Config, _cpu_copy, _hyper, resolve_device
from agent_client.rl.update import LearnerState, Tensors, make_steps
from agent_client.training.config import TrainConfig

NO_GPU = pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA GPU")


@NO_GPU
def test_auto_is_the_cpu_where_torch_sees_no_gpu() -> None:
    assert resolve_device("auto") == torch.device("cpu")
    assert resolve_device("cpu") == torch.device("cpu")


@NO_GPU
def test_a_gpu_asked_for_where_there_is_none_is_a_usage_error_saying_so() -> None:
    with pytest.raises(UsageError, match="torch sees no CUDA GPU here"):
        resolve_device("cuda")


def test_a_device_that_is_no_device_is_refused_by_name() -> None:
    with pytest.raises(UsageError, match="device 'gpu' is not one of: auto, cpu, cuda"):
        resolve_device("gpu")
    with pytest.raises(UsageError, match="device 'tpu' is not one of"):
        TrainConfig(device="tpu")


def on_meta(agent: Agent) -> LearnerState:
    def moved(params: list[torch.Tensor]) -> list[torch.Tensor]:
        return [p.to("meta") for p in params]

    s = agent.state
    return LearnerState(
        actor=moved(s.actor), critics=moved(s.critics), actor_target=moved(s.actor_target),
        critic_targets=moved(s.critic_targets), actor_adam=AdamState.zeros_like(moved(s.actor)),
        critic_adam=AdamState.zeros_like(moved(s.critics)),
        actor_average=moved(s.actor_average), critics_average=moved(s.critics_average),
    )  # fmt: skip


def samples(agent: Agent, n: int) -> list[Batch]:
    """`n` minibatches from a small buffer, as the trainer samples them."""
    buffer = ReplayBuffer(100, agent.obs_dim, 0, agent.n_lane_actions)
    for i in range(50):
        x = np.full(agent.obs_dim, i / 50, np.float32)
        mask = np.ones(agent.n_lane_actions, bool)
        buffer.add(x, 0.1, 0, 1.0, x, False, mask, mask)
    return [buffer.sample(16) for _ in range(n)]


def batches(agent: Agent, n: int) -> list[Tensors]:
    """`n` minibatches as the agent hands them to the update, on its device."""
    return [agent._tensors(batch) for batch in samples(agent, n)]


@pytest.mark.parametrize("lanes", [1, 3])
def test_an_update_keeps_every_tensor_on_the_learners_device(lanes: int) -> None:
    agent = Agent(6, lanes, TD3Config(compile=False), seed=0)
    agent.device, agent._on_cpu = torch.device("meta"), False  # what a GPU agent hands over
    state = on_meta(agent)
    first, second = batches(agent, 2)
    assert {t.device.type for t in dataclasses.astuple(first) if t is not None} == {"meta"}
    steps = make_steps(_hyper(agent.config), compile_steps=False)
    assert steps.critic(state, first).device.type == "meta"
    assert steps.pair(state, first, second).shape == (2, 7)
    stray = dataclasses.replace(first, smoothing=torch.zeros(16, 1))  # left on the CPU
    with pytest.raises(RuntimeError, match="device"):
        steps.critic(state, stray)


def test_acting_reads_copies_refreshed_after_each_update_where_the_learner_is_elsewhere() -> None:
    agent = Agent(6, 3, TD3Config(compile=False), seed=0)
    # as on a GPU: acting reads CPU copies of the networks, not the learner's own
    agent._on_cpu = False
    agent._acting = (_cpu_copy(agent.state.actor), _cpu_copy(agent.state.critics))
    agent._act_actor = NumpyActor(numpy_views(agent._acting[0]))
    agent._act_critic = NumpyCritic(numpy_views(agent._acting[1]))
    x = np.linspace(-1, 1, 6, dtype=np.float32)
    before = agent.act_batch(x[None], explore=False)[0]
    for batch in samples(agent, 4):
        agent.update(batch)
    after = agent.act_batch(x[None], explore=False)[0]
    assert after != pytest.approx(before)  # the copies followed the learner
    with torch.no_grad():
        learned = actor_forward(agent.state.actor, torch.from_numpy(x[None]))
    assert after == pytest.approx(learned.numpy()[:, 0], abs=1e-6)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU here")
def test_on_a_gpu_an_agent_learns_acts_and_checkpoints_from_the_cpu() -> None:
    agent = Agent(6, 3, TD3Config(compile=False), seed=0, device="cuda")
    x = np.linspace(-1, 1, 6, dtype=np.float32)
    before = agent.act_batch(x[None], explore=False)[0]
    agent.update_many(samples(agent, 4))
    assert agent.act_batch(x[None], explore=False)[0] != pytest.approx(before)
    state = agent.state_dict()
    assert all(t.device.type == "cpu" for t in state["actor"] + state["critics"])
    again = Agent.from_state_dict(state)  # on the CPU
    assert again.act_batch(x[None], explore=False)[0] == pytest.approx(
        agent.act_batch(x[None], explore=False)[0], abs=1e-5
    )
