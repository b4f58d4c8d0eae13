"""Does the compiled PPO (``agent=ppo_jax``) learn as SB3's PPO does, over many seeds? And the
compiled SAC (``agent=sac_jax``) as SB3's SAC (``--env mountain_car_sac``)?

The tests check the pieces against SB3 (the policy, the reward scaling, GAE and one update on SB3's
own rollout and weights). This checks the whole loop: for each seed, SB3's PPO (``rl.agents.make_agent``
around the surrogate vector env, as the harness trains it) and ``rl.jax_agent.JaxPPO`` (its rollouts
compiled in the same surrogate) train ``--steps`` steps with the same recipe (``PACKS``)
in the same SINDy surrogate (fitted once, ``PACKS``), and each trained policy plays
``--episodes`` deterministic episodes in that surrogate (``ModelEnv.step``, numpy, the same reset
draws for every policy). Printed: per seed, both returns; their medians, IQMs and a Mann-Whitney
test (``scipy.stats``).

Resumable: each seed's returns are appended to ``--results`` (JSON lines, default
``mlruns/compiled_parity.jsonl``) as soon as the seed ends, with the host's CPU. A rerun of the same
command (the same ``--env``, ``--steps`` and ``--episodes``) trains only the seeds not yet there and
prints them all; a line cut short by a kill is passed over. A seed's numbers may differ between hosts
(measured: an AVX2-only host against an earlier one), while both arms of one seed always share a
host.

    .venv/bin/python studies/compiled_ppo_parity.py [--env lunar_lander] [--seeds 0-15] [--steps 262144]
    .venv/bin/python studies/compiled_ppo_parity.py --env cartpole_swingup --steps 1048576
    .venv/bin/python studies/compiled_ppo_parity.py --env mountain_car_sac --steps 20000 --jobs 2  # SAC: agent=sac_jax

Measured (LunarLander, seeds 0-15, 262,144 steps, 20 episodes; about 6 min on this 2-core
machine beside another job): SB3 median 230.7, IQM 226.4, lowest 47.9; compiled median 232.1, IQM
228.6, lowest 65.8; Mann-Whitney p = 0.92. Both arms have seeds that failed (SB3: 47.9 in seed 8;
compiled: 65.8 and 74.2 in seeds 10 and 13), and no difference between the two shows.
MountainCar (seeds 0-31, 20 episodes): at 98,304 steps SB3 median 78.9 (IQM 76.5), compiled 65.9
(IQM 43.8), p = 0.09; at 131,072 steps 90.7 (90.4) against 89.9 (85.1), p = 0.34; at 163,840 steps
91.6 against 91.5, p = 0.54; over seeds 0-127 on a 16-core Xeon (``--jobs 15``), at 98,304 steps
78.9 (IQM 65.2) against 82.1 (64.6), p = 0.85, the IQM difference -0.7 [-20.2, 18.5], and at
131,072 steps 90.5 (89.6) against 90.7 (90.0), p = 0.28, 0.4 [-4.1, 6.0] (docs/compiled.md).
SAC (``--env mountain_car_sac --steps 20000 --seeds 0-15 --jobs 2``, about 34 min): SB3 median 93.4, IQM 93.6, lowest 91.7; compiled median 93.7, IQM
93.6, lowest 88.0; p = 0.78.
"""

from __future__ import annotations

import argparse
import functools
import json
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np
import torch
from scipy import stats

from sdrl_bench.cli.build import build_fit_job, compose, instantiate_key
from sdrl_bench.pipeline import fit_dynamics
from sdrl_bench.rl import jax_compile
from sdrl_bench.rl.agents import make_agent
from sdrl_bench.rl.transfer import surrogate_vec_env
from sdrl_bench.surrogate.model_env import ModelEnv
from sdrl_bench.tracking import cpu_tags, machine_label


def surrogate_return(policy, menv: ModelEnv, episodes: int, seed: int) -> float:
    """Mean return of ``policy.predict`` (deterministic) over ``episodes`` episodes side by side in
    ``menv`` (resets drawn with ``seed``)."""
    states = menv.initial_states(episodes, np.random.default_rng(seed))
    ret, live = np.zeros(episodes), np.ones(episodes, bool)
    for _ in range(menv.spec.max_episode_steps):
        actions, _ = policy.predict(menv.observation(states), deterministic=True)
        states, r, term, div = menv.step(states, np.asarray(actions))
        ret += np.where(live, r, 0.0)
        live &= ~term & ~div
        if not live.any():
            break
    return float(ret.mean())


PACKS = {
    "lunar_lander": (["experiment=fast_lunar_lander", "collector=heuristic"], ["experiment=fast_lunar_lander"]),
    "mountain_car": (["experiment=fast_mountain_car", "collector=heuristic"], ["experiment=fast_mountain_car"]),
    "cartpole_swingup": (["env=cartpole_swingup", "collector=random"], ["experiment=dyna_cartpole_swingup"]),
    "mountain_car_sac": (["experiment=quick_mountain_car"], ["experiment=quick_mountain_car"]),
}
"""Per env: the surrogate's fit (the env's heuristic, or for the swing-up 8,000 uniform-random steps
as ``benchmarks/compiled_ppo.py`` fits it) and the recipe (the fast pack's; the swing-up's Dyna pack;
``mountain_car_sac``: the README's main job, its SAC against ``agent=sac_jax``)."""
COMPILED = {"mountain_car_sac": "sac_jax"}
"""The compiled agent each recipe is compared with (``ppo_jax`` where not named)."""


def one_seed(env: str, steps: int, episodes: int, seed: int) -> dict[str, float]:
    """Both agents trained on one seed in the pack's surrogate (fitted here: the same data and
    model in every process), each scored in it: {arm name: surrogate return}."""
    fit_overrides, pack = PACKS[env]
    compiled = COMPILED.get(env, "ppo_jax")
    cfg = compose(fit_overrides)
    torch.set_num_threads(int(cfg.torch_threads))  # as the harness trains SB3 (cli.train.prepare)
    jax_compile.size_cpu_pool(int(cfg.jax_threads))  # and the compiled agents
    fit = fit_dynamics(build_fit_job(cfg))
    menv = ModelEnv(fit.model, fit.spec, seed=0)
    out = {}
    for extra in ([], [f"agent={compiled}"]):
        agent = instantiate_key(compose([*pack, *extra]).agent, "agent")
        model = make_agent(agent, surrogate_vec_env(fit.model, fit.spec, agent.n_envs, seed), seed)
        model.learn(steps)
        out[agent.name if extra else f"SB3 {agent.name}"] = surrogate_return(model, menv, episodes, seed=123)
    return out


def host() -> str:
    """The CPU's model name and vector extensions (``tracking.cpu_tags``, as every run records them):
    seeds repeat bit for bit only on machines alike in these (docs/seeds.md)."""
    return machine_label(cpu_tags())


def stored(path: Path, key: dict) -> dict[int, dict[str, float]]:
    """{seed: returns} of ``path``'s lines made with ``key`` (env, steps, episodes)."""
    done: dict[int, dict[str, float]] = {}
    if path.exists():
        for line in path.read_text().splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:  # the last line of a killed run
                continue
            if isinstance(rec, dict) and all(rec.get(k) == v for k, v in key.items()):
                done[int(rec["seed"])] = rec["returns"]
    return done


def append(path: Path, rec: dict) -> None:
    """One line, on disk before the next seed ends; after a line a killed run cut short, on a
    line of its own (the cut line stays unreadable, this one is read)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a+b") as f:
        cut = f.seek(0, os.SEEK_END) > 0 and (f.seek(-1, os.SEEK_END), f.read(1))[1] != b"\n"
        f.write((("\n" if cut else "") + json.dumps(rec) + "\n").encode())
        f.flush()
        os.fsync(f.fileno())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", default="lunar_lander", choices=list(PACKS))
    ap.add_argument("--seeds", default="0-15")
    ap.add_argument("--steps", type=int, default=262_144)
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--jobs", type=int, default=1, help="seeds trained at once, one process each")
    ap.add_argument("--results", type=Path, default=Path("mlruns/compiled_parity.jsonl"),
                    help="each seed's returns, appended as it ends; a rerun adopts the seeds already there")
    args = ap.parse_args()
    from sdrl_bench.cli.args import at_least, seed_list

    seeds = seed_list(ap, args.seeds)
    at_least(ap, args, 1, "--steps", "--episodes", "--jobs")
    if args.results.is_dir():
        ap.error(f"--results: {args.results} is a folder, not a file")
    key = {"env": args.env, "steps": args.steps, "episodes": args.episodes}
    done = {s: r for s, r in stored(args.results, key).items() if s in seeds}
    todo = [s for s in seeds if s not in done]
    if done:
        print(f"{len(done)} seed(s) from {args.results}; training {len(todo)}", flush=True)
    if todo:
        train = functools.partial(one_seed, args.env, args.steps, args.episodes)
        cpu = host()
        with ProcessPoolExecutor(max_workers=args.jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = {pool.submit(train, seed): seed for seed in todo}
            for fut in as_completed(futures):
                seed, got = futures[fut], fut.result()
                append(args.results, {**key, "seed": seed, "returns": got, "host": cpu})
                done[seed] = got
                print(f"seed {seed} (trained): " + ", ".join(f"{k} {v:.1f}" for k, v in got.items()), flush=True)
    out: dict[str, list[float]] = {}
    for seed in seeds:
        for k, v in done[seed].items():
            out.setdefault(k, []).append(v)
        print(f"seed {seed}: " + ", ".join(f"{k} {v:.1f}" for k, v in done[seed].items()), flush=True)
    for name, v in out.items():
        print(f"{name}: median {np.median(v):.1f}, IQM {stats.trim_mean(v, 0.25):.1f}, min {min(v):.1f}")
    print(f"Mann-Whitney U: p = {stats.mannwhitneyu(*out.values()).pvalue:.2f}")
    (sb3, a), (comp, b) = out.items()
    if len(seeds) > 1:
        print(f"IQM difference, {comp} - {sb3}: {iqm_gap(a, b):.1f}, 95% CI {iqm_gap_ci(a, b)}")


def iqm_gap(a, b, axis: int = -1):
    """IQM(b) - IQM(a) (the interquartile mean: ``scipy.stats.trim_mean`` at 25%)."""
    return stats.trim_mean(b, 0.25, axis=axis) - stats.trim_mean(a, 0.25, axis=axis)


def iqm_gap_ci(a: list[float], b: list[float]) -> str:
    """The 95% percentile-bootstrap interval of ``iqm_gap`` (``scipy.stats.bootstrap``: the arms
    resampled independently, 10,000 resamples, seeded), as ``[lo, hi]``; the arms' values in seed order."""
    ci = stats.bootstrap((np.asarray(a), np.asarray(b)), iqm_gap, n_resamples=10_000, method="percentile",
                         rng=np.random.default_rng(0)).confidence_interval
    return f"[{ci.low:.1f}, {ci.high:.1f}]"


if __name__ == "__main__":
    main()
