"""Is the snapping test calibrated? The true MountainCar law's Wald p-values over data seeds.

``models.snap.snap_equation`` rounds an exact equation's coefficients to the fewest significant
digits a robust (HC3) Wald test at level ``alpha`` does not reject. For the default fit of each
data seed (75 heuristic eps-0.2 transitions, poly_trig, STLSQ, as ``sdrl-bench seed=S`` fits it),
this computes the p-value of the test that the true law's two-digit coefficients (0.0015,
-0.0025, 1) meet for each equation, from the very rows and terms the fit hands to the test.
A calibrated test gives p-values uniform on [0, 1]: a level then rejects the truth in that share
of equations (the default, ``models.snap.ALPHA``, was set from this measurement). Printed: the
p-values below 0.01, the count below each level, and a Kolmogorov-Smirnov test against uniform.

    .venv/bin/python studies/snap_calibration.py [--seeds 40]
"""

from __future__ import annotations

import argparse
import warnings

import numpy as np
from scipy import stats

import sdrl_bench.models.sindy as sindy_model
from sdrl_bench.models.snap import robust_covariance, round_significant

TRUE_SUPPORT = {"x": ("x", "v", "u", "cos(3 x)"), "v": ("v", "u", "cos(3 x)")}
"""MountainCar's law, term by term (its coefficients have two significant digits: 1, 0.0015, -0.0025)."""


def true_law_pvalue(theta: np.ndarray, y: np.ndarray, coef: np.ndarray) -> float:
    """The HC3 Wald test's p-value for the coefficients rounded to two significant digits
    (the law's own), against the fitted ones: the statistic ``snap_equation`` computes."""
    theta, y, coef = (np.asarray(a, dtype=float) for a in (theta, y, coef))
    cov = robust_covariance(theta, y - theta @ coef)
    if cov is None:
        return float("nan")
    step = round_significant(coef, 2) - coef
    return float(stats.chi2.sf(float(step @ np.linalg.solve(cov, step)), len(coef)))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=40, help="data seeds 0 .. seeds-1")
    args = ap.parse_args()
    from sdrl_bench.cli.args import at_least
    from sdrl_bench.cli.build import build_fit_job, compose
    from sdrl_bench.pipeline import fit_dynamics

    at_least(ap, args, 1, "--seeds")
    pvalues: list[tuple[int, str, float]] = []
    calls: list[float] = []
    snap = sindy_model.snap_equation

    def recording(theta, y, coef, *rest, **kw):  # the fit's own call (one per equation, in state order)
        calls.append(true_law_pvalue(theta, y, coef) if np.size(coef) else float("nan"))
        return snap(theta, y, coef, *rest, **kw)

    sindy_model.snap_equation = recording
    off_support = 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for seed in range(args.seeds):
            calls.clear()
            model = fit_dynamics(build_fit_job(compose([f"seed={seed}"]))).model
            if len(calls) != len(model.state_names_):
                raise SystemExit(f"seed {seed}: the fit called the snapping test {len(calls)} times for "
                                 f"{len(model.state_names_)} equations (not a SindyModel with snapping on?)")
            for state, value in zip(model.state_names_, calls, strict=True):
                if set(model.coefficients_by_name()[state]) == set(TRUE_SUPPORT[state]):
                    pvalues.append((seed, state, value))
                else:  # another support: its two-digit rounding is not the law's
                    off_support += 1
    p = np.array([v for *_, v in pvalues])
    print(f"{len(p)} equations on the law's support ({args.seeds} seeds x 2; {off_support} on another left out); "
          f"smallest p-value {p.min():.4g}")
    print("below 0.01: " + (", ".join(f"seed {s} {e} p={v:.4g}" for s, e, v in pvalues if v < 0.01) or "none"))
    for level in (0.05, 0.01, 0.001):
        print(f"rejected at {level:g}: {int((p < level).sum())} of {len(p)} (expected {level * len(p):.2g})")
    print(f"Kolmogorov-Smirnov against uniform: p = {stats.kstest(p, 'uniform').pvalue:.2f}; "
          f"deciles {np.histogram(p, bins=10, range=(0, 1))[0].tolist()}")


if __name__ == "__main__":
    main()
