"""Exploration noise: OU is autocorrelated and mean-reverting, Gaussian is not; seeded and resumable."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from agent_client.rl.noise import GaussianNoise, OrnsteinUhlenbeckNoise, make_noise

torch.set_num_threads(1)


def _lag1_autocorrelation(x: np.ndarray) -> float:
    return float(np.corrcoef(x[:-1], x[1:])[0, 1])


def test_ou_is_autocorrelated_and_gaussian_is_not() -> None:
    ou = OrnsteinUhlenbeckNoise(sigma=0.3, theta=0.15, dt=0.1, seed=0)
    gauss = GaussianNoise(sigma=0.3, seed=0)
    ou_x = np.array([ou.sample() for _ in range(5000)])
    gauss_x = np.array([gauss.sample() for _ in range(5000)])
    assert _lag1_autocorrelation(ou_x) > 0.9  # theory: 1 - theta dt = 0.985
    assert abs(_lag1_autocorrelation(gauss_x)) < 0.05
    assert gauss_x.std() == pytest.approx(0.3, rel=0.05)


def test_ou_reverts_to_its_mean() -> None:
    ou = OrnsteinUhlenbeckNoise(sigma=0.0, theta=0.5, dt=0.1, mu=0.2, seed=0, initial=3.0)
    xs = [ou.sample() for _ in range(200)]
    assert xs[0] < 3.0
    assert np.all(np.diff(xs) < 0)  # monotone towards mu without diffusion
    assert xs[-1] == pytest.approx(0.2, abs=1e-3)
    ou.reset()
    assert ou.x == 3.0

    noisy = OrnsteinUhlenbeckNoise(sigma=0.2, theta=0.5, dt=0.1, seed=1, initial=3.0)
    tail = np.array([noisy.sample() for _ in range(20000)])[2000:]
    assert abs(tail.mean()) < 0.1
    # stationary sd: sigma sqrt(dt / (1 - (1 - theta dt)^2))
    assert tail.std() == pytest.approx(0.2 * np.sqrt(0.1 / (1 - 0.95**2)), rel=0.15)


def test_scale_multiplies_the_output() -> None:
    a, b = GaussianNoise(0.5, seed=3), GaussianNoise(0.5, seed=3)
    b.scale = 0.1
    for _ in range(5):
        assert b.sample() == pytest.approx(0.1 * a.sample())


@pytest.mark.parametrize("kind", ["gaussian", "ou"])
def test_seeded_determinism(kind: str) -> None:
    a, b, c = make_noise(kind, 0.2, seed=5), make_noise(kind, 0.2, seed=5), make_noise(kind, 0.2, 6)
    xa = [a.sample() for _ in range(20)]
    assert xa == [b.sample() for _ in range(20)]
    assert xa != [c.sample() for _ in range(20)]


@pytest.mark.parametrize("kind", ["gaussian", "ou"])
def test_state_roundtrip_continues_the_sequence(kind: str) -> None:
    noise = make_noise(kind, 0.2, seed=11, dt=0.05)
    for _ in range(17):
        noise.sample()
    noise.scale = 0.5
    stream = io.BytesIO()
    torch.save(noise.state_dict(), stream)
    stream.seek(0)
    restored = make_noise(kind, 0.9, seed=0)
    restored.load_state_dict(torch.load(stream, weights_only=True))
    assert [restored.sample() for _ in range(10)] == [noise.sample() for _ in range(10)]


def test_make_noise_rejects_unknown_kinds_and_cross_loading() -> None:
    with pytest.raises(ValueError, match="gaussian, ou"):
        make_noise("pink", 0.1)
    with pytest.raises(ValueError, match="cannot load"):
        make_noise("ou", 0.1).load_state_dict(make_noise("gaussian", 0.1).state_dict())
