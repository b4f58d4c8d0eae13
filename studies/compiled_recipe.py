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
policy plays ``--episodes`` episodes in the surrogate (``jax_ppo.surrogate_evaluator``); training stops at the first mean at the env's solved threshold, or at
``--budget`` steps. Then the candidate's compiled iteration (rollout and update, back to back, as
``benchmarks/eval_interlude.py`` runs them) is timed in the same process: median of ``--calls``.

With ``--confirm N`` every evaluation draws fresh resets, and a mean at the threshold stops
training only if N more fresh surrogate episodes reach it too (as ``rl.confirm_episodes`` does
in the real env); without, every evaluation replays the same resets.

Printed per candidate: the seeds solved, the median steps to the solve (unsolved seeds count as
never), one iteration's milliseconds, and their product, the median training wall to a solve
(evaluations excluded), with its ratio to the pack's; and the median of the seeds' training walls
as measured (``learn``'s wall less its compile and the evaluations). No real step is spent: the
surrogate plays every episode. What it cannot tell: whether the surrogate's stop would pass the
real env's judge.

    .venv/bin/python studies/compiled_recipe.py --cores 1 \\
        --candidate epochs2=agent.algo.n_epochs=2 --candidate epochs1=agent.algo.n_epochs=1

``--search`` runs an Optuna study instead (``run_search``: TPE over the rollout's shape, epochs,
minibatches, learning rate, gamma, GAE's lambda, the clip and gSDE's initial log-std; the value a
trial's mean training wall over the tuning seeds, unsolved seeds penalised), stored in
``--storage`` under ``--study``: a rerun of the same command adds trials to it, and several
workers (one per core, ``taskset``) share it. It prints the best trials' overrides, to check as
``--candidate`` on seeds the search did not see.

Measured (2026-11-27, MountainCar's fast pack, seeds 100-109, two processes, each on a core of
its own): the pack 9/10 solved, median 131,072 steps at 15.0-15.2 ms an iteration; two epochs
10/10, 196,608 steps at 8.3 ms, 0.82x the pack's wall; three epochs 0.86x; two epochs at a
learning rate of 5e-3 0.69x but 7/10 solved; one epoch 1.10x (6/10); minibatches of 2,048 1.40x.
The search (169 trials, two workers, ``--confirm 20 --budget 300000``) chose 64 envs x 32 steps,
minibatches of 512, 3 epochs, learning rate 1.04e-2, gamma 0.995, clip 0.1, log-std -0.26
(``experiment=compiled_mountain_car``); on seeds 200-219, beside the pack, it solved 20/20 (the
pack 17/20) at 0.45x the pack's measured training wall (docs/compiled.md).
"""

from __future__ import annotations

import argparse
import os
from typing import Any

import numpy as np


CHOICES = {"n_envs": [64, 128, 256, 512], "n_steps": [8, 16, 32, 64], "n_minibatches": [1, 2, 4, 8],
           "gamma": [0.98, 0.99, 0.995], "gae_lambda": [0.9, 0.95, 0.98], "clip_range": [0.1, 0.2, 0.3]}
"""The search's categorical choices (``suggest``)."""
RANGES = {"n_epochs": (1, 4), "learning_rate": (1e-3, 1.5e-2), "log_std_init": (-2.0, 0.0)}
"""The search's numeric ranges, bounds included (``suggest``; learning rate on a log scale)."""


def pack_params(agent) -> dict | None:
    """The pack's own recipe in the search's terms (``n_minibatches``: n_envs x n_steps /
    batch_size), enqueued as a study's first trial so that every study holds the pack's score
    beside the others; None where the pack lies outside the search space."""
    a = agent.algo
    p = {"n_envs": int(agent.n_envs), "n_steps": int(a.n_steps),
         "n_minibatches": int(agent.n_envs) * int(a.n_steps) // int(a.batch_size), "n_epochs": int(a.n_epochs),
         "learning_rate": float(a.learning_rate), "gamma": float(a.gamma), "gae_lambda": float(a.gae_lambda),
         "clip_range": float(a.get("clip_range", 0.2)), "log_std_init": float(a.get("policy_kwargs", {}).get("log_std_init", 0.0))}
    inside = all(p[k] in v for k, v in CHOICES.items()) and all(lo <= p[k] <= hi for k, (lo, hi) in RANGES.items())
    return p if inside else None


def suggest(trial) -> dict:
    """One recipe from the search space: the rollout's shape, the update's epochs and minibatches,
    the learning rate, the return's discount and GAE's lambda, the clip and gSDE's initial log-std.
    gSDE, reward scaling, the networks and every other setting stay the pack's."""
    c, r = CHOICES, RANGES
    return {"n_envs": trial.suggest_categorical("n_envs", c["n_envs"]),
            "n_steps": trial.suggest_categorical("n_steps", c["n_steps"]),
            "n_minibatches": trial.suggest_categorical("n_minibatches", c["n_minibatches"]),
            "n_epochs": trial.suggest_int("n_epochs", *r["n_epochs"]),
            "learning_rate": trial.suggest_float("learning_rate", *r["learning_rate"], log=True),
            "gamma": trial.suggest_categorical("gamma", c["gamma"]),
            "gae_lambda": trial.suggest_categorical("gae_lambda", c["gae_lambda"]),
            "clip_range": trial.suggest_categorical("clip_range", c["clip_range"]),
            "log_std_init": trial.suggest_float("log_std_init", *r["log_std_init"])}


def overrides_of(p: dict) -> list[str]:
    """A recipe's config overrides (on the pack, under ``agent=ppo_jax``)."""
    batch = p["n_envs"] * p["n_steps"] // p["n_minibatches"]
    return [f"agent.n_envs={p['n_envs']}", f"agent.algo.n_steps={p['n_steps']}", f"agent.algo.batch_size={batch}",
            f"agent.algo.n_epochs={p['n_epochs']}", f"agent.algo.learning_rate={p['learning_rate']:.4g}",
            f"agent.algo.gamma={p['gamma']}", f"agent.algo.gae_lambda={p['gae_lambda']}",
            f"++agent.algo.clip_range={p['clip_range']}", f"agent.algo.policy_kwargs.log_std_init={p['log_std_init']:.3g}"]


class Bench:
    """The study's fixed parts: the pack's surrogate (fitted once, on the env's heuristic's data),
    its compiled evaluators, and ``train``, which trains one recipe on one seed to a solve."""

    def __init__(self, experiment: str, episodes: int, confirm: int, cache_dir: str | None):
        from sdrl_bench.cli.build import build_fit_job, compose
        from sdrl_bench.pipeline import fit_dynamics
        from sdrl_bench.rl import jax_compile, jax_nets, jax_ppo
        from sdrl_bench.surrogate.model_env import ModelEnv

        self.base = [f"experiment={experiment}", "agent=ppo_jax", "collector=heuristic"]
        cfg = compose(self.base)
        self.agent = cfg.agent
        self._agents: dict[tuple[str, ...], Any] = {}  # a recipe's agent config, composed once for all its seeds
        jax_compile.size_cpu_pool(int(cfg.jax_threads))
        if cache_dir:
            jax_compile.use_compilation_cache(cache_dir)
        self.jax, _, _ = jax_nets.modules()
        self.fit = fit_dynamics(build_fit_job(cfg))
        self.spec, self.threshold = self.fit.spec, self.fit.spec.solved_threshold
        if self.threshold is None:
            raise SystemExit(f"{experiment}: env '{self.spec.name}' has no solved threshold to stop at")
        menv = ModelEnv(self.fit.model, self.spec, seed=0)
        sur = jax_ppo.surrogate(menv)
        low, high = (None, None) if sur.discrete else (sur.action_low, sur.action_high)
        self.episodes, self.confirm = episodes, confirm
        self.evaluate = jax_ppo.surrogate_evaluator(menv, episodes, low, high)
        self.confirmer = jax_ppo.surrogate_evaluator(menv, confirm, low, high) if confirm else None

    def train(self, overrides: list[str], seed: int, budget: int):
        """(steps at the solve or None, training seconds, the agent): ``JaxPPO`` in the surrogate
        from ``seed``, stopped at its first solve. After every rollout the deterministic policy
        plays ``episodes`` surrogate episodes; with ``confirm``, each evaluation draws fresh resets
        and a mean at the threshold stops training only if ``confirm`` more fresh episodes reach it
        too (as ``rl.confirm_episodes`` does in the real env); without, every evaluation replays the
        same resets. Training seconds: ``learn``'s wall less its compile and the evaluations."""
        import time

        from stable_baselines3.common.callbacks import BaseCallback

        from sdrl_bench.cli.build import compose, instantiate_key
        from sdrl_bench.rl.agents import make_agent
        from sdrl_bench.rl.transfer import surrogate_vec_env

        bench, jax = self, self.jax
        key = tuple(overrides)
        if key not in self._agents:
            self._agents[key] = instantiate_key(compose([*self.base, *overrides]).agent, "agent")
        agent = self._agents[key]
        model = make_agent(agent, surrogate_vec_env(self.fit.model, self.spec, agent.n_envs, seed), seed)
        base_key = jax.random.key(10**6 + seed)

        class StopAtSolve(BaseCallback):
            def __init__(self):
                super().__init__()
                self.solved_at: int | None = None
                self.evals, self.eval_seconds = 0, 0.0

            def _on_step(self) -> bool:
                t0 = time.perf_counter()
                key = jax.random.fold_in(base_key, self.evals) if bench.confirm else base_key
                self.evals += 1
                hit = float(np.mean(bench.evaluate(self.model.net, key))) >= bench.threshold
                if hit and bench.confirm:
                    more = bench.confirmer(self.model.net, jax.random.fold_in(jax.random.key(2 * 10**6 + seed), self.evals))
                    hit = float(np.mean(more)) >= bench.threshold
                self.eval_seconds += time.perf_counter() - t0
                if hit:
                    self.solved_at = int(self.num_timesteps)
                return not hit

        stop = StopAtSolve()
        t0 = time.perf_counter()
        model.learn(budget, callback=stop)
        wall = time.perf_counter() - t0 - stop.eval_seconds - model.compile_seconds
        if model.rollout_backend != "compiled":
            raise SystemExit("the surrogate's step is not covered by the compiled rollout; this study times the compiled loop")
        return stop.solved_at, wall, model


def iteration_ms(model, calls: int) -> float:
    """One compiled iteration (rollout and update, back to back): the median of ``calls`` after 3."""
    times = [sum(model.compiled_iteration()) for _ in range(calls + 3)]
    return float(np.median(times[3:])) * 1e3


def run_search(args, bench: Bench, seeds: list[int]) -> None:
    """An Optuna study (TPE, resumable in ``--storage``): each trial trains one recipe on every
    tuning seed; its value is the mean training wall over the seeds, an unsolved seed counting as
    ``--penalty`` seconds or twice its wall to the budget, whichever is more (a recipe that fails
    some seeds is slow; twice its own wall alone would favour recipes whose budget runs out fast).
    Pruned (Optuna's median rule) after 4 seeds when its running mean is worse than the median
    trial's there."""
    import optuna

    from sdrl_bench.search.location import resolve_storage
    from sdrl_bench.search.storage import open_storage

    storage = open_storage(resolve_storage(args.storage))
    sampler = optuna.samplers.TPESampler(seed=args.sampler_seed, n_startup_trials=12)
    pruner = optuna.pruners.MedianPruner(n_startup_trials=8, n_warmup_steps=3)
    study = optuna.create_study(study_name=args.study, storage=storage, sampler=sampler, pruner=pruner,
                                direction="minimize", load_if_exists=True)
    pack = pack_params(bench.agent)
    if not study.trials:
        if pack is None:
            print(f"{args.experiment}: its own recipe lies outside the search space; not enqueued", flush=True)
        else:
            study.enqueue_trial(pack)
    for key, value in (("experiment", args.experiment), ("seeds", args.seeds), ("budget", args.budget),
                       ("episodes", args.episodes), ("confirm", args.confirm), ("penalty", args.penalty)):
        if study.user_attrs.get(key, value) != value:
            raise SystemExit(f"--study {args.study}: made with {key}={study.user_attrs[key]!r}, not {value!r}; "
                             f"name a new study")
        study.set_user_attr(key, value)
    study.set_user_attr("real_transitions", len(bench.fit.data.states))

    def objective(trial) -> float:
        p = suggest(trial)
        over = overrides_of(p)
        walls, steps, model = [], [], None
        for i, seed in enumerate(seeds):
            solved_at, wall, model = bench.train(over, seed, args.budget)
            steps.append(solved_at)
            walls.append(wall if solved_at is not None else max(2.0 * wall, args.penalty))
            trial.report(float(np.mean(walls)), i)
            if trial.should_prune():
                trial.set_user_attr("solved", sum(s is not None for s in steps))
                raise optuna.TrialPruned()
        it_ms = iteration_ms(model, args.calls)
        trial.set_user_attr("overrides", ",".join(over))
        trial.set_user_attr("pack", p == pack)
        trial.set_user_attr("solved", sum(s is not None for s in steps))
        trial.set_user_attr("median_steps", float(np.median([s if s is not None else np.inf for s in steps])))
        trial.set_user_attr("median_wall_ms", float(np.median([w if s is not None else np.inf for w, s in zip(walls, steps, strict=True)])) * 1e3)
        trial.set_user_attr("iteration_ms", it_ms)
        print(f"trial {trial.number}: {','.join(over)}: solved {sum(s is not None for s in steps)}/{len(seeds)}, "
              f"mean wall {np.mean(walls) * 1e3:.0f} ms, iteration {it_ms:.2f} ms", flush=True)
        return float(np.mean(walls)) * 1e3

    done = sum(t.state.is_finished() for t in study.trials)
    study.optimize(objective, n_trials=max(0, args.trials - done) if args.total else args.trials)
    print_study(study)


def print_study(study) -> None:
    """The study's best complete trials: value (mean training wall, ms), seeds solved, median
    steps and wall, one iteration's ms, and the overrides (a ``--candidate`` to check on other seeds)."""
    import optuna

    done = sorted((t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE), key=lambda t: t.value)
    pruned = sum(t.state == optuna.trial.TrialState.PRUNED for t in study.trials)
    print(f"study {study.study_name}: {len(done)} complete, {pruned} pruned; tuning seeds {study.user_attrs.get('seeds')}, "
          f"budget {study.user_attrs.get('budget'):,} steps, confirm {study.user_attrs.get('confirm')}")
    pack = next((t for t in done if t.user_attrs.get("pack")), None)
    for t in done[:10] + ([pack] if pack is not None and pack not in done[:10] else []):
        a = t.user_attrs
        print(f"  #{t.number:<4} {t.value:8.0f} ms  solved {a.get('solved')}  median steps {a.get('median_steps', np.nan):>9,.0f}  "
              f"median wall {a.get('median_wall_ms', np.nan):6.0f} ms  iteration {a.get('iteration_ms', np.nan):6.2f} ms"
              f"{'  (the pack)' if a.get('pack') else ''}\n        {a.get('overrides')}")


def run_candidates(args, bench: Bench, seeds: list[int]) -> None:
    candidates = {"pack": []}
    for c in args.candidate:
        name, _, over = c.partition("=")
        if not name or not over:
            raise SystemExit(f"--candidate {c!r}: expected NAME=KEY=VALUE[,KEY=VALUE...]")
        candidates[name] = over.split(",")
    rows = []
    for name, over in candidates.items():
        steps, walls, model = [], [], None
        for seed in seeds:
            solved_at, wall, model = bench.train(over, seed, args.budget)
            steps.append(solved_at)
            walls.append(wall if solved_at is not None else np.inf)
            print(f"  {name}, seed {seed}: {solved_at if solved_at else 'not solved'} ({wall * 1e3:.0f} ms)", flush=True)
        it_ms = iteration_ms(model, args.calls)
        med = float(np.median([x if x is not None else np.inf for x in steps]))
        rows.append((name, over, sum(x is not None for x in steps), med, it_ms, med / model.cfg.rollout_size * it_ms,
                     float(np.median(walls)) * 1e3))
    pack_wall, pack_measured = rows[0][5], rows[0][6]
    head = (f"{'recipe':<16} {'solved':>7} {'median steps':>12} {'iteration ms':>12} {'wall ms':>8} {'/ pack':>7} "
            f"{'measured ms':>11} {'/ pack':>7}")
    print(head)
    print("-" * len(head))

    def ratio(a: float, b: float) -> float:
        return a / b if np.isfinite(a) and np.isfinite(b) else float("nan")

    for name, over, solved, med, it_ms, wall, measured in rows:
        print(f"{name:<16} {solved:>4}/{len(seeds):<2} {med:>12,.0f} {it_ms:>12.2f} {wall:>8.0f} {ratio(wall, pack_wall):>6.2f}x "
              f"{measured:>11.0f} {ratio(measured, pack_measured):>6.2f}x\n    {','.join(over) or '(the pack)'}")
    print(f"wall ms: median steps to a solve / steps per rollout x one iteration's ms (median of {args.calls} back to "
          f"back); measured ms: the median of the seeds' training walls (compile and evaluations excluded; unsolved: "
          f"never); {len(os.sched_getaffinity(0))} core(s)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--experiment", default="fast_mountain_car")
    ap.add_argument("--candidate", action="append", default=[], metavar="NAME=KEY=VALUE,...",
                    help="a recipe: overrides on the pack (repeatable); the pack's own runs first as 'pack'")
    ap.add_argument("--seeds", default="100-109")
    ap.add_argument("--episodes", type=int, default=10)
    ap.add_argument("--confirm", type=int, default=0, help="confirm a hit on this many fresh surrogate episodes "
                    "(and draw fresh resets at every evaluation); 0: none, the same resets every time")
    ap.add_argument("--budget", type=int, default=400_000, help="steps before a seed counts as unsolved")
    ap.add_argument("--calls", type=int, default=30, help="timed iterations per candidate")
    ap.add_argument("--cores", type=int, default=None, help="pin the process to its first N cores")
    ap.add_argument("--search", action="store_true", help="search recipes with Optuna instead of trying --candidate")
    ap.add_argument("--trials", type=int, default=50, help="--search: trials this process runs")
    ap.add_argument("--total", action="store_true", help="--search: --trials counts the study's finished trials "
                    "(a rerun tops the study up to it)")
    ap.add_argument("--study", default="compiled_recipe_mountain_car", help="--search: the study's name")
    ap.add_argument("--storage", default=None, help="--search: Optuna storage (default sqlite:///mlruns/optuna.db)")
    ap.add_argument("--penalty", type=float, default=2.0, help="--search: an unsolved seed's seconds at least")
    ap.add_argument("--sampler-seed", type=int, default=None, help="--search: TPE's seed (workers: one each)")
    ap.add_argument("--cache", default="mlruns/jax_cache", help="JAX's persistent compilation cache ('' for none)")
    args = ap.parse_args()
    from sdrl_bench.cli.args import at_least, pin_cores, seed_list

    seeds = seed_list(ap, args.seeds)
    at_least(ap, args, 1, "--episodes", "--budget", "--calls", "--trials")
    at_least(ap, args, 0, "--confirm")
    pin_cores(ap, args.cores)  # before jax starts its thread pool
    bench = Bench(args.experiment, args.episodes, args.confirm, args.cache or None)
    print(f"{args.experiment}: {bench.fit.model.kind} surrogate from {len(bench.fit.data.states):,} real transitions; "
          f"tuning seeds {seeds[0]}-{seeds[-1]}; stop at a mean of {bench.threshold} over {args.episodes} surrogate "
          f"episodes{f', confirmed on {args.confirm} more' if args.confirm else ''}, or {args.budget:,} steps", flush=True)
    (run_search if args.search else run_candidates)(args, bench, seeds)


if __name__ == "__main__":
    main()
