"""The LunarLander pessimism's free band: how much the flight law's ensemble disagrees on real
flight, in units of the flight noise floor's standard deviation.

The surrogate penalizes disagreement beyond ``env.spec.uncertainty.free`` (``envs/task.py``,
MOPO); the band is the data's own level, so that an ordinary flight step costs nothing and only
states the data did not cover are penalized. For each seed: the default fit
(``sdrl-bench env=lunar_lander``: the per-equation flight law with 5 bootstrap members), its
disagreement (``ModelEnv.disagreement``) on the held-out set's flight rows (both legs up), and
the 50th, 90th, 99th percentiles. No real step beyond the fits' own collections and the fixed
held-out set.

    .venv/bin/python studies/pessimism_free_band.py [--seeds 0,1,2,3,4]
"""

from __future__ import annotations

import argparse

import numpy as np

from sdrl_bench.cli.build import build_fit_job, compose
from sdrl_bench.pipeline import fit_dynamics
from sdrl_bench.surrogate.model_env import ModelEnv


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--overrides", nargs="*", default=[])
    args = ap.parse_args()
    from sdrl_bench.cli.args import seed_list

    seeds = seed_list(ap, args.seeds)
    print("seed  rows  p50    p90    p99")
    for seed in seeds:
        fit = fit_dynamics(build_fit_job(compose(["env=lunar_lander", f"seed={seed}", *args.overrides])))
        core = ModelEnv(fit.model, fit.job.spec, noise=False)
        test = fit.test
        flight = np.asarray(core.task.model_regime(test.states), bool)
        z = core.model_inputs(test.states[flight], test.actions[flight])
        u = core.disagreement(z)
        p50, p90, p99 = np.percentile(u, [50, 90, 99])
        print(f"{seed:4d}  {flight.sum():4d}  {p50:.3f}  {p90:.3f}  {p99:.3f}")


if __name__ == "__main__":
    main()
