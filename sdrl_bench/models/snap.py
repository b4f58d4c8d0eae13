"""Snapping the coefficients of an exact law to the short decimals the data cannot tell apart.

A deterministic environment seen through float32 observations (MountainCar) gives data in
which a sparse law holds to the observations' precision. Least squares then returns that law
with coefficients a few float32 ulps off (0.0014999988 for 0.0015): harmless for one-step
error, but enough to change the rounding of a float32 step now and then, so a surrogate
drifts a few ulps away from the real env over an episode. Occam's answer: of the coefficient
vectors the data cannot reject, take the one with the fewest significant digits.

``prune_exact`` comes first, for the same reason with terms instead of digits: of the supports
the data cannot reject, take the smallest. Over a narrow band of positions (75 expert
transitions of MountainCar seed 3) x, x^2, sin 3x, cos 3x and the bias are collinear to float32
precision, and STLSQ keeps a seven-term x equation that fits those rows exactly but is wrong
outside them (held-out MSE 2.8e-3, normalized 9.0). Backward elimination, each step dropping the
term whose removal leaves the smallest residual while the equation stays exact, recovers the
four-term law there (the next removal raises the residual from 2.7e-8 to 2.0e-4, relative).

``snap_equation`` does that for one equation, in two gates:

1. **Exact regime.** The equation's residual RMS must be within ``rtol`` of its target's RMS
   (float32 resolves about 6e-8 relative; the default 1e-6 leaves room for a few roundings).
   A noisy equation (LunarLander: 1e-2 and worse) is never touched: there rounding would
   bias a coefficient known only to its standard error.
2. **Not rejected.** For d = 1, 2, ... significant digits, the rounded vector is tested against
   the fitted one by a Wald test with a heteroscedasticity-robust (HC3) covariance, at level
   ``alpha``. Robust, because float32 rounding noise scales with each target's magnitude: an
   ordinary F-test rejected the true MountainCar law in 5 of 80 equations at the 1% level,
   the HC3 test in 0 of 80 (seeds 0-39, both equations) on an AVX2 host, 2 of 80 on an AVX-512
   one, as a calibrated test does at that level (``ALPHA``). The first d not rejected wins.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

MAX_DIGITS = 15
ALPHA = 0.001
"""The test's default level. The true MountainCar law's Wald p-values are uniform over data seeds
(seeds 0-39, both equations, 2026-11-30: Kolmogorov-Smirnov p = 0.69 against uniform), so a level
rejects the truth in that share of equations: at 0.01, 2 of 80 on an AVX-512 EPYC (p = 0.0091
and just below 0.01; 0 of 80 on an AVX2 one), and those fits kept 10-digit coefficients that
drift off the real env. At 0.001 none of the 80. A lower level admits no wrong law: a rounding
that changes a coefficient beyond float32 noise lies many standard errors from the fit, far
past either critical value (13.3 and 18.5 for four terms).
Provenance: studies/snap_calibration.py (`.venv/bin/python studies/snap_calibration.py --seeds 40`); data: the default fit's own 75 heuristic eps-0.2 transitions of each data seed 0-39 (3,000 real steps)."""


def round_significant(values: np.ndarray, digits: int) -> np.ndarray:
    """Each value rounded to ``digits`` significant decimal digits (then to the nearest double)."""
    return np.array([float(f"{float(v):.{digits - 1}e}") for v in np.ravel(values)])


def _relative_residual(theta: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray]:
    coef, *_ = np.linalg.lstsq(theta, y, rcond=None)
    resid = y - theta @ coef
    return float(np.sqrt(resid @ resid / max(float(y @ y), np.finfo(float).tiny))), coef


def prune_exact(theta: np.ndarray, y: np.ndarray, rtol: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """(kept column indices, their least-squares coefficients) for an exact equation
    ``y ~ theta @ coef``: backward elimination of terms while the residual RMS stays within
    ``rtol`` of the target's RMS. An equation that is not exact to begin with keeps every column
    (its least-squares coefficients are returned; callers keep their own fit then)."""
    theta, y = np.asarray(theta, dtype=float), np.asarray(y, dtype=float)
    keep = list(range(theta.shape[1]))
    res, coef = _relative_residual(theta, y) if keep else (np.inf, np.zeros(0))
    if not res <= rtol:
        return np.asarray(keep, dtype=int), coef
    while len(keep) > 1:
        trials = [(_relative_residual(theta[:, [j for j in keep if j != k]], y), k) for k in keep]
        (best_res, best_coef), drop = min(trials, key=lambda t: t[0][0])
        if not best_res <= rtol:
            break
        keep.remove(drop)
        coef = best_coef
    return np.asarray(keep, dtype=int), coef


def robust_covariance(theta: np.ndarray, resid: np.ndarray) -> np.ndarray | None:
    """The HC3 (heteroscedasticity-robust) covariance of least-squares coefficients over the
    columns of ``theta`` with residuals ``resid``; None for a degenerate design (a singular
    normal matrix, or a row of leverage 1)."""
    try:
        xtx_inv = np.linalg.inv(theta.T @ theta)
    except np.linalg.LinAlgError:
        return None
    leverage = np.einsum("ij,jk,ik->i", theta, xtx_inv, theta)
    if not np.all(np.isfinite(leverage)) or np.any(leverage >= 1.0 - 1e-12):
        return None
    meat = theta.T @ (theta * (resid**2 / (1.0 - leverage) ** 2)[:, None])
    return xtx_inv @ meat @ xtx_inv


def snap_equation(theta: np.ndarray, y: np.ndarray, coef: np.ndarray, alpha: float = ALPHA,
                  rtol: float = 1e-6) -> tuple[np.ndarray, int]:
    """(coefficients, digits) for ``y ~ theta @ coef`` over the active terms (columns of theta).

    Returns the rounded coefficients and their number of significant digits, or ``coef``
    unchanged and 0 when the equation is not in the exact regime, the design is degenerate,
    or no rounding up to ``MAX_DIGITS`` digits passes the test.
    """
    theta, y, coef = (np.asarray(a, dtype=float) for a in (theta, y, coef))
    n, p = theta.shape
    if p == 0 or n <= p:
        return coef, 0
    resid = y - theta @ coef
    if float(resid @ resid) > rtol**2 * float(y @ y):
        return coef, 0
    cov = robust_covariance(theta, resid)
    if cov is None:
        return coef, 0
    critical = float(stats.chi2.ppf(1.0 - alpha, p))
    previous = None
    for digits in range(1, MAX_DIGITS + 1):
        rounded = round_significant(coef, digits)
        if previous is not None and np.array_equal(rounded, previous):
            continue
        previous = rounded
        if np.array_equal(rounded, coef):
            return coef, 0  # nothing shorter than the fit itself
        step = rounded - coef
        try:
            wald = float(step @ np.linalg.solve(cov, step))
        except np.linalg.LinAlgError:
            return coef, 0
        if np.isfinite(wald) and wald <= critical:
            return rounded, digits
    return coef, 0
