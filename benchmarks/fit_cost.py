"""Fit cost of SINDy vs the NN baseline on identical data, as ratios measured in one run.

For each env, builds both fit jobs from the app's config (default groups plus the overrides
given), collects the dataset once, then fits SINDy and the NN alternately ``--repeats`` times
(so load from other processes hits both alike) and prints the median wall and CPU seconds, the
SINDy / NN ratios and the parameter counts. One-off imports and torch's first-optimizer setup
happen before the timed fits, for both models.

    .venv/bin/python benchmarks/fit_cost.py --repeats 5
    .venv/bin/python benchmarks/fit_cost.py --envs lunar_lander -- library=polynomial
"""

from __future__ import annotations

import argparse
import statistics

import torch
from tabulate import tabulate

from sdrl_bench.cli.build import build_fit_job, compose
from sdrl_bench.data import collect, random_policy
from sdrl_bench.pipeline import build_model, check


def fit_rows(env: str, overrides: list[str]):
    """(sindy job, nn job, library, fit arrays) for ``env`` with the app's defaults."""
    jobs = [build_fit_job(compose([f"env={env}", f"surrogate={kind}", *overrides])) for kind in ("sindy", "nn")]
    library, _ = check(jobs[0])
    job, spec = jobs[0], jobs[0].spec
    data = collect(spec, job.policy or random_policy, job.n_transitions, job.epsilon, job.seed)
    x, u = spec.model_inputs(data.states, data.actions)
    keep = ~spec.at_bound(data.next_states)
    arrays = (x[keep], u[keep], data.next_states[keep][:, spec.target_index])
    return jobs, library, arrays, data.content_hash()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", nargs="+", default=["mountain_car", "lunar_lander"])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for both jobs (after --)")
    args = parser.parse_args()
    from sdrl_bench.cli.args import at_least

    at_least(parser, args, 1, "--repeats")
    torch.set_num_threads(1)
    rows = []
    for env in args.envs:
        jobs, library, (x, u, xn), digest = fit_rows(env, args.overrides)
        spec = jobs[0].spec
        names = dict(state_names=spec.target_names, control_names=spec.control_names)
        times: dict[str, list[tuple[float, float]]] = {"sindy": [], "nn": []}
        params = {}
        for r in range(args.repeats + 1):  # the first round warms both up and is not counted
            for job in jobs:
                model = build_model(job, library).fit(x, u, xn, **names)
                if r:
                    times[job.surrogate].append((model.fit_wall_seconds_, model.fit_cpu_seconds_))
                params[job.surrogate] = model.summary_metrics()["n_parameters"]
        wall = {k: statistics.median(t[0] for t in v) for k, v in times.items()}
        cpu = {k: statistics.median(t[1] for t in v) for k, v in times.items()}
        rows.append([env, len(x), digest[:12], wall["sindy"], wall["nn"], wall["sindy"] / wall["nn"],
                     cpu["sindy"], cpu["nn"], cpu["sindy"] / cpu["nn"], params["sindy"], params["nn"],
                     params["sindy"] / params["nn"]])
    print(f"median of {args.repeats} alternating fits per model; overrides: {args.overrides or 'none'}")
    print(tabulate(rows, floatfmt=".3g", headers=[
        "env", "fit rows", "dataset", "SINDy wall s", "NN wall s", "wall SINDy/NN", "SINDy CPU s",
        "NN CPU s", "CPU SINDy/NN", "SINDy terms", "NN params", "params SINDy/NN"]))


if __name__ == "__main__":
    main()
