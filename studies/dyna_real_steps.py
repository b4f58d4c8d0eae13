"""Dyna-style refits against the real arm, per env, on the same seeds, counted in real transitions.

Three arms, each an ordinary ``sdrl-bench -m`` sweep into one MLflow store (resumable: a rerun
adopts finished jobs; ``--report-only`` prints the table from the store):

  real   the fast PPO recipe in real envs, stopped at its first real evaluation >= the solved
         threshold (``experiment=fast_<env> rl.arms=[real]``)
  sindy  ``experiment=dyna_<env>``: Dyna with the SINDy surrogate and the learned event model
  nn     ``experiment=dyna_<env> surrogate=nn``: the same loop, the same budget, the NN surrogate

Per arm: seeds solved; real transitions to solve, by phase (the Dyna loop's model data,
screens and confirmations; the real arm's training steps and the learning-curve evaluations
that decided it was solved); surrogate steps; wall seconds; the last confirmation (Dyna) or the
final 20-episode evaluation (real arm); the audit of the final Dyna agent on fresh episodes.
Medians over seeds, IQM with a 95% percentile-bootstrap CI for the returns, and the ratio of the
median real transitions to solve (Dyna / real arm). A seed that does not solve within its budget
counts as infinitely expensive.

    .venv/bin/python studies/dyna_real_steps.py --env lunar_lander --seeds 0-4 --workdir /tmp/dyna
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from tabulate import tabulate

from sdrl_bench.cli.args import run_child, script_main
from sdrl_bench.report.tables import bootstrap_ci
from sdrl_bench.tracking.read import find_runs

ARMS = ("real", "sindy", "nn")


def overrides(env: str, arm: str, seeds: list[int], uri: str, jobs: int) -> list[str]:
    common = [f"seed={','.join(map(str, seeds))}", f"tracking.uri={uri}", f"hydra.launcher.n_jobs={jobs}"]
    if arm == "real":
        return [f"experiment=fast_{env}", "rl.arms=[real]", "rl.reuse_real_arm=false", *common]
    return [f"experiment=dyna_{env}", f"surrogate={arm}", *common]


def run_arm(workdir: Path, args: list[str]) -> None:
    print("+ sdrl-bench -m " + " ".join(args), flush=True)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    run_child([sys.executable, "-m", "sdrl_bench.cli.main", "-m", *args], cwd=workdir, env=env,
              stdout=subprocess.DEVNULL)  # stopped with this script


def gather(uri: str, env: str, seeds: list[int]) -> dict[str, dict[int, dict[str, float]]]:
    """{arm: {seed: metrics}} from the store's finished runs (the newest run of a seed wins)."""
    out: dict[str, dict[int, dict[str, float]]] = {a: {} for a in ARMS}
    runs = find_runs(uri, "sdrl-bench", f"tags.env = '{env}' and attributes.status = 'FINISHED'")
    for r in sorted(runs, key=lambda r: r["start_time"]):
        t, m = r["tags"], r["metrics"]
        seed = int(t.get("seed", -1))
        if seed not in seeds:
            continue
        if t.get("sdrl.kind") == "dyna" and t.get("surrogate") in ("sindy", "nn"):
            out[t["surrogate"]][seed] = {**m, "run_id": r["run_id"]}
        elif t.get("sdrl.kind") == "transfer" and t.get("arms") == "real" and t.get("agent") == "ppo_fast":
            real = {k.split("/", 1)[1]: v for k, v in m.items() if k.startswith("real/")}
            if "solved_real_steps" in real:  # training steps to the first hit + the evaluations that found it
                real["solved"] = 1.0
                real["solved_real_transitions"] = real["solved_real_steps"] + real.get("eval_steps", 0.0)
            else:
                real["solved"] = 0.0
            real["wall_seconds"] = real.get("train_wall_seconds", math.nan) + real.get("curve_eval_wall_seconds", 0.0)
            real["real_transitions_total"] = (real.get("real_transitions_train", 0.0) + real.get("eval_steps", 0.0)
                                              + real.get("final_eval_steps", 0.0))
            out["real"][seed] = {**real, "run_id": r["run_id"]}
    return out


def _median(values: list[float]) -> float:
    return float(np.median(values)) if values else math.nan


def _steps(value: float) -> str:
    return "-" if math.isnan(value) else f"{value:,.0f}"


def _ci(values: list[float]) -> str:
    point, lo, hi, name = bootstrap_ci(values)
    if math.isnan(point):
        return "-"
    return f"{point:.1f} [{lo:.1f}, {hi:.1f}]" if not math.isnan(lo) else f"{point:.1f}"


def table(data: dict[str, dict[int, dict[str, float]]], seeds: list[int]) -> tuple[str, str]:
    rows, per_seed = [], []
    medians: dict[str, float] = {}
    for arm in ARMS:
        runs = data[arm]
        if not runs:
            continue
        solved = [s for s in seeds if runs.get(s, {}).get("solved") == 1.0]
        # unsolved seeds count as infinitely expensive
        cost = [runs[s]["solved_real_transitions"] if s in solved else math.inf for s in seeds if s in runs]
        medians[arm] = float(np.median(cost)) if cost else math.nan
        if arm == "real":
            phases = (f"train {_steps(_median([runs[s].get('solved_real_steps', math.nan) for s in solved]))} + "
                      f"evaluations {_steps(_median([runs[s].get('eval_steps', math.nan) for s in solved]))}")
            final = [runs[s].get("final_return_mean", math.nan) for s in runs]
            audit = "-"
        else:
            phases = " + ".join(f"{p} {_steps(_median([runs[s].get(f'real_steps_{p}', math.nan) for s in solved]))}"
                                for p in ("collect", "evaluate", "final"))
            final = [runs[s].get("final_return_mean", math.nan) for s in runs]
            audit = _ci([runs[s].get("audit_return_mean", math.nan) for s in runs])
        rows.append([arm, f"{len(solved)}/{len(runs)}", "not solved" if math.isinf(medians[arm]) else _steps(medians[arm]), phases,
                     f"{_median([runs[s].get('surrogate_steps', 0.0) for s in runs]):,.0f}",
                     f"{_median([runs[s].get('wall_seconds', math.nan) for s in runs]):.1f}",
                     _ci(final), audit])
        for s in sorted(runs):
            m = runs[s]
            per_seed.append([arm, s, "yes" if m.get("solved") == 1.0 else "no",
                             _steps(m.get("solved_real_transitions", math.nan)), _steps(m.get("real_transitions_total", math.nan)),
                             f"{m.get('rounds', math.nan):.0f}", f"{m.get('final_return_mean', math.nan):.1f}",
                             f"{m.get('audit_return_mean', math.nan):.1f}", m["run_id"]])
    head = ["arm", "solved", "median real transitions to solve", "of which (medians over the solved seeds)", "median surrogate steps",
            "median wall s", "last 20-episode return, IQM [95% CI]", "audit return, IQM [95% CI]"]
    text = tabulate(rows, head, tablefmt="github", disable_numparse=True)
    for arm in ("sindy", "nn"):
        if arm in medians and "real" in medians and medians["real"] not in (0, math.inf):
            ratio = medians[arm] / medians["real"]
            text += (f"\nratio of median real transitions to solve, {arm} Dyna / real arm: "
                     + ("- (Dyna's median seed did not solve)" if math.isinf(ratio) else f"{ratio:.3f}"))
    seeds_text = tabulate(per_seed, ["arm", "seed", "solved", "real transitions to solve", "real transitions in all",
                                     "rounds", "last 20-episode return", "audit return", "run id"], tablefmt="github",
                          disable_numparse=True)
    return text, seeds_text


def curves_figure(uri: str, data: dict[str, dict[int, dict[str, float]]], env: str, path: Path) -> Path | None:
    """Every seed's learning curve against real transitions, on one axis: Dyna (x: every real
    step of the loop when the screen ended) and the real arm (x: its training steps; its own
    evaluation steps are not added, which flatters it)."""
    import tempfile

    import pandas as pd
    from matplotlib.figure import Figure

    from sdrl_bench.tracking.read import download_artifact

    fig = Figure(figsize=(8, 4.5))
    ax = fig.subplots()
    colors = {"real": "tab:gray", "sindy": "tab:blue", "nn": "tab:orange"}
    drawn = False
    with tempfile.TemporaryDirectory() as tmp:
        for arm, runs in data.items():
            artifact, x = ("curves/real.csv", "train_steps") if arm == "real" else ("curves/dyna.csv", "real_transitions")
            for i, (seed, m) in enumerate(sorted(runs.items())):
                got = download_artifact(uri, m["run_id"], artifact, Path(tmp) / f"{arm}-{seed}")
                if got is None:
                    continue
                c = pd.read_csv(got)
                c = c[c[x] > 0]  # the real arm's point before training has no place on a log axis
                label = {"real": "real arm (x: training steps)", "sindy": "Dyna, SINDy", "nn": "Dyna, NN"}[arm]
                ax.plot(c[x], c["return_mean"], color=colors[arm], alpha=0.8, marker="." if arm != "real" else None,
                        label=label if i == 0 else None)
                drawn = True
    if not drawn:
        return None
    ax.axhline(200 if env == "lunar_lander" else 90, color="k", ls="--", lw=0.8, label="solved")
    ax.set_xscale("log")
    ax.set_ylim(bottom=max(ax.get_ylim()[0], -300.0))  # the real arm's untrained start (down to -1000) is cut off
    ax.set_xlabel("real transitions (log scale)")
    ax.set_ylabel("return in the real env")
    ax.set_title(f"{env}: Dyna vs the real arm, one line per seed")
    ax.legend(loc="lower left", fontsize=8, framealpha=0.9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--env", choices=("lunar_lander", "mountain_car"), default="lunar_lander")
    ap.add_argument("--seeds", default="0-4")
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/sdrl-dyna"))
    ap.add_argument("--arms", default=",".join(ARMS), help="which arms to run (comma-separated)")
    ap.add_argument("--jobs", type=int, default=2, help="parallel jobs per sweep")
    ap.add_argument("--report-only", action="store_true", help="print the table from the store; run nothing")
    args = ap.parse_args()
    from sdrl_bench.cli.args import folder, jobs, seed_list

    seeds = seed_list(ap, args.seeds)
    unknown = [a for a in args.arms.split(",") if a not in ARMS]
    if unknown:
        ap.error(f"--arms: {', '.join(map(repr, unknown))} is not an arm ({','.join(ARMS)})")
    jobs(ap, args.jobs)
    folder(ap, args.workdir, "--workdir")
    args.workdir.mkdir(parents=True, exist_ok=True)
    uri = f"sqlite:///{(args.workdir / 'mlruns' / 'mlflow.db').resolve()}"
    if not args.report_only:
        for arm in args.arms.split(","):
            run_arm(args.workdir, overrides(args.env, arm, seeds, uri, args.jobs))
    data = gather(uri, args.env, seeds)
    summary, per_seed = table(data, seeds)
    print(f"\n{args.env}, seeds {args.seeds} (store {uri})\n\n{summary}\n\n{per_seed}")
    fig = curves_figure(uri, data, args.env, args.workdir / "figures" / f"dyna_{args.env}.png")
    if fig is not None:
        print(f"\nlearning curves against real transitions: {fig}")


if __name__ == "__main__":
    script_main(main, "dyna_real_steps.py")
