"""The worked examples' laws over seeds (issue 17): Pendulum-v1 with the angle map, CartPole-v1
with the force encoding, each from the shipped config (``--overrides`` changes it).

Pendulum: the exact law in its per-equation form (``library=pendulum_law``: thdot' = thdot +
0.75 sin th + 0.15 u, th' = th + 0.05 thdot'; every other coefficient zero) from ``n_transitions`` random transitions,
and whether 200 surrogate steps keep (cos, sin) on the unit circle. CartPole: the number of
terms (nonzero coefficients) of the law, and the one-step normalized MSE on the held-out set.

    .venv/bin/python studies/byo_env_laws.py [--seeds 5] [--overrides n_transitions=100]
"""

from __future__ import annotations

import argparse

import numpy as np

from sdrl_bench.cli.build import build_fit_job, compose
from sdrl_bench.pipeline import fit_dynamics
from sdrl_bench.surrogate.env import SurrogateEnv

PENDULUM = {"th": {"thdot'": 0.05}, "thdot": {"sin(th)": 0.75, "torque": 0.15}}


def nonzero(model) -> dict:
    return {eq: {t: c for t, c in terms.items() if c != 0} for eq, terms in model.coefficients_by_name().items()}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--overrides", nargs="*", default=[])
    args = ap.parse_args()
    from sdrl_bench.cli.args import at_least

    at_least(ap, args, 1, "--seeds")
    exact, ring = 0, []
    for seed in range(args.seeds):
        res = fit_dynamics(build_fit_job(compose(["env=pendulum", "collector=random", f"seed={seed}", *args.overrides])))
        ok = nonzero(res.model) == PENDULUM
        exact += ok
        env = SurrogateEnv(res.model, res.job.spec)
        env.reset(seed=seed)
        dev = 0.0
        for _ in range(200):
            obs, *_ = env.step(env.action_space.sample())
            dev = max(dev, abs(float(np.hypot(obs[0], obs[1])) - 1))
        ring.append(dev)
        print(f"pendulum seed {seed}: {len(res.data)} transitions, exact law {ok}, max |r - 1| over 200 steps {dev:.1e}")
    print(f"pendulum: exact law in {exact} of {args.seeds} seeds; max |r - 1| {max(ring):.1e}")
    terms = []
    for seed in range(args.seeds):
        res = fit_dynamics(build_fit_job(compose(["env=cartpole", "collector=random", f"seed={seed}", *args.overrides])))
        n = int(res.model.summary_metrics()["n_parameters"])
        terms.append(n)
        print(f"cartpole seed {seed}: {len(res.data)} transitions, {n} terms, "
              f"mse_norm/mean {res.fidelity.metrics['mse_norm/mean']:.2e}")
    print(f"cartpole: terms per seed {terms}; <= 20 in {sum(t <= 20 for t in terms)} of {args.seeds}")
    print(res.model.describe())


if __name__ == "__main__":
    main()
