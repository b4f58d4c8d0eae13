"""Surrogate throughput of this checkout beside another git revision's, measured in one run.

Did a change slow the surrogate step? This checks out ``--base`` (default ``HEAD``) into a temp
worktree and times, in child processes that alternate between the two trees (so that a busy
machine slows both alike), the single surrogate env and the vector env at N = 64 and 1024 for
MountainCar and LunarLander, built from the env's own config (``compose(["env=..."])``: the
pessimism and noise its packs use) around the same saved models (fitted here once, by this
checkout's defaults). Prints steps per CPU second (median of ``--repeats``) and the ratio
this / base.

    .venv/bin/python benchmarks/surrogate_vs_revision.py --base 9b64496 [--repeats 3]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ENVS = ("mountain_car", "lunar_lander")

PROBE = r'''
import sys, time
import numpy as np
from sdrl_bench.cli.build import compose, build_fit_job
from sdrl_bench.models.base import load_model
from sdrl_bench.surrogate.env import SurrogateEnv
from sdrl_bench.surrogate.vec import SurrogateVecEnv

def rate(fn, n):
    fn(50)
    t = time.process_time()
    done = fn(n)
    return done / (time.process_time() - t)

for env_name, path in zip(sys.argv[1::2], sys.argv[2::2]):
    spec = build_fit_job(compose([f"env={env_name}"])).spec
    model = load_model(path)
    single = SurrogateEnv(model, spec)
    space = single.action_space
    space.seed(0)
    acts = [space.sample() for _ in range(4096)]

    def run_single(n):
        single.reset(seed=1)
        for i in range(n):
            _, _, te, tr, _ = single.step(acts[i % 4096])
            if te or tr:
                single.reset()
        return n

    print(env_name, "single", rate(run_single, 20000), flush=True)
    for N in (64, 1024):
        venv = SurrogateVecEnv(model, spec, N, seed=0)
        venv.reset()
        A = np.array([[space.sample() for _ in range(N)] for _ in range(8)])

        def run_vec(n, venv=venv, A=A, N=N):
            steps = max(1, n // N)
            for i in range(steps):
                venv.step(A[i % 8])
            return steps * N

        print(env_name, f"vec_N={N}", rate(run_vec, 200_000 if N == 64 else 2_000_000), flush=True)
'''


def probe(tree: Path, models: dict[str, Path]) -> dict[tuple[str, str], float]:
    args = [a for env, p in models.items() for a in (env, str(p))]
    env = {"PYTHONPATH": str(tree), "OPENBLAS_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"}
    out = subprocess.run([sys.executable, "-c", PROBE, *args], cwd=tree, env=env, capture_output=True, text=True, check=True)
    return {(p[0], p[1]): float(p[2]) for p in (line.split() for line in out.stdout.splitlines()) if len(p) == 3}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--base", default="HEAD", help="the git revision to compare against")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    from sdrl_bench.cli.args import at_least

    at_least(ap, args, 1, "--repeats")
    if subprocess.run(["git", "rev-parse", "--verify", "--quiet", f"{args.base}^{{commit}}"], cwd=ROOT,
                      capture_output=True).returncode:
        ap.error(f"--base: {args.base!r} is not a commit of this checkout")
    from sdrl_bench.cli.build import build_fit_job, compose
    from sdrl_bench.pipeline import fit_dynamics

    with tempfile.TemporaryDirectory() as tmp:
        models = {}
        for env in ENVS:
            models[env] = fit_dynamics(build_fit_job(compose([f"env={env}"]))).model.save(Path(tmp) / f"{env}.json")
        base = Path(tmp) / "base"
        subprocess.run(["git", "worktree", "add", "--detach", str(base), args.base], cwd=ROOT, check=True,
                       capture_output=True)
        try:
            runs: dict[str, list[dict]] = {"base": [], "this": []}
            for _ in range(args.repeats):
                runs["base"].append(probe(base, models))
                runs["this"].append(probe(ROOT, models))
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(base)], cwd=ROOT, check=False)
    print(f"steps per CPU second, median of {args.repeats} alternating runs; base = {args.base}")
    print(f"{'env':14s} {'config':12s} {'base':>14s} {'this':>14s} {'this/base':>10s}")
    for key in runs["this"][0]:
        b = statistics.median(r[key] for r in runs["base"])
        t = statistics.median(r[key] for r in runs["this"])
        print(f"{key[0]:14s} {key[1]:12s} {b:14,.0f} {t:14,.0f} {t / b:10.3f}")


if __name__ == "__main__":
    main()
