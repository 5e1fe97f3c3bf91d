"""TD3/DDPG with a hybrid action: learning, targets, delays, masks, checkpoints, clipping.

Most tests run the update eagerly (``compile=False``): the same functions, without the compile
time; `test_the_compiled_update_is_the_eager_update` checks that compiling changes nothing.
"""

from __future__ import annotations

import dataclasses
import io
from typing import Any

import numpy as np
import pytest
import torch

from agent_client.rl.networks import Params, actor_forward, critics_forward
from agent_client.rl.policy import Policy
from agent_client.rl.replay import Batch, ReplayBuffer
from agent_client.rl.td3 import Agent, TD3Config

torch.set_num_threads(1)

OBS_DIM = 3


def eager(config: TD3Config) -> TD3Config:
    return dataclasses.replace(config, compile=False)


def _roundtrip(state: dict[str, Any]) -> dict[str, Any]:
    stream = io.BytesIO()
    torch.save(state, stream)
    stream.seek(0)
    return torch.load(stream, weights_only=True)


def _bandit_buffer(n_lanes: int, seed: int, n: int = 1000, terminated: float = 1.0) -> ReplayBuffer:
    """One-step episodes: reward -(a - 0.5)^2, plus 1 for lane index 2; all terminated."""
    rng = np.random.default_rng(seed)
    obs = rng.normal(size=(n, OBS_DIM)).astype(np.float32)
    acc = rng.uniform(-1, 1, n)
    lane = rng.integers(0, n_lanes, n)
    reward = -((acc - 0.5) ** 2) + (lane == 2)
    buffer = ReplayBuffer(n, OBS_DIM, seed=seed, n_lanes=n_lanes)
    buffer.add_batch(obs, acc, lane, reward, obs, np.full(n, terminated))
    return buffer


def _bandit_config(**overrides: Any) -> TD3Config:
    return TD3Config.ddpg(
        **{"actor_lr": 1e-3, "critic_lr": 3e-3, "batch_size": 128, "tau": 0.05, "compile": False,
           **overrides}
    )  # fmt: skip


def _obs(n: int, seed: int = 123) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, OBS_DIM)).astype(np.float32)


def _params(params: Params) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in params]).clone()


def _hand_batch(reward: list[float], terminated: list[float], lane: list[int]) -> Batch:
    n = len(reward)
    obs = torch.from_numpy(_obs(n, seed=1))
    return Batch(
        obs=obs,
        acceleration=torch.linspace(-0.5, 0.5, n).unsqueeze(1),
        lane=torch.tensor(lane, dtype=torch.int64),
        reward=torch.tensor(reward),
        next_obs=torch.from_numpy(_obs(n, seed=2)),
        terminated=torch.tensor(terminated),
    )


def test_ddpg_learns_the_best_acceleration_on_a_bandit() -> None:
    config = _bandit_config()
    agent = Agent(OBS_DIM, 1, config, seed=0)
    buffer = _bandit_buffer(1, seed=0)
    for _ in range(1000):
        metrics = agent.update(buffer.sample(config.batch_size))
    acc, lanes = agent.act_batch(_obs(100), explore=False)
    assert np.abs(acc - 0.5).mean() < 0.1
    assert np.abs(acc - 0.5).max() < 0.25
    assert np.all(lanes == 0)
    assert metrics["critic_loss"] < 0.05


def test_hybrid_agent_learns_the_rewarded_lane() -> None:
    config = _bandit_config()
    agent = Agent(OBS_DIM, 3, config, seed=1)
    buffer = _bandit_buffer(3, seed=1)
    for _ in range(500):
        agent.update(buffer.sample(config.batch_size))
    obs = _obs(100)
    acc, lanes = agent.act_batch(obs, explore=False)
    assert np.all(lanes == 2)
    assert np.abs(acc - 0.5).mean() < 0.15
    q = agent.q_values(obs[0], 0.5)
    assert q.shape == (3,)
    assert q[2] - max(q[0], q[1]) == pytest.approx(1.0, abs=0.2)
    assert [agent.act(o, explore=False)[1] for o in obs[:10]] == [2] * 10


def test_a_masked_lane_is_never_chosen_nor_explored() -> None:
    agent = Agent(OBS_DIM, 3, _bandit_config(lane_epsilon=1.0), seed=1)
    buffer = _bandit_buffer(3, seed=1)
    for _ in range(300):
        agent.update(buffer.sample(128))
    obs = _obs(50)
    only_keep_or_left = np.tile([True, True, False], (50, 1))
    assert np.all(agent.act_batch(obs, explore=False)[1] == 2)  # the rewarded lane
    greedy = agent.act_batch(obs, explore=False, masks=only_keep_or_left)[1]
    assert set(greedy.tolist()) <= {0, 1}
    explored = [agent.act(o, explore=True, mask=np.array([True, False, True]))[1] for o in obs]
    assert set(explored) == {0, 2}  # epsilon 1: every choice random, but only among the valid


def test_the_td_target_takes_the_max_over_the_valid_lanes_only() -> None:
    agent = Agent(OBS_DIM, 3, eager(TD3Config.ddpg(gamma=1.0)), seed=4)
    batch = _hand_batch([0.0] * 4, [0.0] * 4, [0] * 4)
    keep_only = torch.tensor([[True, False, False]] * 4)
    target = agent.td_target(batch._replace(next_mask=keep_only))
    with torch.no_grad():
        next_acc = actor_forward(agent.state.actor_target, batch.next_obs)
        q = critics_forward(agent.state.critic_targets, batch.next_obs, next_acc)[0]
    torch.testing.assert_close(target, q[:, 0])
    assert not torch.allclose(agent.td_target(batch), q[:, 0])  # all valid: the max of three


def test_td3_has_twin_critics_and_delays_the_actor() -> None:
    config = eager(TD3Config.td3(batch_size=32))
    assert config.algo == "td3"
    assert TD3Config.ddpg().algo == "ddpg"
    agent = Agent(OBS_DIM, 3, config, seed=0)
    s = agent.state
    assert s.critics[0].shape[0] == 2  # two critics, stacked
    assert not torch.equal(s.critics[0][0], s.critics[0][1])
    buffer = _bandit_buffer(3, seed=0, n=200)
    actor0, actor_target0 = _params(s.actor), _params(s.actor_target)
    critic0, critic_target0 = _params(s.critics), _params(s.critic_targets)

    first = agent.update(buffer.sample(32))
    assert "actor_loss" not in first
    assert torch.equal(_params(s.actor), actor0)
    assert torch.equal(_params(s.actor_target), actor_target0)
    assert torch.equal(_params(s.critic_targets), critic_target0)
    assert not torch.equal(_params(s.critics), critic0)

    second = agent.update(buffer.sample(32))
    assert "actor_loss" in second
    assert not torch.equal(_params(s.actor), actor0)
    assert not torch.equal(_params(s.actor_target), actor_target0)
    assert not torch.equal(_params(s.critic_targets), critic_target0)


def test_ddpg_updates_the_actor_every_step() -> None:
    agent = Agent(OBS_DIM, 1, eager(TD3Config.ddpg(batch_size=32)), seed=0)
    assert agent.state.critics[0].shape[0] == 1
    actor0 = _params(agent.state.actor)
    assert "actor_loss" in agent.update(_bandit_buffer(1, seed=0, n=100).sample(32))
    assert not torch.equal(_params(agent.state.actor), actor0)


@pytest.mark.parametrize("config", [TD3Config.ddpg(), TD3Config.td3(target_noise=0.0)])
def test_td_target_bootstraps_only_when_not_terminated(config: TD3Config) -> None:
    agent = Agent(OBS_DIM, 3, eager(config), seed=4)
    batch = _hand_batch([1.0, -2.0, 0.5, 3.0], [1.0, 0.0, 1.0, 0.0], [0, 1, 2, 0])
    target = agent.td_target(batch)
    with torch.no_grad():
        next_acc = actor_forward(agent.state.actor_target, batch.next_obs)
        q = critics_forward(agent.state.critic_targets, batch.next_obs, next_acc)
    value = q.min(dim=0).values.max(dim=1).values  # min over critics, then max over lanes
    expected = batch.reward + config.gamma * torch.tensor([0.0, 1.0, 0.0, 1.0]) * value
    torch.testing.assert_close(target, expected)
    assert target[0] == 1.0
    assert target[2] == 0.5
    assert not torch.isclose(target[1], torch.tensor(-2.0))
    if config.n_critics == 2:  # the min matters: it differs from critic 1 alone
        assert not torch.allclose(value, q[0].max(dim=1).values)


def test_td3_target_smoothing_is_clipped_and_seeded() -> None:
    config = eager(TD3Config.td3(target_noise=5.0, target_noise_clip=0.01, gamma=1.0))
    agent = Agent(OBS_DIM, 1, config, seed=0)
    batch = _hand_batch([0.0] * 4, [0.0] * 4, [0] * 4)
    plain = dataclasses.replace(config, target_noise=0.0)
    reference = Agent(OBS_DIM, 1, plain, seed=0)
    smoothed, exact = agent.td_target(batch), reference.td_target(batch)
    assert not torch.equal(smoothed, exact)
    torch.testing.assert_close(smoothed, exact, atol=0.01, rtol=0)  # Q barely moves in 0.01
    again = Agent(OBS_DIM, 1, config, seed=0)
    assert torch.equal(again.td_target(batch), smoothed)  # the same seed, the same noise


def test_checkpoint_roundtrip_continues_identically() -> None:
    config = eager(TD3Config.td3(batch_size=32, noise="ou", noise_dt=0.1, lane_epsilon=0.5))
    agent = Agent(OBS_DIM, 3, config, seed=0)
    buffer = _bandit_buffer(3, seed=0, n=300, terminated=0.0)  # targets use smoothing noise
    for _ in range(3):
        agent.update(buffer.sample(32))
    for o in _obs(5):
        agent.act(o, explore=True)
    agent.noise_scale = 0.7
    state = _roundtrip({"agent": agent.state_dict(), "buffer": buffer.state_dict()})

    restored = Agent(OBS_DIM, 3, config, seed=99)
    restored.load_state_dict(state["agent"])
    restored_buffer = ReplayBuffer(buffer.capacity, OBS_DIM, seed=5, n_lanes=3)
    restored_buffer.load_state_dict(state["buffer"])
    rebuilt = Agent.from_state_dict(state["agent"])

    obs = _obs(20, seed=7)
    for other in (restored, rebuilt):
        assert [other.act(o, explore=False) for o in obs] == [
            agent.act(o, explore=False) for o in obs
        ]
    explored = [agent.act(o, explore=True) for o in obs]
    assert [restored.act(o, explore=True) for o in obs] == explored
    assert len({lane for _, lane in explored}) > 1  # exploration really was drawn
    for _ in range(3):  # includes an actor update and target smoothing noise
        assert restored.update(restored_buffer.sample(32)) == agent.update(buffer.sample(32))
    assert torch.equal(_params(restored.state.actor), _params(agent.state.actor))
    assert torch.equal(_params(restored.state.critic_targets), _params(agent.state.critic_targets))


def test_checkpoint_refuses_another_architecture() -> None:
    state = Agent(OBS_DIM, 3, eager(TD3Config.td3()), seed=0).state_dict()
    with pytest.raises(ValueError, match="does not fit"):
        Agent(OBS_DIM, 3, eager(TD3Config.ddpg()), seed=0).load_state_dict(state)


def test_policy_from_policy_state_dict_acts_like_the_agent() -> None:
    agent = Agent(OBS_DIM, 3, _bandit_config(), seed=2)
    # A contextual bandit, reward = obs[lane]: the greedy lane varies with the observation.
    obs = _obs(300, seed=3)
    lane = np.random.default_rng(3).integers(0, 3, 300)
    buffer = ReplayBuffer(300, OBS_DIM, seed=2, n_lanes=3)
    buffer.add_batch(obs, np.zeros(300), lane, obs[np.arange(300), lane], obs, np.ones(300))
    for _ in range(20):
        agent.update(buffer.sample(64))
    state = _roundtrip(agent.policy_state_dict())
    assert "actor_optimizer" not in state
    assert "critic_optimizer" not in state
    policy = Policy.from_state_dict(state)
    obs = _obs(30, seed=8)
    assert [policy.act(o) for o in obs] == [agent.act(o, explore=False) for o in obs]
    acc_p, lane_p = policy.act_batch(obs)
    acc_a, lane_a = agent.act_batch(obs, explore=False)
    np.testing.assert_array_equal(acc_p, acc_a)
    np.testing.assert_array_equal(lane_p, lane_a)
    assert len(set(lane_a.tolist())) > 1  # otherwise the lane comparison would be vacuous

    single = Agent(OBS_DIM, 1, eager(TD3Config()), seed=0)
    single_state = _roundtrip(single.policy_state_dict())
    assert "critic" not in single_state
    assert Policy.from_state_dict(single_state).act(obs[0]) == single.act(obs[0], explore=False)


def test_a_policy_file_of_version_1_still_loads() -> None:
    """Version 1 held nn.Sequential states (weights of shape (out, in)); they drive the same."""
    agent = Agent(OBS_DIM, 3, _bandit_config(), seed=2)
    state = agent.policy_state_dict()
    v1 = {**state, "version": 1}
    v1["actor"] = _as_module_state(state["actor"], ensemble=False)
    v1["critic"] = _as_module_state(state["critic"], ensemble=True)
    obs = _obs(10)
    np.testing.assert_allclose(
        Policy.from_state_dict(_roundtrip(v1)).act_batch(obs)[0],
        agent.act_batch(obs, explore=False)[0],
        rtol=1e-6,
    )


def _as_module_state(params: Params, ensemble: bool) -> dict[str, torch.Tensor]:
    state = {}
    for layer in range(len(params) // 2):
        weight, bias = params[2 * layer], params[2 * layer + 1]
        state[f"net.{2 * layer}.weight"] = (weight[0] if ensemble else weight).t().contiguous()
        state[f"net.{2 * layer}.bias"] = (bias[0, 0] if ensemble else bias).clone()
    return state


@pytest.mark.parametrize("max_grad_norm", [None, 1e-10])
def test_gradient_clipping_bounds_the_parameter_change(max_grad_norm: float | None) -> None:
    config = eager(TD3Config.ddpg(actor_lr=1e-3, critic_lr=1e-3, max_grad_norm=max_grad_norm))
    agent = Agent(OBS_DIM, 3, config, seed=0)
    batch = _bandit_buffer(3, seed=0, n=200).sample(64)
    actor0, critic0 = _params(agent.state.actor), _params(agent.state.critics)
    metrics = agent.update(batch)
    d_actor = torch.linalg.vector_norm(_params(agent.state.actor) - actor0)
    d_critic = torch.linalg.vector_norm(_params(agent.state.critics) - critic0)
    # First Adam step: |d theta_i| = lr |g_i| / (|g_i| + eps) <= lr |g_i| / eps.
    eps = 1e-8
    if max_grad_norm is None:
        assert d_critic > 1e-3
        assert d_actor > 1e-3
        assert metrics["critic_grad_norm"] > 1e-3
    else:
        assert d_critic <= config.critic_lr * max_grad_norm / eps * 1.01
        assert d_actor <= config.actor_lr * max_grad_norm / eps * 1.01
        assert d_critic > 0  # clipped, not frozen


def test_exploration_stays_in_range_and_visits_every_lane() -> None:
    config = eager(TD3Config(noise_sigma=2.0, lane_epsilon=1.0))
    agent = Agent(OBS_DIM, 3, config, seed=0, n_envs=4)
    accs, lanes = [], []
    for o in _obs(200):
        acc, lane = agent.act(o, explore=True)
        accs.append(acc)
        lanes.append(lane)
    assert min(accs) == -1.0 and max(accs) == 1.0  # sigma 2 saturates: the clip is applied
    assert set(lanes) == {0, 1, 2}
    acc_b, lane_b = agent.act_batch(_obs(4), explore=True)
    assert acc_b.shape == lane_b.shape == (4,)
    assert np.all(np.abs(acc_b) <= 1.0)
    with pytest.raises(ValueError, match="n_envs"):
        agent.act_batch(_obs(5), explore=True)


def test_updates_due_realises_learning_starts_and_fractional_ratio() -> None:
    agent = Agent(OBS_DIM, 1, eager(TD3Config(learning_starts=3, updates_per_step=0.5)), seed=0)
    assert [agent.updates_due() for _ in range(8)] == [0, 0, 0, 1, 0, 1, 0, 1]
    fast = Agent(OBS_DIM, 1, eager(TD3Config(learning_starts=0, updates_per_step=0.1)), seed=0)
    assert sum(fast.updates_due() for _ in range(10)) == 1
    vector = Agent(OBS_DIM, 1, eager(TD3Config(learning_starts=0, updates_per_step=2.0)), seed=0)
    assert vector.updates_due(n_transitions=4) == 8


def test_maybe_update_runs_the_updates_due_and_returns_the_last_metrics() -> None:
    config = eager(TD3Config.td3(batch_size=16, learning_starts=4, updates_per_step=2.0))
    agent = Agent(OBS_DIM, 3, config, seed=0)
    buffer = _bandit_buffer(3, seed=0, n=100, terminated=0.0)
    assert agent.maybe_update(buffer, n_transitions=3) is None
    metrics = agent.maybe_update(buffer, n_transitions=2)  # 5 transitions: 2 past the start
    assert agent.n_updates == 4
    assert metrics is not None and metrics["actor_loss"] != 0.0  # the 4th is a delayed one


def test_actor_l2_is_part_of_the_actor_loss() -> None:
    buffer = _bandit_buffer(1, seed=0, n=100)
    losses = []
    for actor_l2 in (0.0, 1.0):
        agent = Agent(OBS_DIM, 1, eager(TD3Config.ddpg(actor_l2=actor_l2)), seed=0)
        squares = float(sum(p.square().sum() for p in agent.state.actor))
        losses.append((agent.update(buffer.sample(32))["actor_loss"], squares))
        buffer.rng = np.random.default_rng(0)
    (plain, squares), (regularised, _) = losses
    assert regularised - plain == pytest.approx(squares, rel=1e-3)


def test_smoothness_is_the_policy_change_between_consecutive_states() -> None:
    obs, following = _obs(100, seed=1), _obs(100, seed=2)
    buffer = ReplayBuffer(100, OBS_DIM, seed=0)
    buffer.add_batch(obs, np.zeros(100), np.zeros(100), np.zeros(100), following, np.zeros(100))
    batch = buffer.sample(32)
    change = torch.tensor(0.0)
    losses = {}
    for weight in (0.0, 10.0):
        agent = Agent(OBS_DIM, 1, eager(TD3Config.ddpg(smoothness=weight)), seed=0)
        with torch.no_grad():
            mu = actor_forward(agent.state.actor, batch.obs)
            change = ((mu - actor_forward(agent.state.actor, batch.next_obs)) ** 2).mean()
        losses[weight] = agent.update(batch)["actor_loss"]
    assert change > 0
    assert losses[10.0] - losses[0.0] == pytest.approx(10.0 * float(change), rel=1e-3)


def test_two_updates_in_one_call_are_two_updates() -> None:
    config = eager(TD3Config.td3(batch_size=32, target_noise=0.0))
    paired, single = Agent(OBS_DIM, 3, config, seed=0), Agent(OBS_DIM, 3, config, seed=0)
    buffer = _bandit_buffer(3, seed=0, n=300, terminated=0.0)
    batches = [buffer.sample(32) for _ in range(4)]
    metrics = paired.update_many(batches)
    expected = [single.update(batch) for batch in batches]
    assert [m.keys() for m in metrics] == [m.keys() for m in expected]
    for mine, theirs in zip(metrics, expected, strict=True):
        assert mine == pytest.approx(theirs, rel=1e-5, abs=1e-6)
    torch.testing.assert_close(_params(paired.state.actor), _params(single.state.actor))
    assert paired.n_updates == single.n_updates == 4


def test_updates_without_the_actor_leave_it_as_it_was() -> None:
    """A residual policy's burn-in: the critic learns, the actor (and its target) do not."""
    agent = Agent(OBS_DIM, 3, eager(TD3Config.td3(batch_size=32)), seed=0)
    buffer = _bandit_buffer(3, seed=0, n=300, terminated=0.0)
    actor, critics = _params(agent.state.actor), _params(agent.state.critics)
    agent.update_many([buffer.sample(32) for _ in range(4)], actor=False)
    torch.testing.assert_close(_params(agent.state.actor), actor)
    assert not torch.equal(_params(agent.state.critics), critics)
    assert agent.n_updates == 4


def test_the_compiled_update_is_the_eager_update() -> None:
    config = TD3Config.td3(batch_size=16, target_noise=0.0, hidden_sizes=(8, 8))
    compiled, plain = Agent(OBS_DIM, 3, config, seed=0), Agent(OBS_DIM, 3, eager(config), seed=0)
    buffer = _bandit_buffer(3, seed=0, n=100, terminated=0.0)
    for _ in range(4):  # two critic-only updates and two delayed ones
        batch = buffer.sample(16)
        assert compiled.update(batch) == pytest.approx(plain.update(batch), rel=1e-4, abs=1e-6)
    torch.testing.assert_close(_params(compiled.state.actor), _params(plain.state.actor))
    torch.testing.assert_close(_params(compiled.state.critics), _params(plain.state.critics))


def test_config_validation() -> None:
    with pytest.raises(ValueError, match="critic_loss"):
        TD3Config(critic_loss="l1")
    with pytest.raises(ValueError, match="n_critics"):
        TD3Config(n_critics=3)
    with pytest.raises(ValueError, match="noise"):
        TD3Config(noise="pink")
    config = TD3Config.td3(hidden_sizes=(8, 8), critic_loss="huber")
    assert TD3Config.from_dict(_roundtrip(config.to_dict())) == config


def test_cloning_lane_choices_makes_the_demonstrated_ones_the_greedy_ones() -> None:
    rng = np.random.default_rng(0)
    agent = Agent(4, 3, TD3Config(compile=False), seed=1)
    obs = rng.normal(size=(300, 4)).astype(np.float32)
    lanes = (obs[:, 0] > 0).astype(np.int64) + (obs[:, 1] > 1.0)  # a rule of the state
    masks = np.ones((300, 3), dtype=bool)
    loss = agent.clone_lanes(obs, np.zeros(300), lanes, masks, epochs=60)
    chosen = np.array(
        [agent.act(x, explore=False, mask=m)[1] for x, m in zip(obs, masks, strict=True)]
    )
    assert loss < 0.3 and np.mean(chosen == lanes) > 0.9
