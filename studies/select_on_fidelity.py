"""Does selecting the surrogate on the fidelity study's best metric give better agents?

Two Optuna searches over the same SINDy space on the same data (``sdrl-bench-search``, one with
today's objective ``search.objective=one_step``, one with ``--objective``), each picking its best
trial; then both picks fitted on that data as two surrogates of one ``task=fidelity`` cluster, with
``--agents`` agents each (the env's fidelity pack: recipe, budget) judged on 10 real episodes each
on the final-evaluation stream. Printed and written to ``<workdir>/select_<env>.json``: each
search's pick, its validation errors under both objectives, and its agents' real return as the
IQM with a 95% bootstrap CI (``report.tables.bootstrap_ci``), with the real steps of both arms.

The data seed (``--seed``, default 100) lies outside the study's clusters (seeds 0-11), so
nothing here was chosen on the evaluations that chose the metric.

    .venv/bin/python studies/select_on_fidelity.py --env lunar_lander --objective rollout_episode \\
        [--trials 30] [--agents 10] [--seed 100] [--workdir runs/select]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from omegaconf import open_dict

from sdrl_bench import tracking
from sdrl_bench.cli.build import compose
from sdrl_bench.cli.fidelity_task import run_fidelity_task
from sdrl_bench.cli.search import run_search
from sdrl_bench.report.tables import bootstrap_ci
from sdrl_bench.rl.jax_compile import use_compilation_cache
from sdrl_bench.search.space import GROUP_PARAMS, PARAM_KEYS

DATA = {  # the fidelity pack's middle cluster: data size and collector
    "mountain_car": (75, "heuristic"), "pendulum": (200, "random"), "lunar_lander": (1000, "heuristic"),
    "cartpole_swingup": (8000, "random"),
}


def overrides_of(params: dict) -> list[str]:
    """A search's best params as ``sdrl-bench`` overrides (group choices first)."""
    groups = [f"{k}={v}" for k, v in params.items() if k in GROUP_PARAMS]
    return groups + [f"{PARAM_KEYS[k]}={v}" for k, v in params.items() if k not in GROUP_PARAMS]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", required=True, choices=sorted(DATA))
    ap.add_argument("--objective", required=True)
    ap.add_argument("--trials", type=int, default=30)
    ap.add_argument("--agents", type=int, default=10)
    ap.add_argument("--seed", type=int, default=100)
    ap.add_argument("--workdir", type=Path, default=Path("runs/select"))
    args = ap.parse_args()
    from sdrl_bench.cli.args import at_least, folder

    at_least(ap, args, 1, "--trials", "--agents")
    work = folder(ap, args.workdir, "--workdir")
    work.mkdir(parents=True, exist_ok=True)
    uri = f"sqlite:///{work}/mlruns/mlflow.db"
    n, collector = DATA[args.env]
    common = [f"env={args.env}", f"collector={collector}", f"n_transitions={n}", f"seed={args.seed}",
              f"tracking.uri='{uri}'", f"study.storage='sqlite:///{work}/optuna.db'", f"study.export_dir='{work}/search'",
              f"search.n_trials={args.trials}", "search.space.poly_degree.high=2"]
    pack = compose([f"experiment=fidelity_{args.env}"])  # the study's recipe: a policy objective's agent and budget
    picks, t0 = {}, time.perf_counter()
    for objective in ("one_step", args.objective):
        cfg = compose([*common, f"search.objective={objective}", f"study.name={args.env}-s{args.seed}-{objective}",
                       f"search.policy.train_steps={pack.fidelity.train_steps}", "search.policy.episodes=2",
                       f"search.policy.reference={pack.fidelity.reference}"],
                      config_name="search_app", return_hydra_config=True)
        with open_dict(cfg):
            cfg.agent = pack.agent
        if pack.get("jax_cache_dir"):
            use_compilation_cache(str(work / "jax_cache"))
        _, summary = run_search(cfg, quiet=True)
        picks[objective] = {"params": dict(summary.best_params), "validation_error": summary.best_error,
                            "test_error": summary.test_error}
        print(f"{objective}: best {summary.best_params} ({objective} {summary.best_error:.4g})", flush=True)
    search_wall = time.perf_counter() - t0
    models = "{" + ", ".join(f"{k}: [{', '.join(repr(o) for o in overrides_of(v['params']))}]" for k, v in picks.items()) + "}"
    overrides = [f"experiment=fidelity_{args.env}", f"seed={args.seed}", f"tracking.uri='{uri}'",
                 f"fidelity.axes.n_transitions=[{n}]", f"fidelity.axes.collector=[{collector}]", "fidelity.axes.data_noise=[0.0]",
                 "~fidelity.models", f"+fidelity.models={models}", f"fidelity.agent_seeds={args.agents}", "fidelity.onpolicy_episodes=1",
                 f"fidelity.study=select-{args.env}", "progress_bar=false"]
    run_fidelity_task(compose(overrides), None, given=overrides)
    runs = tracking.find_runs(uri, "sdrl-bench", f"tags.`sdrl.kind` = 'fidelity-surrogate' and tags.`sdrl.study` = 'select-{args.env}'"
                              f" and attributes.status = 'FINISHED'")
    out = {"env": args.env, "objective": args.objective, "seed": args.seed, "trials": args.trials,
           "search_wall_seconds": search_wall, "picks": picks,
           "search_real_steps": {"model_data (each search)": n, "selection (trials' own episodes)": sum(
               t["metrics"].get("real_steps/selection", 0.0) for t in tracking.find_runs(
                   uri, "sdrl-bench-search", f"tags.`sdrl.study` = '{args.env}-s{args.seed}-{args.objective}' "
                   "and tags.`sdrl.kind` = 'trial'"))}}
    for objective in picks:
        r = next(r for r in runs if r["tags"].get("model") == objective)
        m = r["metrics"]
        returns = [m[f"agent{k}/real_return"] for k in range(args.agents)]
        point, lo, hi, stat = bootstrap_ci(returns)
        out[objective] = {"run_id": r["run_id"], "returns": returns, stat: point, "ci": [lo, hi],
                          "candidates": {k.split("/", 1)[1]: v for k, v in m.items() if k.startswith("candidate/")},
                          "real_steps": {k: v for k, v in m.items() if k.startswith("real_steps/")}}
        print(f"{objective}: {stat} {point:.1f} [{lo:.1f}, {hi:.1f}] over {args.agents} agents; run {r['run_id']}")
    (work / f"select_{args.env}.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
