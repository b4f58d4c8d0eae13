"""Pruning an exact equation to its smallest exact support, on MountainCar-like data from a
narrow band of positions where x, x^2, sin 3x, cos 3x and the bias are nearly collinear."""

from __future__ import annotations

import numpy as np
import pysindy as ps
import pytest

from sdrl_bench.models.snap import prune_exact, snap_equation


def narrow_band(n: int = 75, seed: int = 3):
    """MountainCar's position law in float32 over x in [-0.56, -0.44] (an expert's first steps)."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-0.56, -0.44, n).astype(np.float32)
    v = rng.uniform(-0.01, 0.01, n).astype(np.float32)
    u = rng.uniform(-1, 1, n).astype(np.float32)
    v_next = (v + np.float32(0.0015) * u - np.float32(0.0025) * np.cos(np.float32(3) * x)).astype(np.float32)
    x_next = (x + v_next).astype(np.float32)
    x, v, u, x_next = (a.astype(float) for a in (x, v, u, x_next))
    names = ["1", "x", "v", "u", "x^2", "sin(3 x)", "cos(3 x)"]
    theta = np.stack([np.ones_like(x), x, v, u, x**2, np.sin(3 * x), np.cos(3 * x)], axis=1)
    return theta, x_next, names


def test_an_exact_equation_is_pruned_to_the_true_law_and_then_snapped():
    theta, y, names = narrow_band()
    full, *_ = np.linalg.lstsq(theta, y, rcond=None)
    resid = y - theta @ full
    assert np.sqrt(resid @ resid / (y @ y)) < 1e-6  # seven terms fit these rows exactly...
    assert np.count_nonzero(np.abs(full) > 1e-3) > 4  # ...with spurious terms the band cannot rule out
    kept, coef = prune_exact(theta, y)
    assert [names[k] for k in kept] == ["x", "v", "u", "cos(3 x)"]
    snapped, digits = snap_equation(theta[:, kept], y, coef)
    assert digits > 0 and snapped.tolist() == [1.0, 1.0, 0.0015, -0.0025]


def test_a_noisy_equation_keeps_every_term():
    theta, y, _ = narrow_band()
    noisy = y + np.random.default_rng(0).normal(0, 1e-3, len(y))
    kept, coef = prune_exact(theta, noisy)
    assert kept.tolist() == list(range(theta.shape[1]))
    assert coef == pytest.approx(np.linalg.lstsq(theta, noisy, rcond=None)[0])


def test_stlsq_alone_keeps_spurious_terms_on_this_band():
    """Why the pruning exists: pysindy's STLSQ, as the MountainCar config runs it, keeps more
    than the four true terms on these rows."""
    theta, y, _ = narrow_band()
    opt = ps.STLSQ(threshold=0.003, alpha=0.0, normalize_columns=True)
    opt.fit(theta, y.reshape(-1, 1))
    assert np.count_nonzero(opt.coef_) > 4
