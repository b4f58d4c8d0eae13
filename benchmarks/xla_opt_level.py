"""XLA's backend optimization level for the compiled PPO's programs: time, compile and code size.

For one pack (``--experiment``, default ``fast_mountain_car``; its surrogate fitted on the env's
heuristic's data, ``--transitions`` of them or the pack's number, as ``benchmarks/compiled_ppo.py``
fits it), the two programs of a training
iteration that ``rl.jax_agent.JaxPPO`` compiles, its rollout in the surrogate (``jax_ppo.make_rollout``)
and its update (``make_batch`` + ``make_update``), are each compiled at every level of
``--levels`` (XLA's ``xla_backend_optimization_level``: LLVM's -O level; 3 is XLA's default,
``jax_ppo.COMPILER_OPTIONS`` sets the one the harness uses). Per program and level, measured in
one process, the levels interleaved over ``--rounds`` rounds of ``--calls`` calls each:

- the cold compile (seconds; JAX's persistent cache is not used here), the executable's size and
  the time to load it back (``jax.experimental.serialize_executable``: what a cached compile pays);
- the median call time and its ratio to level 3's;
- whether the outputs equal level 3's bit for bit (the largest absolute difference otherwise).

    .venv/bin/python benchmarks/xla_opt_level.py --experiment fast_lunar_lander_terrain --cores 1

Wall-clock seconds: run it on a quiet machine.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np


def fit_pack(experiment: str, transitions: int | None) -> tuple:
    """(config, XLA's pool size, fit) for a pack under ``agent=ppo_jax``: its surrogate fitted on
    the env's heuristic's data (``transitions`` of them, or the pack's number), XLA's CPU pool
    sized by the config's ``jax_threads`` first (also used by ``benchmarks/eval_interlude.py``)."""
    from sdrl_bench.cli.build import build_fit_job, compose
    from sdrl_bench.pipeline import fit_dynamics
    from sdrl_bench.rl import jax_compile

    over = [f"experiment={experiment}", "agent=ppo_jax", "collector=heuristic"]
    cfg = compose([*over, *([f"n_transitions={transitions}"] if transitions else [])])
    pool = jax_compile.size_cpu_pool(int(cfg.jax_threads))
    return cfg, pool, fit_dynamics(build_fit_job(cfg))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--experiment", default="fast_mountain_car", help="the pack (experiment=...) whose agent and surrogate are compiled")
    ap.add_argument("--transitions", type=int, default=None, help="the model data (n_transitions); default: the pack's")
    ap.add_argument("--levels", default="3,2,1", help="comma-separated levels (3: XLA's default)")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--calls", type=int, default=15)
    ap.add_argument("--cores", type=int, default=None, help="pin the process to its first N cores")
    args = ap.parse_args()
    from sdrl_bench.cli.args import at_least, pin_cores

    at_least(ap, args, 1, "--transitions", "--rounds", "--calls")
    parts = [x.strip() for x in args.levels.split(",")]
    if not all(x in ("0", "1", "2", "3") for x in parts):
        ap.error(f"--levels: comma-separated levels 0 to 3 are required, got {args.levels!r}")
    levels = list(dict.fromkeys(int(x) for x in parts))
    if 3 not in levels:
        levels = [3, *levels]
    pin_cores(ap, args.cores)  # before jax starts its thread pool

    from sdrl_bench.cli.build import instantiate_key
    from sdrl_bench.rl import jax_nets
    from sdrl_bench.rl import jax_ppo
    from sdrl_bench.surrogate.model_env import ModelEnv

    cfg, pool, fit = fit_pack(args.experiment, args.transitions)
    jax, _, _ = jax_nets.modules()
    from jax.experimental import serialize_executable

    pcfg = jax_ppo.PPOConfig.from_agent(instantiate_key(cfg.agent, "agent"))
    sur = jax_ppo.surrogate(ModelEnv(fit.model, fit.spec, seed=0))
    net = jax_nets.init_net(jax.random.key(0), sur.n_obs, sur.n_act, pcfg, sur.discrete)
    env, obs = jax_ppo.init_env(sur, jax.random.key(1), pcfg.n_envs, pcfg, sur.params)
    rollout = jax.jit(jax_ppo.make_rollout(sur, pcfg))
    roll_args = (net, env, obs, jax.random.key(2), sur.params)
    _, _, traj, last = rollout(*roll_args)
    update = jax_ppo.make_update(pcfg)
    opt = jax_ppo.optimizer(pcfg).init(net)
    upd_args = (net, opt, traj, last, jax.random.key(3))
    programs = {"rollout": (rollout.lower(*roll_args), roll_args),
                "update": (jax.jit(lambda n, o, tr, lv, k: update(n, o, jax_ppo.make_batch(pcfg, tr, lv), k)).lower(*upd_args), upd_args)}
    print(f"{args.experiment}: {fit.model.kind} surrogate from {len(fit.data.states):,} transitions; {pcfg.n_envs} envs x "
          f"{pcfg.n_steps} steps, batch {pcfg.batch_size}, {pcfg.n_epochs} epochs; jax {jax.__version__}, {pool} thread(s) "
          f"in XLA's pool, {len(os.sched_getaffinity(0))} core(s)", flush=True)

    exes, info = {}, {}
    for name, (lowered, call_args) in programs.items():
        for lev in levels:
            t = time.perf_counter()
            exe = lowered.compile(compiler_options={"xla_backend_optimization_level": lev})
            cold = time.perf_counter() - t
            blob, in_tree, out_tree = serialize_executable.serialize(exe)
            loads = []
            for _ in range(3):
                t = time.perf_counter()
                serialize_executable.deserialize_and_load(blob, in_tree, out_tree)
                loads.append(time.perf_counter() - t)
            exes[name, lev] = exe
            info[name, lev] = {"cold": cold, "bytes": len(blob), "load": float(np.median(loads)), "times": []}
            jax.block_until_ready(exe(*call_args))  # warm

    for _ in range(args.rounds):  # interleaved: load on the machine slows every level alike
        for (name, lev), exe in exes.items():
            call_args = programs[name][1]
            ts = []
            for _ in range(args.calls):
                t = time.perf_counter()
                jax.block_until_ready(exe(*call_args))
                ts.append(time.perf_counter() - t)
            info[name, lev]["times"].append(float(np.median(ts)))

    head = f"{'program':<8} {'level':>5} {'cold compile s':>14} {'code MB':>8} {'load ms':>8} {'call ms':>8} {'vs O3':>6}  outputs vs O3"
    print(head)
    print("-" * len(head))
    for name, (_, call_args) in programs.items():
        ref = jax.tree.leaves(exes[name, 3](*call_args))
        ref_ms = float(np.median(info[name, 3]["times"])) * 1e3
        for lev in levels:
            x = info[name, lev]
            ms = float(np.median(x["times"])) * 1e3
            out = jax.tree.leaves(exes[name, lev](*call_args))
            diff = max(float(np.max(np.abs(np.asarray(a, dtype=float) - np.asarray(b, dtype=float)))) for a, b in zip(ref, out, strict=True))
            same = "the same bits" if all(np.array_equal(np.asarray(a), np.asarray(b)) for a, b in zip(ref, out, strict=True)) else f"max abs diff {diff:.3g}"
            print(f"{name:<8} {lev:>5} {x['cold']:>14.2f} {x['bytes'] / 1e6:>8.2f} {x['load'] * 1e3:>8.1f} {ms:>8.2f} "
                  f"{ms / ref_ms:>5.2f}x  {same}")
    print(f"call ms: median over {args.rounds} interleaved rounds of each round's median of {args.calls} calls; "
          f"load ms: median of 3 loads of the serialized executable; load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
