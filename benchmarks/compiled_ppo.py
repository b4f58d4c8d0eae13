"""PPO compiled with the surrogate's step against stable-baselines3's PPO in the same surrogate.

On an env's SINDy surrogate (``--surrogate nn`` or ``pe``: the NN models, fitted on the same data)
(``--env``; default the cartpole swing-up, fitted from 8,000
uniform-random real steps as ``sdrl-bench env=cartpole_swingup collector=random`` fits it; MountainCar
and LunarLander from their fast packs' data, the env's heuristic in place of the pack's expert),
measured side by side in one run:

  (a) SB3's PPO training in the surrogate vector env, as the harness builds both
      (``rl.transfer.surrogate_vec_env``, ``rl.agents.make_agent``: the recipe's VecNormalize
      included), numpy surrogate step and torch networks;
  (b) the compiled PPO (``rl.jax_ppo``): rollout in the jax surrogate step and update in one
      ``jax.jit`` + ``lax.scan`` (its reward scaling is VecNormalize's, in jax);

each with the same settings (gSDE and reward scaling included where a recipe sets them), for the
env's recipes (``ENVS``): on the swing-up its Dyna pack's (``experiment=dyna_cartpole_swingup``: 64
envs x 256 steps, batch 1024, 4 epochs, gamma 0.995) and ``agent=ppo_fast`` (128 envs x 32 steps,
batch 1024, 4 epochs, gamma 0.99); on MountainCar and LunarLander their fast packs
(``experiment=fast_<env>``), and on MountainCar also its compiled pack (``experiment=compiled_mountain_car``:
64 envs x 32 steps, batch 512, 3 epochs, gamma 0.995; ``--recipes "fast pack"`` for the fast pack
alone). For a fixed number of env
steps (``--steps``, rounded up to whole rollouts as SB3's ``learn`` does), repeated ``--repeats``
times: median steps per second of training (rollout + update), the ratio (b)/(a), the share of
the time in rollouts, each update's seconds and its achieved GFLOP/s (the FLOPs of the actor's and
critic's forward and backward passes over every minibatch of every epoch, counted analytically;
elementwise work not counted), and (b)'s compile time: its first call (trace, compile, run) beside
a later call with another seed (run only). Beside them: float32 and float64 matmul peaks (jax,
1024 x 1024) measured in the same run, and the surrogate return of each trained policy
(deterministic, ``--eval-episodes`` episodes in the surrogate) as a check that both learn alike.

(b)'s rollout and update are also compiled and timed apart (for the share and the update's
GFLOP/s); (a)'s are split by SB3's rollout callbacks. Wall-clock seconds: run it on a quiet
machine (other load slows both arms, not necessarily alike).

    .venv/bin/python benchmarks/compiled_ppo.py [--env mountain_car] [--steps 131072] [--repeats 5] [--quick]

``--jax-threads 0`` gives XLA its default pool (one thread per core) in place of the harness's
``jax_threads``: the pool is made once per process, so compare two runs.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

from sdrl_bench.cli.build import build_fit_job, compose, instantiate_key
from sdrl_bench.pipeline import fit_dynamics
from sdrl_bench.rl import jax_compile, jax_nets, jax_ppo
from sdrl_bench.rl.agents import make_agent
from sdrl_bench.rl.transfer import surrogate_vec_env
from sdrl_bench.surrogate.model_env import ModelEnv

ENVS = {
    "cartpole_swingup": {"fit": ["env=cartpole_swingup", "collector=random"],
                         "recipes": {"dyna pack": ["experiment=dyna_cartpole_swingup"],
                                     "ppo_fast": ["env=cartpole_swingup", "agent=ppo_fast"]}},
    "mountain_car": {"fit": ["experiment=fast_mountain_car", "collector=heuristic"],
                     "recipes": {"fast pack": ["experiment=fast_mountain_car"],
                                 "compiled pack": ["experiment=compiled_mountain_car", "agent=ppo_fast"]}},
    "lunar_lander": {"fit": ["experiment=fast_lunar_lander", "collector=heuristic"],
                     "recipes": {"fast pack": ["experiment=fast_lunar_lander"]}},
}
"""Per env: the surrogate's fit (its pack's model data, from the env's heuristic where the pack
trains an expert first) and the recipes, as config overrides (their ``agent`` node is the SB3
recipe: the compiled pack's own recipe under ``agent=ppo_fast``)."""


class RolloutClock(BaseCallback):
    """Wall seconds SB3 spends collecting rollouts (the rest of ``learn`` is its updates)."""

    def __init__(self):
        super().__init__()
        self.rollout_seconds, self.rollouts, self._t0 = 0.0, 0, 0.0

    def _on_rollout_start(self) -> None:
        self._t0 = time.perf_counter()

    def _on_rollout_end(self) -> None:
        self.rollout_seconds += time.perf_counter() - self._t0
        self.rollouts += 1

    def _on_step(self) -> bool:
        return True


def update_flops(cfg: jax_ppo.PPOConfig, n_obs: int, n_act: int) -> float:
    """FLOPs of one update's matrix products: for every sample of every epoch, each linear layer
    (in x out) of the actor and critic costs 2 in out forward, 2 in out for its weights' gradient
    and 2 in out for its input's gradient (not for the first layer)."""
    per_sample = 0
    for layers in jax_nets.mlp_layers(n_obs, n_act).values():
        for i, (n_in, n_out) in enumerate(layers):
            per_sample += 2 * n_in * n_out * (2 if i == 0 else 3)
    return float(per_sample) * cfg.rollout_size * cfg.n_epochs


def matmul_peak(dtype: str, n: int = 1024, repeats: int = 5) -> float:
    """GFLOP/s of a jitted n x n matmul in ``dtype`` (best of ``repeats`` after a warm-up)."""
    import jax
    import jax.numpy as jnp

    a = jax.random.normal(jax.random.key(0), (n, n), dtype=getattr(jnp, dtype))
    f = jax.jit(lambda x: x @ x)
    f(a).block_until_ready()
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        f(a).block_until_ready()
        best = min(best, time.perf_counter() - t)
    return 2 * n**3 / best / 1e9


def layer_peak(batch: int = 1024, width: int = 64, reps: int = 200) -> float:
    """GFLOP/s of the networks' own shape: ``reps`` chained (batch x width) @ (width x width)
    matmuls, each followed by tanh, in one jitted loop (best of 5): what XLA reaches on PPO's
    layers, well below the large-matmul peak."""
    import jax
    import jax.numpy as jnp

    a = jax.random.normal(jax.random.key(0), (batch, width), jnp.float32)
    w = jax.random.normal(jax.random.key(1), (width, width), jnp.float32) / jnp.float32(np.sqrt(width))
    f = jax.jit(lambda a, w: jax.lax.fori_loop(0, reps, lambda i, x: jnp.tanh(x @ w), a))
    f(a, w).block_until_ready()
    best = np.inf
    for _ in range(5):
        t = time.perf_counter()
        f(a, w).block_until_ready()
        best = min(best, time.perf_counter() - t)
    return 2 * batch * width * width * reps / best / 1e9


def timed(fn, *args, repeats: int = 3) -> float:
    """Median wall seconds of ``fn(*args)`` (jax results waited for), after one warm-up call."""
    import jax

    jax.block_until_ready(fn(*args))
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        out.append(time.perf_counter() - t)
    return float(np.median(out))


def sb3_run(agent, model, spec, steps: int, seed: int):
    """One SB3 training run in the surrogate vector env: (wall s, rollout wall s, rollouts, SB3 model)."""
    venv = surrogate_vec_env(model, spec, agent.n_envs, seed)
    algo = make_agent(agent, venv, seed)
    clock = RolloutClock()
    t = time.perf_counter()
    algo.learn(total_timesteps=int(steps), callback=clock)
    wall = time.perf_counter() - t
    venv.close()
    return wall, clock.rollout_seconds, clock.rollouts, algo


def sb3_surrogate_returns(algo, menv: ModelEnv, n: int, seed: int) -> np.ndarray:
    """Deterministic episodes of an SB3 policy in the surrogate, side by side (numpy step)."""
    states = menv.initial_states(n, np.random.default_rng(seed))
    ret, live = np.zeros(n), np.ones(n, bool)
    for _ in range(menv.spec.max_episode_steps):
        actions, _ = algo.predict(menv.observation(states), deterministic=True)
        states, r, term, div = menv.step(states, np.asarray(actions, dtype=float))
        ret += np.where(live, r, 0.0)
        live &= ~term & ~div
    return ret


def compiled_parts(menv: ModelEnv, cfg: jax_ppo.PPOConfig, repeats: int) -> tuple[float, float]:
    """(rollout s, update s) of one iteration of the compiled PPO, each jitted and timed alone."""
    import jax

    sur = jax_ppo.surrogate(menv)
    net = jax_nets.init_net(jax.random.key(0), sur.n_obs, sur.n_act, cfg, sur.discrete)
    env, obs = jax_ppo.init_env(sur, jax.random.key(1), cfg.n_envs, cfg)
    opts = jax_ppo.COMPILER_OPTIONS  # as (b) and the harness compile them
    rollout = jax.jit(jax_ppo.make_rollout(sur, cfg), compiler_options=opts)
    _, _, traj, last = rollout(net, env, obs, jax.random.key(2))
    batch = jax.jit(lambda tr, lv: jax_ppo.make_batch(cfg, tr, lv))(traj, last)
    update = jax.jit(jax_ppo.make_update(cfg), compiler_options=opts)
    opt = jax_ppo.optimizer(cfg).init(net)
    return (timed(lambda: rollout(net, env, obs, jax.random.key(3))[2].reward, repeats=repeats),
            timed(lambda: update(net, opt, batch, jax.random.key(4))[0], repeats=repeats))


def run_recipe(env: str, name: str, model, spec, steps: int, repeats: int, eval_episodes: int) -> dict:
    import jax

    agent = instantiate_key(compose(ENVS[env]["recipes"][name]).agent, "agent")
    cfg = jax_ppo.PPOConfig.from_agent(agent)
    menv = ModelEnv(model, spec, seed=0)
    iters = jax_ppo.n_iterations(cfg, steps)
    n_steps = iters * cfg.rollout_size
    flops = update_flops(cfg, len(spec.obs_names), spec.n_discrete_actions or spec.raw_action_width)
    print(f"\n{name}: {cfg}\n  {n_steps:,} steps = {iters} iterations of {cfg.rollout_size:,}; "
          f"update {flops / 1e9:.2f} GFLOP (matmuls, forward + backward)", flush=True)

    train_fn = jax_ppo.make_train(menv, cfg, steps)
    t = time.perf_counter()
    net, _ = train_fn(jax.random.key(0))
    jax.block_until_ready(net)
    first = time.perf_counter() - t
    print(f"  (b) first call {first:.2f} s (trace + compile + run)", flush=True)

    sb3, jx = [], []
    algo = None
    for r in range(repeats):  # interleaved: load on the machine slows both alike
        wall, roll, n_roll, algo = sb3_run(agent, model, spec, steps, seed=r)
        sb3.append((wall, roll, n_roll))
        t = time.perf_counter()
        net, _ = train_fn(jax.random.key(r + 1))
        jax.block_until_ready(net)
        jx.append(time.perf_counter() - t)
        print(f"  repeat {r}: (a) {wall:.2f} s ({algo.num_timesteps:,} steps), (b) {jx[-1]:.2f} s", flush=True)
    roll_s, upd_s = compiled_parts(menv, cfg, repeats=max(repeats, 3))

    a_wall = float(np.median([w for w, _, _ in sb3]))
    a_roll = float(np.median([ro / w for w, ro, _ in sb3]))
    a_upd = float(np.median([(w - ro) / max(n, 1) for w, ro, n in sb3]))
    b_wall = float(np.median(jx))
    a_ret = sb3_surrogate_returns(algo, menv, eval_episodes, seed=123)
    b_ret = jax_ppo.evaluate_surrogate(menv, jax_ppo.as_params(net, menv), eval_episodes, seed=123)
    return {"name": name, "steps": n_steps, "flops": flops, "first": first, "later": b_wall, "rollout_size": cfg.rollout_size,
            "roll_s": roll_s,
            "a": {"rate": n_steps / a_wall, "roll": a_roll, "upd": a_upd, "ret": float(np.mean(a_ret))},
            "b": {"rate": n_steps / b_wall, "roll": roll_s / (roll_s + upd_s), "upd": upd_s, "ret": float(np.mean(b_ret))},
            "pairs": [w / b for (w, _, _), b in zip(sb3, jx, strict=True)]}


MIN_CI_PAIRS = 5
"""The fewest interleaved pairs ``paired_ratio`` gives a CI for (also ``--repeats``' default)."""


def paired_ratio(pairs: list[float]) -> str:
    """(b)/(a) per interleaved pair (the same steps in both: (a)'s wall over (b)'s), their median
    and a 95% percentile bootstrap CI of it (``scipy.stats.bootstrap``): how far the ratio of the
    medians in the table moves with the machine's state during one run. Under ``MIN_CI_PAIRS``
    pairs no CI is printed: a percentile bootstrap of the median of three or four values is their
    range (or nearly), not an interval to read."""
    from scipy import stats

    text = f"{' '.join(f'{p:.1f}' for p in pairs)}; median {np.median(pairs):.1f}x"
    if len(pairs) < MIN_CI_PAIRS:
        return f"{text} (no CI under {MIN_CI_PAIRS} pairs: --repeats {MIN_CI_PAIRS} or more)"
    if len(set(pairs)) < 2:
        return text
    ci = stats.bootstrap((np.asarray(pairs),), np.median, n_resamples=2000, method="percentile",
                         random_state=np.random.default_rng(0)).confidence_interval
    return f"{text}, 95% CI [{ci.low:.1f}, {ci.high:.1f}]"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=2**17, help="env steps per training run (rounded up to whole rollouts)")
    ap.add_argument("--repeats", type=int, default=MIN_CI_PAIRS, help="interleaved pairs of runs (the pairs' CI needs %(default)s or more)")
    ap.add_argument("--eval-episodes", type=int, default=10)
    ap.add_argument("--env", default="cartpole_swingup", choices=list(ENVS))
    ap.add_argument("--recipes", nargs="+", default=None, help="default: all of the env's (ENVS)")
    ap.add_argument("--cores", type=int, default=None, help="pin this process to its first N cores (both arms; "
                    "e.g. 1 for a per-core comparison); default: all it may use")
    ap.add_argument("--jax-threads", type=int, default=None, help="threads in XLA's CPU pool (default: the config's "
                    "jax_threads, as the harness trains; 0: XLA's default, one per core)")
    ap.add_argument("--surrogate", default="sindy", choices=["sindy", "nn", "pe"],
                    help="the surrogate model (the config group surrogate=...), fitted on the same data")
    ap.add_argument("--quick", action="store_true", help="a smoke run: 2^14 steps, 1 repeat, 2 eval episodes")
    args = ap.parse_args()
    from sdrl_bench.cli.args import at_least, pin_cores

    at_least(ap, args, 1, "--steps", "--repeats", "--eval-episodes")
    at_least(ap, args, 0, "--jax-threads")
    if args.quick:
        args.steps, args.repeats, args.eval_episodes = 2**14, 1, 2
    unknown = sorted(set(args.recipes or ()) - set(ENVS[args.env]["recipes"]))
    if unknown:
        ap.error(f"--recipes: {', '.join(map(repr, unknown))} is not one of {args.env}'s recipes "
                 f"({', '.join(map(repr, ENVS[args.env]['recipes']))})")
    pin_cores(ap, args.cores)  # before jax starts its thread pool

    import torch

    from sdrl_bench.models.jax_eval import jax_modules

    jax, _ = jax_modules("benchmarks/compiled_ppo.py")  # float64 on before any jax array (the surrogate's step)
    env = ENVS[args.env]
    recipes = args.recipes or list(env["recipes"])
    fit_overrides = [*env["fit"], *([] if args.surrogate == "sindy" else [f"surrogate={args.surrogate}"])]
    cfg = compose(fit_overrides)
    torch.set_num_threads(int(cfg.torch_threads))  # as the harness trains SB3 (cli.train.prepare)
    pool = jax_compile.size_cpu_pool(int(cfg.jax_threads) if args.jax_threads is None else args.jax_threads)  # ditto
    t = time.perf_counter()
    fit = fit_dynamics(build_fit_job(cfg))
    print(f"fit: {args.env} {fit.model.kind} model from {len(fit.data.states):,} transitions ({' '.join(fit_overrides)}) "
          f"in {time.perf_counter() - t:.1f} s")
    peaks = {d: matmul_peak(d) for d in ("float32", "float64")}
    peaks["layer"] = layer_peak()
    rows = [run_recipe(args.env, name, fit.model, fit.spec, args.steps, args.repeats, args.eval_episodes)
            for name in recipes]

    load = os.getloadavg()
    print(f"\nmedian of {args.repeats} interleaved runs; load average {load[0]:.1f} (a busy machine makes these noisy); "
          f"(a): torch {torch.get_num_threads()} thread(s) (the harness's torch_threads); (b): jax {jax.__version__} on "
          f"{jax.devices()[0].platform}, {pool} thread(s) in XLA's CPU pool (--jax-threads, else the harness's jax_threads), "
          f"{len(os.sched_getaffinity(0))} core(s) for the process")
    print(f"matmul peak (jax, 1024 x 1024): float32 {peaks['float32']:.1f} GFLOP/s, float64 {peaks['float64']:.1f} GFLOP/s; "
          f"the layers' shape (1024 x 64 @ 64 x 64 + tanh, chained): {peaks['layer']:.1f} GFLOP/s")
    head = (f"{'recipe':<10} {'arm':<26} {'steps':>8} {'steps/s':>10} {'(b)/(a)':>8} {'rollout':>8} "
            f"{'update s':>9} {'upd GFLOP/s':>11} {'% f32 peak':>10} {'sur. return':>11}")
    print(head)
    print("-" * len(head))
    for r in rows:
        for arm, label in (("a", "(a) SB3 PPO, numpy surr."), ("b", "(b) compiled PPO (jax)")):
            x = r[arm]
            gflops = r["flops"] / x["upd"] / 1e9
            ratio = f"{r['b']['rate'] / r['a']['rate']:.1f}x" if arm == "b" else ""
            print(f"{r['name']:<10} {label:<26} {r['steps']:>8,} {x['rate']:>10,.0f} {ratio:>8} {x['roll']:>8.0%} "
                  f"{x['upd']:>9.3f} {gflops:>11.2f} {gflops / peaks['float32']:>10.1%} {x['ret']:>11.1f}")
    print("\n(b)/(a) per interleaved pair: " + "; ".join(f"{r['name']}: {paired_ratio(r['pairs'])}" for r in rows))
    print("(b) compile: " + "; ".join(f"{r['name']}: first call {r['first']:.1f} s, later call {r['later']:.2f} s, "
                                        f"compile ~ {r['first'] - r['later']:.1f} s" for r in rows))
    print("(b) with its compile (first call): " + "; ".join(
        f"{r['name']}: {r['steps'] / r['first']:,.0f} steps/s, {r['steps'] / r['first'] / r['a']['rate']:.1f}x (a)" for r in rows))
    def at_rate(r: dict, gflops: float) -> float:
        """(b)'s steps/s were its update's matmul FLOPs done at ``gflops`` and nothing else, plus its rollout."""
        return r["rollout_size"] / (r["flops"] / (gflops * 1e9) + r["roll_s"])

    print("were the update at the layers' shape rate (its matmul FLOPs / that rate, plus (b)'s rollout; a forward-only "
          "micro-benchmark, not a bound: the update's products can run faster): " + "; ".join(
        f"{r['name']}: {at_rate(r, peaks['layer']):,.0f} steps/s, {at_rate(r, peaks['layer']) / r['a']['rate']:.1f}x (a)"
        for r in rows))
    print("ceiling of (b) on this machine (the update's matmul FLOPs at the float32 matmul peak, every other op of the "
          "update free, plus (b)'s rollout; an estimate from this run's peak and rollout, each measured with its noise): "
          + "; ".join(
        f"{r['name']}: {at_rate(r, peaks['float32']):,.0f} steps/s, {at_rate(r, peaks['float32']) / r['a']['rate']:.1f}x "
        f"(a); (b) reaches {r['b']['rate'] / at_rate(r, peaks['float32']):.0%} of it" for r in rows))
    print("rollout: share of training wall time in rollouts ((b): its rollout and update jitted and timed apart); "
          "update s: one iteration's update; sur. return: mean deterministic return in the surrogate after training")


if __name__ == "__main__":
    main()
