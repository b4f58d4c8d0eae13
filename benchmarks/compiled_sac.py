"""SAC with its gradient steps compiled (``agent=sac_jax``) against stable-baselines3's SAC
(``agent=sac``), side by side in one run, in MountainCar's SINDy surrogate.

The surrogate is the README's main job's (``experiment=quick_mountain_car``: 75 transitions of
the env's heuristic, the trig library, STLSQ); both agents take the same recipe, the agent group's
SAC (the rl-zoo settings: gSDE at log-std -3.67, [64, 64] networks, batch 512, 32 steps collected
then 32 gradient steps, a fixed entropy coefficient 0.1), built as the harness builds them
(``rl.transfer.surrogate_vec_env``, ``rl.agents.make_agent``). Measured, repeated ``--repeats``
times with the two interleaved and a fresh seed each time:

  (a) SB3's SAC training ``--steps`` steps in the surrogate vector env (torch networks);
  (b) the compiled SAC (``rl.jax_sac_agent.JaxSAC``): the same collection in Python, the gradient
      steps one jax call per collection (its first call compiles: timed apart);

the median training steps per second (collection + gradient steps), the ratio (b)/(a), the share
of each in collection, the gradient step alone (SB3's ``SAC.train(32, 512)`` and (b)'s compiled
call, each timed over warm calls on the trained agent's replay buffer), (b)'s compile, and each
trained policy's deterministic return in the surrogate (``--eval-episodes``), a check that both
learn alike. Wall-clock seconds: run it on a quiet machine.

    .venv/bin/python benchmarks/compiled_sac.py [--steps 8192] [--repeats 3] [--cores 1] [--quick]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from compiled_ppo import sb3_run, sb3_surrogate_returns  # this folder's: the script's own directory is on the path

from sdrl_bench.cli.build import build_fit_job, compose, instantiate_key
from sdrl_bench.pipeline import fit_dynamics
from sdrl_bench.rl import jax_compile, jax_sac_agent

FIT = ["experiment=quick_mountain_car"]
"""The main job's surrogate (its fit: the pack's collector, library and optimizer)."""
ARMS = {"a": ("agent=sac", "(a) SB3 SAC"), "b": ("agent=sac_jax", "(b) compiled SAC (jax)")}


def run_arm(agent, model, spec, steps: int, seed: int, eval_episodes: int) -> dict:
    """One training run in the surrogate (``compiled_ppo.sb3_run``: any agent behind SB3's
    interface): wall, collection wall, compile, the policy's surrogate return; the agent."""
    wall, collect, _, algo = sb3_run(agent, model, spec, steps, seed)
    ret = float(np.mean(sb3_surrogate_returns(algo, algo.get_env().surrogate, eval_episodes, seed + 1000)))
    return {"wall": wall, "collect": collect, "compile": float(getattr(algo, "compile_seconds", 0.0)), "ret": ret,
            "steps": int(algo.num_timesteps), "algo": algo}


def gradient_step_seconds(algo, repeats: int = 20) -> float:
    """Median seconds per gradient step of one train call (``gradient_steps`` steps on batches of
    ``batch_size``), warm, on the agent's own replay buffer; the agent trains on."""
    if isinstance(algo, jax_sac_agent.JaxSAC):
        call = algo._train
        n = algo.cfg.gradient_steps
    else:
        n = int(algo.gradient_steps)

        def call() -> None:
            algo.train(gradient_steps=n, batch_size=int(algo.batch_size))

    call()
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        call()
        if isinstance(algo, jax_sac_agent.JaxSAC):
            import jax

            jax.block_until_ready(algo.state)
        out.append(time.perf_counter() - t)
    return float(np.median(out)) / n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=8192, help="env steps per training run (whole collections)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--eval-episodes", type=int, default=10)
    ap.add_argument("--cores", type=int, default=None, help="pin this process to its first N cores (both arms)")
    ap.add_argument("--quick", action="store_true", help="a smoke run: 1,024 steps, 1 repeat, 2 eval episodes")
    args = ap.parse_args()
    from sdrl_bench.cli.args import at_least, pin_cores

    at_least(ap, args, 1, "--steps", "--repeats", "--eval-episodes")
    if args.quick:
        args.steps, args.repeats, args.eval_episodes = 1024, 1, 2
    pin_cores(ap, args.cores)  # before jax starts its thread pool

    import torch

    cfg = compose(FIT)
    torch.set_num_threads(int(cfg.torch_threads))  # as the harness trains SB3 (cli.train.prepare)
    pool = jax_compile.size_cpu_pool(int(cfg.jax_threads))  # ditto
    fit = fit_dynamics(build_fit_job(cfg))
    agents = {k: instantiate_key(compose([*FIT, over]).agent, "agent") for k, (over, _) in ARMS.items()}
    runs: dict[str, list[dict]] = {k: [] for k in ARMS}
    for i in range(args.repeats):
        for k in ("a", "b") if i % 2 == 0 else ("b", "a"):
            runs[k].append(run_arm(agents[k], fit.model, fit.spec, args.steps, i, args.eval_episodes))
            print(f"repeat {i} {ARMS[k][1]}: {runs[k][-1]['wall']:.1f} s", flush=True)
    grad = {k: gradient_step_seconds(runs[k][-1]["algo"]) for k in ARMS}

    def med(k: str, key: str) -> float:
        return float(np.median([r[key] for r in runs[k]]))

    rate = {k: med(k, "steps") / med(k, "wall") for k in ARMS}
    import jax

    print(f"\nMountainCar surrogate ({' '.join(FIT)}), the agent group's SAC recipe; median of {args.repeats} "
          f"interleaved runs of {args.steps:,} steps; load average {os.getloadavg()[0]:.1f}; torch "
          f"{torch.get_num_threads()} thread(s); jax {jax.__version__}, {pool} thread(s) in XLA's CPU pool; "
          f"{len(os.sched_getaffinity(0))} core(s) for the process")
    head = (f"{'arm':<24} {'steps/s':>9} {'(b)/(a)':>8} {'collect':>8} {'ms/grad step':>13} {'(a)/(b)':>8} "
            f"{'compile s':>9} {'sur. return':>11}")
    print(head)
    print("-" * len(head))
    for k, (_, label) in ARMS.items():
        b = k == "b"
        speedup = f"{rate[k] / rate['a']:.1f}x" if b else ""
        grad_ratio = f"{grad['a'] / grad[k]:.1f}x" if b else ""
        compile_s = f"{med(k, 'compile'):.2f}" if b else ""
        print(f"{label:<24} {rate[k]:>9,.0f} {speedup:>8} {med(k, 'collect') / med(k, 'wall'):>8.0%} "
              f"{1e3 * grad[k]:>13.2f} {grad_ratio:>8} {compile_s:>9} {med(k, 'ret'):>11.1f}")
    with_compile = med("b", "steps") / med("b", "wall")
    without = med("b", "steps") / (med("b", "wall") - med("b", "compile"))
    print(f"(b) steps/s with its compile {with_compile:,.0f}, without {without:,.0f} ({without / rate['a']:.1f}x (a))")


if __name__ == "__main__":
    main()
