"""The probabilistic ensemble (models/pe.py): its mean and its learned variance on a toy system
with known state-dependent noise, elites, sampling, saving as data, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from sdrl_bench import ConfigError
from sdrl_bench.models.base import load_model
from sdrl_bench.models.pe import GaussianEnsembleDynamics

A = np.array([[0.95, 0.10], [-0.20, 0.90]])
B = np.array([[0.0], [0.5]])
NOISE = (0.01, 0.05)
"""The toy's noise std on the second state: NOISE[0] where u < 0, NOISE[1] where u >= 0 (the first
state is exact)."""


def toy(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x, u = rng.uniform(-1, 1, (n, 2)), rng.uniform(-1, 1, (n, 1))
    std = np.where(u[:, 0] < 0, NOISE[0], NOISE[1])
    xn = x @ A.T + u @ B.T
    xn[:, 1] += std * rng.standard_normal(n)
    return x, u, xn


@pytest.fixture(scope="module")
def pe() -> GaussianEnsembleDynamics:
    x, u, xn = toy(2000, 0)
    return GaussianEnsembleDynamics(ensemble_size=5, n_elites=3, width=32, depth=2, learning_rate=3e-3,
                                    max_steps=3000, batch_size=128, patience=100, seed=0).fit(
        x, u, xn, state_names=["p", "q"], control_names=["c"])


def test_learns_the_mean_and_the_state_dependent_noise(pe):
    x, u, xn = toy(4000, 1)
    clean = x @ A.T + u @ B.T
    assert np.all(np.mean((pe.predict(x, u) - clean) ** 2, axis=0) < 2e-4)
    # the learned spread of its own draws: about each regime's true noise (sampled, many draws)
    rng = np.random.default_rng(0)
    draws = np.stack([pe.sample(x, u, rng) for _ in range(20)])  # (20, N, 2)
    spread = (draws - pe.predict(x, u)).std(axis=0)[:, 1]
    for lo, hi, true in ((-1.0, 0.0, NOISE[0]), (0.0, 1.0, NOISE[1])):
        got = float(np.median(spread[(u[:, 0] >= lo) & (u[:, 0] < hi)]))
        assert 0.6 * true < got < 1.6 * true, (true, got)
    # elites: the n best members by validation MSE, and only they predict
    best = np.sort(np.argsort(pe.best_val_loss_)[:3])
    assert np.array_equal(pe.elites_, best) and pe.predict_members(x[:5], u[:5]).shape == (3, 5, 2)
    assert "ensemble of 5 Gaussian MLPs" in pe.describe()


def test_sampling_is_seeded_and_saving_keeps_every_prediction(pe, tmp_path):
    x, u, _ = toy(64, 2)
    a = pe.sample(x, u, np.random.default_rng(5))
    b = pe.sample(x, u, np.random.default_rng(5))
    c = pe.sample(x, u, np.random.default_rng(6))
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    back = load_model(pe.save(tmp_path / "pe" / "model.json"))
    assert isinstance(back, GaussianEnsembleDynamics) and np.array_equal(back.elites_, pe.elites_)
    assert np.array_equal(back.predict(x, u), pe.predict(x, u))
    assert np.array_equal(back.sample(x, u, np.random.default_rng(5)), a)


@pytest.mark.parametrize("kw, needle", [({"n_elites": 8, "ensemble_size": 7}, "surrogate.model.n_elites"),
                                        ({"n_elites": 0}, "surrogate.model.n_elites")])
def test_bad_elites_are_one_line_errors(kw, needle):
    with pytest.raises(ConfigError, match=needle):
        GaussianEnsembleDynamics(**kw)
