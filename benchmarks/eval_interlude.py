"""What an evaluation between two training iterations costs the next one (the compiled PPO).

A time-to-solve run evaluates its policy in the real env after every rollout
(``rl.agents.RealEvalCallback``) and keeps those seconds out of the training time. The iteration
that follows still pays for them: its programs run slower than back to back. This benchmark
measures by how much, and on what the slowdown depends.

For one pack (``--experiment``, default ``fast_mountain_car``; its surrogate fitted on the env's
heuristic's data, as ``benchmarks/compiled_ppo.py`` fits it), ``rl.jax_agent.JaxPPO`` is built
around the surrogate and trained two iterations (its programs compiled). Then, in one process,
the interludes interleaved over ``--rounds`` rounds of ``--calls`` iterations each, every
iteration (the compiled rollout, then the compiled update, each waited for) runs after:

- ``none``: nothing, back to back;
- ``evaluate``: the pack's evaluation, ``rl.eval_episodes`` real episodes
  (``rl.agents.evaluate_real``, the policy's deterministic action on the host), fixed reset seeds;
- ``spin``: Python spinning on the clock for as long as the evaluation's median (no data touched);
- ``spin 1 ms`` and ``spin 5 ms``: the same, shorter;
- ``sleep``: the process asleep for as long as the evaluation's median.

It prints the median rollout, update and iteration time after each, and the iteration's ratio to
``none``.

    .venv/bin/python benchmarks/eval_interlude.py --cores 1

Wall-clock seconds: run it on a quiet machine.
"""

from __future__ import annotations

import argparse
import os
import time
from collections import Counter

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--experiment", default="fast_mountain_car", help="the pack (experiment=...) whose agent and evaluation are timed")
    ap.add_argument("--transitions", type=int, default=None, help="the model data (n_transitions); default: the pack's")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--calls", type=int, default=10, help="iterations per interlude and round")
    ap.add_argument("--cores", type=int, default=None, help="pin the process to its first N cores")
    args = ap.parse_args()
    from sdrl_bench.cli.args import at_least, pin_cores

    at_least(ap, args, 1, "--transitions", "--rounds", "--calls")
    pin_cores(ap, args.cores)  # before jax starts its thread pool

    from xla_opt_level import fit_pack  # this folder's: run as benchmarks/eval_interlude.py

    from sdrl_bench.cli.build import instantiate_key
    from sdrl_bench.rl.agents import evaluate_real, make_agent
    from sdrl_bench.rl.transfer import surrogate_vec_env

    cfg, pool, fit = fit_pack(args.experiment, args.transitions)
    agent = instantiate_key(cfg.agent, "agent")
    model = make_agent(agent, surrogate_vec_env(fit.model, fit.spec, agent.n_envs, 0), 0)
    if not model.compiled_rollout:
        raise SystemExit(f"{args.experiment}: the agent's rollout is not compiled (agent.algo.compiled_rollout)")
    model.learn(2 * model.cfg.rollout_size)  # compiles the programs
    if model.rollout_backend != "compiled":
        raise SystemExit(f"{args.experiment}: the surrogate's step is not covered by the compiled rollout")
    episodes, eval_seed = int(cfg.rl.eval_episodes), 10**6

    def evaluate() -> None:
        evaluate_real(model, fit.spec, episodes, eval_seed, Counter(), "evaluate")

    def spin(seconds: float):
        def run() -> None:
            end = time.perf_counter() + seconds
            while time.perf_counter() < end:
                pass
        return run

    evals = []
    for _ in range(3):
        t = time.perf_counter()
        evaluate()
        evals.append(time.perf_counter() - t)
    eval_s = float(np.median(evals))
    interludes = {"none": None, "evaluate": evaluate, "spin": spin(eval_s), "spin 1 ms": spin(1e-3),
                  "spin 5 ms": spin(5e-3), "sleep": lambda: time.sleep(eval_s)}
    print(f"{args.experiment}: {fit.model.kind} surrogate from {len(fit.data.states):,} transitions; "
          f"{model.cfg.n_envs} envs x {model.cfg.n_steps} steps, batch {model.cfg.batch_size}, {model.cfg.n_epochs} "
          f"epochs; its evaluation ({episodes} real episodes) {eval_s * 1e3:.1f} ms; {pool} thread(s) in XLA's pool, "
          f"{len(os.sched_getaffinity(0))} core(s)", flush=True)

    times: dict[str, list[tuple[float, float]]] = {k: [] for k in interludes}
    for _ in range(args.rounds):
        for name, before in interludes.items():
            for _ in range(args.calls):
                if before is not None:
                    before()
                times[name].append(model.compiled_iteration())
    base = float(np.median(np.sum(times["none"], axis=1)))
    head = f"{'after':<10} {'rollout ms':>10} {'update ms':>10} {'iteration ms':>12} {'/ none':>7}"
    print(head)
    print("-" * len(head))
    for name, got in times.items():
        a = np.asarray(got) * 1e3
        it = float(np.median(a.sum(axis=1)))
        print(f"{name:<10} {np.median(a[:, 0]):>10.2f} {np.median(a[:, 1]):>10.2f} {it:>12.2f} {it / (base * 1e3):>6.2f}x")
    print(f"medians over {args.rounds} rounds x {args.calls} iterations per interlude, the interludes interleaved")


if __name__ == "__main__":
    main()
