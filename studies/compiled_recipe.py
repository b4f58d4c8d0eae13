"""Which PPO recipe solves fastest in wall time inside the compiled loop? Chosen in the surrogate alone.

In the compiled loop a rollout in the surrogate costs a fraction of an update (MountainCar's fast
pack: 2.2 against 11.6 ms per 4,096 steps), where a real-env rollout costs about as much as an
update. So the recipe tuned for real envs need not be the fastest one in the surrogate: fewer
epochs per rollout make each iteration cheaper and may need more steps.

For a pack (``--experiment``, default ``fast_mountain_car``; its surrogate fitted on the env's
heuristic's data, as ``benchmarks/compiled_ppo.py`` fits it), each candidate recipe (``--candidate
NAME=KEY=VALUE,...``: overrides on top of the pack under ``agent=ppo_jax``; ``pack`` is the pack's
own) trains ``rl.jax_agent.JaxPPO`` in the surrogate on the tuning seeds (``--seeds``, default
100-109: apart from the seeds that time-to-solve runs judge). After every rollout its deterministic
policy plays ``--episodes`` episodes in the surrogate (``jax_ppo.surrogate_evaluator``, the same
resets each time); training stops at the first mean at the env's solved threshold, or at
``--budget`` steps. Then the candidate's compiled iteration (rollout and update, back to back, as
``benchmarks/eval_interlude.py`` runs them) is timed in the same process: median of ``--calls``.

Printed per candidate: the seeds solved, the median steps to the solve (unsolved seeds count as
never), one iteration's milliseconds, and their product, the median training wall to a solve
(evaluations excluded), with its ratio to the pack's. No real step is spent: the surrogate plays
every episode. What it cannot tell: whether the surrogate's stop would pass the real env's judge.

    .venv/bin/python studies/compiled_recipe.py --cores 1 \\
        --candidate epochs2=agent.algo.n_epochs=2 --candidate epochs1=agent.algo.n_epochs=1

Measured (2026-11-27, MountainCar's fast pack, seeds 100-109, two processes, each on a core of
its own): the pack 9/10 solved, median 131,072 steps at 15.0-15.2 ms an iteration; two epochs
10/10, 196,608 steps at 8.3 ms, 0.82x the pack's wall; three epochs 0.86x; two epochs at a
learning rate of 5e-3 0.69x but 7/10 solved; one epoch 1.10x (6/10); minibatches of 2,048 1.40x
(docs/compiled.md).
"""

from __future__ import annotations

import argparse
import os

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--experiment", default="fast_mountain_car")
    ap.add_argument("--candidate", action="append", default=[], metavar="NAME=KEY=VALUE,...",
                    help="a recipe: overrides on the pack (repeatable); the pack's own runs first as 'pack'")
    ap.add_argument("--seeds", default="100-109")
    ap.add_argument("--episodes", type=int, default=10)
    ap.add_argument("--budget", type=int, default=400_000, help="steps before a seed counts as unsolved")
    ap.add_argument("--calls", type=int, default=30, help="timed iterations per candidate")
    ap.add_argument("--cores", type=int, default=None, help="pin the process to its first N cores")
    args = ap.parse_args()
    if args.cores:  # before jax starts its thread pool
        os.sched_setaffinity(0, sorted(os.sched_getaffinity(0))[: args.cores])
    lo, _, hi = args.seeds.partition("-")
    seeds = list(range(int(lo), int(hi or lo) + 1))
    candidates = {"pack": []}
    for c in args.candidate:
        name, _, over = c.partition("=")
        if not name or not over:
            raise SystemExit(f"--candidate {c!r}: expected NAME=KEY=VALUE[,KEY=VALUE...]")
        candidates[name] = over.split(",")

    from stable_baselines3.common.callbacks import BaseCallback

    from sdrl_bench.cli.build import build_fit_job, compose, instantiate_key
    from sdrl_bench.pipeline import fit_dynamics
    from sdrl_bench.rl import jax_agent, jax_ppo
    from sdrl_bench.rl.agents import make_agent
    from sdrl_bench.rl.transfer import surrogate_vec_env
    from sdrl_bench.surrogate.model_env import ModelEnv

    base = [f"experiment={args.experiment}", "agent=ppo_jax", "collector=heuristic"]
    cfg = compose(base)
    jax_agent.size_cpu_pool(int(cfg.jax_threads))
    jax, _, _ = jax_ppo._modules()
    fit = fit_dynamics(build_fit_job(cfg))
    spec, threshold = fit.spec, fit.spec.solved_threshold
    if threshold is None:
        raise SystemExit(f"{args.experiment}: env '{spec.name}' has no solved threshold to stop at")
    menv = ModelEnv(fit.model, spec, seed=0)
    sur = jax_ppo.surrogate(menv)
    low, high = (None, None) if sur.discrete else (sur.action_low, sur.action_high)
    evaluate = jax_ppo.surrogate_evaluator(menv, args.episodes, low, high)
    eval_key = jax.random.key(10**6)

    class StopAtSolve(BaseCallback):
        def __init__(self):
            super().__init__()
            self.solved_at: int | None = None

        def _on_step(self) -> bool:
            if float(np.mean(evaluate(self.model.net, eval_key))) >= threshold:
                self.solved_at = int(self.num_timesteps)
                return False
            return True

    print(f"{args.experiment}: {fit.model.kind} surrogate from {len(fit.data.states):,} transitions; tuning seeds "
          f"{seeds[0]}-{seeds[-1]}; stop at a mean of {threshold} over {args.episodes} surrogate episodes, or "
          f"{args.budget:,} steps", flush=True)
    rows = []
    for name, over in candidates.items():
        agent = instantiate_key(compose([*base, *over]).agent, "agent")
        steps = []
        for seed in seeds:
            model = make_agent(agent, surrogate_vec_env(fit.model, spec, agent.n_envs, seed), seed)
            stop = StopAtSolve()
            model.learn(args.budget, callback=stop)
            steps.append(stop.solved_at)
            print(f"  {name}, seed {seed}: {stop.solved_at if stop.solved_at else 'not solved'}", flush=True)
        if model.rollout_backend != "compiled":
            raise SystemExit(f"{name}: the surrogate's step is not covered by the compiled rollout; nothing to time")
        times = [sum(model.compiled_iteration()) for _ in range(args.calls + 3)]
        it_ms = float(np.median(times[3:])) * 1e3
        med = float(np.median([x if x is not None else np.inf for x in steps]))
        rows.append((name, over, sum(x is not None for x in steps), med, it_ms, med / model.cfg.rollout_size * it_ms))
    pack_wall = rows[0][5]
    head = f"{'recipe':<16} {'overrides':<48} {'solved':>7} {'median steps':>12} {'iteration ms':>12} {'wall ms':>8} {'/ pack':>7}"
    print(head)
    print("-" * len(head))
    for name, over, solved, med, it_ms, wall in rows:
        ratio = wall / pack_wall if np.isfinite(wall) and np.isfinite(pack_wall) else float("nan")
        print(f"{name:<16} {','.join(over) or '-':<48} {solved:>4}/{len(seeds):<2} {med:>12,.0f} {it_ms:>12.2f} "
              f"{wall:>8.0f} {ratio:>6.2f}x")
    print(f"wall ms: median steps to a solve / steps per rollout x one iteration's ms (evaluations excluded); "
          f"iteration: median of {args.calls} back to back; {len(os.sched_getaffinity(0))} core(s)")


if __name__ == "__main__":
    main()
