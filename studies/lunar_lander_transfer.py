"""Summarize the LunarLander paper pack's transfer runs in a store: per seed the surrogate arm's
mean real return (20 final episodes), its return in its own surrogate and the optimism gap, the
real arm's mean; across seeds the IQM with a 95% bootstrap CI (scipy.stats.bootstrap,
percentile, 10,000 resamples, seed 0) and how many seeds reach 200.

    .venv/bin/python studies/lunar_lander_transfer.py [--uri sqlite:///mlruns/mlflow.db ...]

Several ``--uri``: the arms may come from different stores (e.g. the real arm run once and kept
in its own store); a seed's arm is taken from the first store that holds it.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy import stats

from sdrl_bench.tracking.read import find_runs


def iqm(x, axis=-1):
    return stats.trim_mean(x, 0.25, axis=axis)


def summary(values: list[float]) -> str:
    v = np.asarray(values, dtype=float)
    if len(v) < 2:
        return f"n={len(v)}"
    ci = stats.bootstrap((v,), iqm, n_resamples=10_000, confidence_level=0.95, method="percentile",
                         random_state=np.random.default_rng(0)).confidence_interval
    return f"IQM {iqm(v):.1f} [95% CI {ci.low:.1f}, {ci.high:.1f}], mean {v.mean():.1f}, n={len(v)}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--uri", action="append", help="a store (repeatable; default sqlite:///mlruns/mlflow.db)")
    ap.add_argument("--experiment", default="sdrl-bench")
    args = ap.parse_args()
    from sdrl_bench.cli.args import store

    for uri in args.uri or []:
        store(ap, uri)
    runs = [r for uri in (args.uri or ["sqlite:///mlruns/mlflow.db"]) for r in find_runs(uri, args.experiment)
            if r["tags"].get("env") == "lunar_lander" and r["status"] == "FINISHED"]
    per_seed: dict[int, dict[str, float]] = {}
    for r in runs:
        m, seed = r["metrics"], int(r["tags"].get("seed", -1))
        row = per_seed.setdefault(seed, {})
        for arm in ("surrogate", "real"):
            if f"{arm}/final_return_mean" in m and arm not in row:
                row[arm] = m[f"{arm}/final_return_mean"]
        if "surrogate/surrogate_optimism_gap" in m and "gap" not in row:
            row["own"] = m["surrogate/surrogate_return_mean"]
            row["gap"] = m["surrogate/surrogate_optimism_gap"]
    print(f"{'seed':>4} {'surrogate arm (real)':>21} {'in own surrogate':>17} {'optimism gap':>13} {'real arm':>9}")
    for seed in sorted(per_seed):
        row = per_seed[seed]
        print(f"{seed:>4} " + " ".join(f"{row.get(k, float('nan')):>{w}.1f}" for k, w in
                                        (("surrogate", 21), ("own", 17), ("gap", 13), ("real", 9))))
    sur = [r["surrogate"] for r in per_seed.values() if "surrogate" in r]
    real = [r["real"] for r in per_seed.values() if "real" in r]
    print(f"surrogate arm: {summary(sur)}; seeds >= 200: {sum(v >= 200 for v in sur)} of {len(sur)}")
    print(f"real arm:      {summary(real)}")


if __name__ == "__main__":
    main()
