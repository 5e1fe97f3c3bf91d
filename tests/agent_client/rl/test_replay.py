"""The replay buffer: ring semantics, uniform sampling, terminated flags, safe checkpoints."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from agent_client.rl.replay import ReplayBuffer

torch.set_num_threads(1)


def _fill(buffer: ReplayBuffer, ids: range, terminated_every: int = 0) -> None:
    """Add transitions whose reward is their id, so a sample tells which entries it holds."""
    for i in ids:
        obs = np.full(buffer.obs_dim, i, dtype=np.float32)
        term = terminated_every > 0 and i % terminated_every == 0
        buffer.add(obs, (i % 21 - 10) / 10, i % 3, float(i), obs + 0.5, term)


def _roundtrip(state: dict) -> dict:
    stream = io.BytesIO()
    torch.save(state, stream)
    stream.seek(0)
    return torch.load(stream, weights_only=True)


def test_wraps_around_and_keeps_the_newest() -> None:
    buffer = ReplayBuffer(capacity=5, obs_dim=2, seed=0, n_lanes=3)
    _fill(buffer, range(7))
    assert len(buffer) == 5
    assert buffer.full
    assert buffer.pos == 2
    # entries 5 and 6 overwrote the two oldest slots
    assert buffer.reward.tolist() == [5.0, 6.0, 2.0, 3.0, 4.0]
    assert buffer.obs[0].tolist() == [5.0, 5.0]
    assert buffer.next_obs[1].tolist() == [6.5, 6.5]


def test_add_batch_matches_add_including_wraparound() -> None:
    single = ReplayBuffer(capacity=6, obs_dim=2, seed=0, n_lanes=3)
    _fill(single, range(9))
    batched = ReplayBuffer(capacity=6, obs_dim=2, seed=0, n_lanes=3)
    for chunk in (range(0, 4), range(4, 9)):
        ids = np.array(chunk)
        obs = np.repeat(ids[:, None], 2, axis=1).astype(np.float32)
        batched.add_batch(
            obs, (ids % 21 - 10) / 10, ids % 3, ids.astype(float), obs + 0.5, np.zeros(len(ids))
        )
    assert (len(batched), batched.pos) == (len(single), single.pos)
    np.testing.assert_array_equal(batched.reward, single.reward)
    np.testing.assert_array_equal(batched.obs, single.obs)
    np.testing.assert_array_equal(batched.acceleration, single.acceleration)
    np.testing.assert_array_equal(batched.lane, single.lane)


def test_sampling_is_uniform_over_the_filled_part() -> None:
    buffer = ReplayBuffer(capacity=100, obs_dim=1, seed=1, n_lanes=3)
    _fill(buffer, range(40))
    counts = np.zeros(100)
    for _ in range(50):
        batch = buffer.sample(400)
        np.add.at(counts, batch.reward.numpy().astype(int), 1)
    assert counts[40:].sum() == 0  # never the empty slots
    expected = 50 * 400 / 40  # 500 per entry, sd about 22
    assert counts[:40].min() > expected - 5 * np.sqrt(expected)
    assert counts[:40].max() < expected + 5 * np.sqrt(expected)


def test_sample_types_and_shapes() -> None:
    buffer = ReplayBuffer(capacity=10, obs_dim=3, seed=0, n_lanes=3)
    _fill(buffer, range(10))
    batch = buffer.sample(8)
    assert batch.obs.shape == batch.next_obs.shape == (8, 3)
    assert batch.acceleration.shape == (8, 1)
    assert batch.lane.dtype == torch.int64
    assert batch.lane.shape == batch.reward.shape == batch.terminated.shape == (8,)
    assert batch.reward.dtype == batch.terminated.dtype == torch.float32
    # each field belongs to the same transition
    ids = batch.reward.long()
    assert torch.equal(batch.obs[:, 0].long(), ids)
    assert torch.equal(batch.lane, ids % 3)


def test_terminated_is_stored_per_transition_not_as_done() -> None:
    buffer = ReplayBuffer(capacity=30, obs_dim=1, seed=0, n_lanes=3)
    _fill(buffer, range(30), terminated_every=4)
    batch = buffer.sample(300)
    ids = batch.reward.numpy().astype(int)
    np.testing.assert_array_equal(batch.terminated.numpy(), (ids % 4 == 0).astype(np.float32))
    assert 0 < batch.terminated.mean() < 1


def test_rejects_bad_transitions() -> None:
    buffer = ReplayBuffer(capacity=4, obs_dim=2, seed=0, n_lanes=3)
    with pytest.raises(ValueError, match="shape"):
        buffer.add(np.zeros(3), 0.0, 0, 0.0, np.zeros(3), False)
    with pytest.raises(ValueError, match=r"\[-1, 1\]"):
        buffer.add(np.zeros(2), 1.5, 0, 0.0, np.zeros(2), False)
    with pytest.raises(ValueError, match="empty"):
        buffer.sample(1)


def test_state_dict_roundtrip_with_weights_only_gives_identical_samples() -> None:
    buffer = ReplayBuffer(capacity=16, obs_dim=3, seed=7, n_lanes=3)
    _fill(buffer, range(21), terminated_every=5)  # wrapped
    buffer.sample(5)  # advance the generator
    state = _roundtrip(buffer.state_dict())
    restored = ReplayBuffer(capacity=16, obs_dim=3, seed=999, n_lanes=3)
    restored.load_state_dict(state)
    assert (len(restored), restored.pos) == (len(buffer), buffer.pos)
    for _ in range(3):
        a, b = buffer.sample(10), restored.sample(10)
        for x, y in zip(a, b, strict=True):
            assert torch.equal(x, y)
    # later additions land in the same slots too
    _fill(buffer, range(21, 24))
    _fill(restored, range(21, 24))
    np.testing.assert_array_equal(buffer.reward, restored.reward)


def test_partial_buffer_state_and_mismatch() -> None:
    buffer = ReplayBuffer(capacity=50, obs_dim=2, seed=0, n_lanes=3)
    _fill(buffer, range(3))
    state = _roundtrip(buffer.state_dict())
    assert state["obs"].shape == (3, 2)  # only the used part is saved
    with pytest.raises(ValueError, match="mismatch"):
        ReplayBuffer(capacity=40, obs_dim=2, n_lanes=3).load_state_dict(state)


def test_the_lane_masks_of_both_states_are_stored_and_sampled() -> None:
    buffer = ReplayBuffer(capacity=4, obs_dim=1, seed=0, n_lanes=3)
    buffer.add(
        np.zeros(1), 0.0, 0, 0.0, np.zeros(1), False, np.array([1, 0, 1]), np.array([1, 1, 0])
    )
    buffer.add(np.ones(1), 0.0, 2, 0.0, np.ones(1), False)  # no masks: every choice possible
    batch = buffer.sample(64)
    assert batch.mask is not None and batch.next_mask is not None
    first = batch.obs[:, 0] == 0
    assert batch.mask[first].tolist()[0] == [True, False, True]
    assert batch.next_mask[first].tolist()[0] == [True, True, False]
    assert batch.mask[~first].all() and batch.next_mask[~first].all()
    with pytest.raises(ValueError, match="below 3"):
        buffer.add(np.zeros(1), 0.0, 3, 0.0, np.zeros(1), False)
