"""Which kernel choices change a seed's numbers on this machine (docs/seeds.md, "On another machine").

torch, MKL, OpenBLAS and XLA pick their kernels by the CPU they run on, so the same seed on a
machine with other vector units rounds differently. This study makes that visible on one machine:
it reruns one seed in fresh processes, each with one kernel choice changed by an environment
variable, and compares what came out with the run that changed nothing:

- ``sac`` / ``sac_jax``: the README main job's agent (``experiment=quick_mountain_car``), trained
  ``--steps`` steps in the surrogate fitted from the main job's 75 transitions; compared by its
  parameters (bit for bit) and its deterministic action on a fixed observation;
- ``fit_lunar_lander`` / ``fit_mountain_car``: the fast packs' SINDy fits (the heuristic's data);
  compared by the model's numbers (``to_dict``), with the largest difference.

    .venv/bin/python studies/kernel_choices.py                 # every row (4 to 6 minutes on 2 cores)
    .venv/bin/python studies/kernel_choices.py --rows fit_lunar_lander

Each case runs in its own process because the libraries read these variables when they load.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

CASES = {
    "sac": [{}, {}, {"ATEN_CPU_CAPABILITY": "default"}, {"MKL_CBWR": "COMPATIBLE"}, {"MKL_CBWR": "AVX2"},
            {"OPENBLAS_CORETYPE": "Sandybridge"}],
    "sac_jax": [{}, {"XLA_FLAGS": "--xla_cpu_prefer_vector_width=256"},
                {"XLA_FLAGS": "--xla_cpu_prefer_vector_width=128"}],
    "fit_mountain_car": [{}, {"OPENBLAS_CORETYPE": "Sandybridge"}, {"OPENBLAS_CORETYPE": "Prescott"}],
    "fit_lunar_lander": [{}, {"OPENBLAS_CORETYPE": "Sandybridge"}, {"OPENBLAS_CORETYPE": "Prescott"}],
}
"""Per row, the processes to run: the first changes nothing (the reference), the rest one
variable each (an empty one: the reference again, to show that a seed repeats)."""

FITS = {"fit_mountain_car": ["experiment=fast_mountain_car", "collector=heuristic"],
        "fit_lunar_lander": ["experiment=fast_lunar_lander", "collector=heuristic"]}


def _numbers(obj, out: list[float]) -> list[float]:
    """Every float in a model's ``to_dict``, in a fixed order."""
    if isinstance(obj, dict):
        for k in sorted(obj):
            _numbers(obj[k], out)
    elif isinstance(obj, list | tuple):
        for v in obj:
            _numbers(v, out)
    elif isinstance(obj, float):
        out.append(obj)
    return out


def worker(row: str, steps: int, out: Path) -> None:
    """One case, in this process: writes the numbers to compare (``out``, .npy) and prints a JSON
    line with the probe."""
    from sdrl_bench.cli.build import build_fit_job, compose, instantiate_key
    from sdrl_bench.pipeline import fit_dynamics

    if row in FITS:
        fit = fit_dynamics(build_fit_job(compose(FITS[row])))
        np.save(out, np.asarray(_numbers(fit.model.to_dict(), []), np.float64))
        print(json.dumps({"probe": None}))
        return
    cfg = compose(["experiment=quick_mountain_car", f"agent={row}"])
    if row == "sac_jax":
        from sdrl_bench.models.jax_eval import jax_modules

        jax_modules("studies/kernel_choices.py")
    import torch

    from sdrl_bench.rl.agents import make_agent
    from sdrl_bench.rl.transfer import surrogate_vec_env

    torch.set_num_threads(int(cfg.torch_threads))
    fit = fit_dynamics(build_fit_job(cfg))
    model = make_agent(instantiate_key(cfg.agent, "agent"), surrogate_vec_env(fit.model, fit.spec, 1, int(cfg.seed)),
                       int(cfg.seed))
    model.learn(steps)
    if row == "sac_jax":
        import jax

        leaves = [np.asarray(x) for x in jax.tree_util.tree_leaves(model.state.nets)]
    else:
        leaves = [p.detach().numpy() for p in model.policy.parameters()]
    np.save(out, np.concatenate([x.astype(np.float64).ravel() for x in leaves]))
    action, _ = model.predict(np.array([-0.5, 0.01], np.float32), deterministic=True)
    print(json.dumps({"probe": float(np.ravel(action)[0])}))


def run_case(row: str, env_change: dict[str, str], steps: int, folder: Path, k: int) -> dict:
    out = folder / f"{row}-{k}.npy"
    env = {**os.environ, **env_change}
    cmd = [sys.executable, __file__, "--worker", row, "--steps", str(steps), "--out", str(out)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=1800)
    if proc.returncode != 0:
        raise SystemExit(f"kernel_choices: {row} with {env_change or 'nothing changed'} failed:\n{proc.stderr[-2000:]}")
    probe = json.loads(proc.stdout.strip().splitlines()[-1])["probe"]
    return {"numbers": np.load(out), "probe": probe}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", nargs="+", default=list(CASES), choices=list(CASES))
    ap.add_argument("--steps", type=int, default=2000, help="the agents' training steps")
    ap.add_argument("--worker", choices=list(CASES), help=argparse.SUPPRESS)
    ap.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        worker(args.worker, args.steps, args.out)
        return
    from sdrl_bench.tracking import cpu_tags, machine_label

    print(f"machine: {machine_label(cpu_tags())}")
    print("| row | changed | numbers' hash | same as the reference | numbers that differ | largest difference | probe |")
    print("|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for row in args.rows:
            ref = None
            for k, change in enumerate(CASES[row]):
                got = run_case(row, change, args.steps, Path(tmp), k)
                nums = got["numbers"]
                digest = hashlib.sha256(nums.tobytes()).hexdigest()[:12]
                ref = ref if ref is not None else nums
                same = nums.shape == ref.shape and np.array_equal(nums, ref)
                diff = float(np.abs(nums - ref).max()) if nums.shape == ref.shape else float("nan")
                n_diff = f"{int(np.count_nonzero(nums != ref))} of {nums.size}" if nums.shape == ref.shape else "other shape"
                label = " ".join(f"{k_}={v}" for k_, v in change.items()) or ("nothing (the reference)" if k == 0
                                                                               else "nothing (again)")
                probe = "" if got["probe"] is None else f"{got['probe']:.9f}"
                print(f"| {row} | {label} | {digest} | {'yes' if same else 'no'} | {n_diff} | {diff:.3g} | {probe} |",
                      flush=True)


if __name__ == "__main__":
    main()
