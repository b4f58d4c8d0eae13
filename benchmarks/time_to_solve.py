"""Time to solve: what a surrogate buys in wall-clock time, beside the controls that say why.

Per env and seed, these arms, each trained until its first real evaluation at the env's solved
threshold (``rl.stop_when_solved=true``, 10 real episodes per evaluation):

  (a) the zoo recipe in the real env           (the paper's real arm)
  (b) the fast recipe in real envs             (the control: same algorithm, same env count)
  (c) the zoo recipe in the surrogate          (the paper's surrogate arm)
  (d) the fast recipe in the surrogate
  (e) (d) with the surrogate fitted on the env's heuristic controller's data (no expert needed)
  (d') (d) trained by the compiled PPO (``agent=ppo_jax``, ``rl.jax_agent``): rollout and update in jax
  (b') (b) trained by the same compiled PPO, its rollout in real envs (the control of (d'))
  (e') (e) trained by the compiled PPO
  (t') (d') in the fast pack's terrain variant (``experiment=fast_<env>_terrain``, where the env has
       one: LunarLander's surrogate with the real env's terrain and its touchdown rules)
  (k') the compiled PPO with a recipe of its own, chosen for the compiled loop in the surrogate
       (``experiment=compiled_<env>``, where the env has one; ``studies/compiled_recipe.py --search``)
  (r') (k')'s recipe, compiled PPO, its rollout in real envs (the control of (k'))

(b'), (d') and (e') need the optional ``[jax]`` extra; their compile seconds (``compile_wall_seconds``, inside
the training wall) are printed apart, and the ratios with the compiled arms are given with and without them.
Before the timed runs, each compiled arm runs once, short and untimed, on a seed of its own (``WARM_SEED``):
that warm-up fills JAX's persistent compilation cache (``jax_cache_dir``, under ``<workdir>/mlruns``), so
every timed run loads its programs from the cache instead of the first seed alone paying the cold
compile. A warm-up that found none of its programs in the cache measured the cold compile (a rerun's
warm-up finds them all; a second surrogate arm's finds the update): the latest such is printed apart (a
one-time cost, as the expert's training is), with the judged ratios as they would be had every run of
the surrogate arm compiled cold (the real arms as measured: a conservative comparison); each run records
how many of its programs came from the cache (``compile_cache_hits`` of ``compile_programs``; and
``lowering_cache_hits``: whose lowerings came from the lowering cache, ``rl.jax_compile.compile_program``).
``--no-warm-up`` skips it (the first run of each compiled arm then compiles cold).

For each: training wall and CPU seconds to the first solved evaluation (the surrogate arms'
collection and fit included, every evaluation's time excluded and reported apart), real
transitions used (model data, or real training steps), surrogate steps; medians over the seeds
and the ratios (d)/(a), (d)/(b) (wall) and (d)/(b) (real transitions). An arm that never solves
within its budget counts as infinitely slow. The first evaluation at the threshold stops the
training, a selection on 10 episodes; each run's final evaluation (fresh episodes, seeds nothing
trained or chose on) then judges it. "judged solved" counts the seeds it confirms, and the
"judged" medians and ratios count the others as unsolved (a * marks them in the per-seed table).
``--confirm N`` has every arm confirm a hit on N fresh real episodes before it stops
(``rl.confirm_episodes``); those runs are kept apart from unconfirmed ones.

Every arm is an ordinary ``sdrl-bench -m`` sweep into one MLflow store (the packs
``experiment=paper_<env>`` and ``experiment=fast_<env>``), so a rerun adopts finished jobs and
resumes where a stopped one left off; ``--report-only`` prints the table from the store.

    .venv/bin/python benchmarks/time_to_solve.py --env mountain_car --seeds 0-4 --workdir /tmp/tts

``--transitions N`` fits the surrogate arms on N real transitions in place of the pack's (the
table then reads only surrogate runs of that size; the real arms are shared).

The surrogate arms' expert collector is trained (and timed) once, before any arm, and cached
under ``<workdir>/mlruns/experts``: its one-time cost is printed apart, not added to (c) or (d); (e) shows the surrogate arm
without an expert to train first.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from tabulate import tabulate

from sdrl_bench.cli.args import run_child, script_main
from sdrl_bench.tracking import resolve_uri
from sdrl_bench.tracking.read import find_runs

PACKS = {"mountain_car": {"zoo": "paper_mountain_car", "fast": "fast_mountain_car", "compiled": "compiled_mountain_car"},
         "lunar_lander": {"zoo": "paper_lunar_lander", "fast": "fast_lunar_lander",
                          "terrain": "fast_lunar_lander_terrain"}}
AGENTS = {"mountain_car": {"zoo": "sac", "fast": "ppo_fast", "jax": "ppo_jax"},
          "lunar_lander": {"zoo": "ppo", "fast": "ppo_fast", "jax": "ppo_jax"}}
"""The packs' agent names: how the runs of each recipe are told apart in the store."""
ARMS = {"a": ("zoo", "real"), "b": ("fast", "real"), "c": ("zoo", "surrogate"), "d": ("fast", "surrogate"),
        "e": ("fast", "surrogate"), "B": ("jax", "real"), "D": ("jax", "surrogate"), "E": ("jax", "surrogate"),
        "T": ("jax", "surrogate"), "K": ("jax", "surrogate"), "R": ("jax", "real")}
"""Arm letters; B, D and E are (b'), (d') and (e'): the fast pack with ``agent=ppo_jax``; T is (t'):
(d') in the terrain pack; K and R are (k') and (r'): the compiled pack (its own recipe), in the
surrogate and in real envs."""
PACK_KIND = {"a": "zoo", "c": "zoo", "T": "terrain", "K": "compiled", "R": "compiled"}
"""Each arm's pack (``PACKS``) where it is not the fast one."""
COLLECTOR = {"c": "expert", "d": "expert", "e": "heuristic", "D": "expert", "E": "heuristic", "T": "expert",
             "K": "expert"}
"""The surrogate arms' data: the paper's (the pack's expert, eps = 0.2), or (e) the env's
hand-written controller with the same eps, which needs no trained expert at all."""
LABELS = {"a": "(a) zoo recipe, real env", "b": "(b) fast recipe, real envs (control)",
          "c": "(c) zoo recipe, surrogate (paper)", "d": "(d) fast recipe, surrogate",
          "e": "(e) = (d), heuristic data", "B": "(b') = (b), compiled PPO (control of d')",
          "D": "(d') = (d), compiled PPO", "E": "(e') = (e), compiled PPO",
          "T": "(t') = (d'), terrain pack", "K": "(k') compiled PPO, the compiled loop's recipe",
          "R": "(r') = (k'), real envs (control of k')"}
CONTROL = {"D": "B", "E": "B", "T": "B", "K": "R"}
"""Each compiled surrogate arm's own real control: the same agent and recipe in real envs."""
# learning-curve cadence of the zoo recipes here (the fast packs set their own: one rollout):
# finer than the paper packs' so the first solved point is not rounded up by a coarse grid
ZOO_EVAL_EVERY = {"mountain_car": 1000, "lunar_lander": 16384}
EVAL_EPISODES = 10
WARM_SEED = 1_000_000
"""The compiled arms' warm-up runs' seed: none of a table's seeds (``collect`` reads only runs
stopped when solved; the warm-ups are not)."""


def cli(workdir: Path, overrides: list[str], multirun: bool = True) -> None:
    """One ``sdrl-bench`` command in ``workdir`` (its experts cache and hydra folders live there)."""
    cmd = [sys.executable, "-m", "sdrl_bench.cli.main", *(["-m"] if multirun else []), *overrides]
    print("+ " + " ".join(["sdrl-bench", *(["-m"] if multirun else []), *overrides]), flush=True)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    run_child(cmd, cwd=workdir, env=env, stdout=subprocess.DEVNULL)  # stopped with this script


def arm_overrides(env: str, arm: str, seeds: list[int], uri: str, jobs: int, rerun: bool = False,
                  transitions: int | None = None, confirm: int = 0) -> list[str]:
    """The arm's ``sdrl-bench -m`` overrides; ``transitions``: the surrogate arms' model data
    (``n_transitions``; None: the pack's); ``confirm``: ``rl.confirm_episodes`` (0: none)."""
    recipe, where = ARMS[arm]
    pack = pack_of(env, arm)
    out = [f"experiment={pack}", f"rl.arms=[{where}]", f"seed={','.join(map(str, seeds))}",
           "rl.stop_when_solved=true", "rl.reuse_real_arm=false", f"rl.eval_episodes={EVAL_EPISODES}",
           f"tracking.uri={uri}", f"hydra.launcher.n_jobs={jobs}", *(["resume=false"] if rerun else []),
           *([f"rl.confirm_episodes={confirm}"] if confirm else [])]
    if recipe == "zoo":
        out.append(f"rl.eval_every={ZOO_EVAL_EVERY[env]}")
    if recipe == "jax":
        out.append(f"agent={AGENTS[env]['jax']}")
    if arm in COLLECTOR:
        out.append(f"collector={COLLECTOR[arm]}")
        if transitions is not None:
            out.append(f"n_transitions={transitions}")
    return out


def warm_up(env: str, arm: str, workdir: Path, uri: str, transitions: int | None = None) -> None:
    """One short untimed run of compiled arm ``arm`` (seed ``WARM_SEED``, one rollout, one final
    episode, not stopped when solved): it compiles the arm's programs cold and leaves them in JAX's
    persistent compilation cache for the timed runs. Its own real steps (model data, evaluations)
    are counted in its run, as any run's; nothing of it reaches a timed run but the cache."""
    over = [o for o in arm_overrides(env, arm, [WARM_SEED], uri, 1, True, transitions) if not o.startswith("rl.stop_when_solved")]
    cli(workdir, [*over, "rl.stop_when_solved=false", "rl.surrogate_steps=1", "rl.real_steps=1", "rl.final_episodes=1"])


def pack_of(env: str, arm: str) -> str:
    """The pack an arm runs (the compiled arms run the fast pack, or its terrain variant)."""
    kind = PACK_KIND.get(arm, "fast")
    if kind not in PACKS[env]:
        raise SystemExit(f"--arms {arm}: env {env} has no {kind} pack ({', '.join(PACKS[env].values())})")
    return PACKS[env][kind]


def pretrain_expert(env: str, workdir: Path, uri: str) -> float | None:
    """Train the surrogate arms' expert once (``task=fit`` collects with it); its wall seconds,
    or None when it was cached already."""
    cached = list((workdir / "mlruns" / "experts").glob(f"{env}-*.zip"))
    if cached:
        return None
    t0 = time.perf_counter()
    cli(workdir, [f"experiment={PACKS[env]['zoo']}", "task=fit", f"tracking.uri={uri}", "progress_bar=false"], multirun=False)
    return time.perf_counter() - t0


def pack_transitions(env: str) -> int:
    """The fast pack's model data (``n_transitions``), the surrogate arms' default."""
    from sdrl_bench.cli.build import compose  # noqa: PLC0415  (Hydra's compose: only when a table is made)

    return int(compose([f"experiment={PACKS[env]['fast']}"]).n_transitions)


def collect(uri: str, env: str, transitions: int | None = None, confirm: int = 0,
            warm_ups: bool = False) -> dict[str, dict[int, dict[str, float]]]:
    """{arm letter: {seed: metrics of that arm}} from the finished time-to-solve runs (stopped
    when solved, 10 episodes per evaluation, ``confirm`` confirmation episodes) of ``env``, the
    surrogate arms' among those fitted on ``transitions`` real transitions (None: the pack's);
    the latest run of a seed wins. ``warm_ups``: the compiled arms' warm-up runs that compiled
    cold (none of their programs from the cache) instead."""
    want = str(transitions if transitions is not None else pack_transitions(env))
    out: dict[str, dict[int, dict[str, float]]] = {k: {} for k in ARMS}
    for r in find_runs(uri, "sdrl-bench", "tags.`sdrl.kind` = 'transfer'"):
        p, t = r["params"], r["tags"]
        where = t.get("arms")
        if r["status"] != "FINISHED" or t.get("env") != env:
            continue
        if warm_ups:
            if (t.get("seed") != str(WARM_SEED) or p.get("rl.stop_when_solved") != "False"
                    or r["metrics"].get(f"{where}/compile_cache_hits", 1.0) != 0.0):
                continue
        elif (p.get("rl.stop_when_solved") != "True" or p.get("rl.eval_episodes") != str(EVAL_EPISODES)
              or p.get("rl.confirm_episodes", "0") != str(confirm)):
            continue
        recipe = next((k for k, v in AGENTS[env].items() if v == t.get("agent")), None)
        collector = p.get("collector.name")
        letter = next((k for k, v in ARMS.items() if v == (recipe, where) and COLLECTOR.get(k) == collector
                       and t.get("sdrl.experiment") == PACKS[env].get(PACK_KIND.get(k, "fast"))), None)
        if letter is None or (where == "surrogate" and p.get("n_transitions") != want):
            continue
        m = {k.split("/", 1)[1]: v for k, v in r["metrics"].items() if k.startswith(f"{where}/")}
        m["run_id"] = r["run_id"]
        if "solved_wall_seconds" in m and where == "real":
            m["solved_surrogate_steps"] = 0.0
        if "solved_wall_seconds" in m:  # training alone (the surrogate arms' collection and fit taken out)
            m["solved_train_wall"] = m["solved_wall_seconds"] - m.get("collect_wall_seconds", 0.0) - m.get("fit_wall_seconds", 0.0)
        out[letter][int(t["seed"])] = m
    return out


def judged(m: dict[str, float]) -> bool:
    """Whether a run that met the threshold at an evaluation is also judged solved by its final
    evaluation (``judged_solved``: fresh episodes on seeds that nothing trained or chose on). The
    first evaluation at the threshold stops the training: a selection on a noisy estimate (10
    episodes), which a policy just below the threshold passes by chance."""
    return "solved_wall_seconds" in m and m.get("judged_solved", 0.0) >= 1.0


def arm_row(metrics: dict[int, dict[str, float]], seeds: list[int], cold_compile: float = math.nan) -> dict[str, float]:
    """Medians over the seeds (unsolved: infinite time and transitions); ``*_judged``: the same
    with a seed its final evaluation does not judge solved counted as unsolved;
    ``wall_judged_cold``: with ``cold_compile`` seconds (the warm-up's) in place of each run's
    compile, as if every run had compiled cold."""
    rows = [metrics[s] for s in seeds if s in metrics]
    solved = [m for m in rows if "solved_wall_seconds" in m]

    def wall(m: dict[str, float], need_judge: bool, compile_as: float | None = None) -> float:
        """The run's wall, its own compile replaced by ``compile_as`` seconds (0: taken out) if given."""
        if "solved_wall_seconds" not in m or (need_judge and not judged(m)):
            return math.inf
        own = m.get("compile_wall_seconds", 0.0)
        return m["solved_wall_seconds"] - (0.0 if compile_as is None else own - compile_as)

    def med_wall(need_judge: bool, compile_as: float | None = None) -> float:
        return float(np.median([wall(m, need_judge, compile_as) for m in rows])) if rows else math.nan

    def med(key: str, default: float = math.inf) -> float:
        vals = [m.get(key, default) for m in rows]
        return float(np.median(vals)) if vals else math.nan

    return {
        "seeds": len(rows), "solved": len(solved), "judged": sum(judged(m) for m in rows),
        "wall_judged": med_wall(True), "wall_judged_ex_compile": med_wall(True, compile_as=0.0),
        "wall": med("solved_wall_seconds"), "cpu": med("solved_cpu_seconds"),
        "real": med("solved_real_steps"), "surrogate": med("solved_surrogate_steps") if solved else math.nan,
        "eval_wall": med("curve_eval_wall_seconds", math.nan), "final": med("final_return_mean", math.nan),
        "compile": med("compile_wall_seconds", math.nan), "confirmations": med("confirmations", math.nan),
        "wall_ex_compile": med_wall(False, compile_as=0.0),
        "wall_judged_cold": med_wall(True, compile_as=cold_compile) if math.isfinite(cold_compile) else math.nan,
        "cache_hits": med("compile_cache_hits", math.nan), "programs": med("compile_programs", math.nan),
        "lowered": med("lowering_cache_hits", math.nan),
        "rollout_share": float(np.median([m["solved_rollout_wall_seconds"] / m["solved_train_wall"]
                                          for m in solved if "solved_rollout_wall_seconds" in m and m["solved_train_wall"] > 0]))
        if any("solved_rollout_wall_seconds" in m for m in solved) else math.nan,
    }


def fmt(v: float, spec: str = ".3g") -> str:
    if isinstance(v, float) and math.isinf(v):
        return "not solved"
    if isinstance(v, float) and math.isnan(v):
        return "-"
    return format(v, spec)


def report(uri: str, env: str, seeds: list[int], expert_seconds: float | None, transitions: int | None = None,
           confirm: int = 0) -> None:
    transitions = transitions if transitions is not None else pack_transitions(env)  # composed once
    data = collect(uri, env, transitions, confirm)
    warm = {k: v[WARM_SEED] for k, v in collect(uri, env, transitions, warm_ups=True).items() if v}  # the latest
    confirmed = f", confirmed on {confirm} fresh episodes" if confirm else ""
    print(f"\n{env}: time to a first real evaluation at the solved threshold ({EVAL_EPISODES} episodes{confirmed}), "
          f"seeds {seeds}; the surrogate arms' model data: {transitions:,} real transitions")
    per_seed = []
    for s in seeds:
        cells = []
        for k in ARMS:
            m = data[k].get(s)
            cell = "-" if m is None else fmt(m.get("solved_wall_seconds", math.inf))
            cells.append(cell + ("*" if m is not None and "solved_wall_seconds" in m and not judged(m) else ""))
        per_seed.append([s, *cells])
    print(tabulate(per_seed, headers=["seed", *(f"({k}) wall s" for k in ARMS)], stralign="right"))
    print("*: met the threshold at an evaluation, but its final evaluation (fresh episodes) does not judge it solved")
    rows = {k: arm_row(data[k], seeds, warm[k].get("compile_wall_seconds", math.nan) if k in warm else math.nan) for k in ARMS}
    table = [[LABELS[k], f"{r['solved']}/{r['seeds']}", f"{r['judged']}/{r['seeds']}", fmt(r["wall"]), fmt(r["wall_judged"]),
              fmt(r["compile"]), fmt(r["cpu"]), fmt(r["real"], ",.0f"), fmt(r["surrogate"], ",.0f"),
              fmt(r["rollout_share"], ".0%"), fmt(r["eval_wall"]), fmt(r["final"], ".1f"),
              *([fmt(r["confirmations"])] if confirm else [])]
             for k, r in rows.items() if r["seeds"]]
    print(tabulate(table, headers=["arm", "solved", "judged solved", "median wall s", "median wall s, judged",
                                   "of it compile s", "median CPU s", "real transitions", "surrogate steps",
                                   "rollouts' share of training", "eval wall s (apart)", "final real return",
                                   *(["confirmations played (median)"] if confirm else [])],
                   stralign="right"))

    def ratio(num: str, den: str, key: str, den_key: str | None = None) -> str:
        a, b = rows[num][key], rows[den][den_key or key]
        if not (math.isfinite(a) and math.isfinite(b)) or b == 0:
            return "n/a (unsolved in most seeds)"
        return f"{a / b:.3g}"

    print(f"wall (d)/(a) = {ratio('d', 'a', 'wall')}, (d)/(b) = {ratio('d', 'b', 'wall')}, "
          f"(b)/(a) = {ratio('b', 'a', 'wall')}; real transitions (d)/(b) = {ratio('d', 'b', 'real')}")
    for k in "BDETKR":
        r = rows[k]
        if r["seeds"] and math.isfinite(r["programs"]):
            cold = (f"cold, its warm-up (seed {WARM_SEED}) compiled {fmt(warm[k].get('compile_programs', math.nan))} "
                    f"programs in {fmt(warm[k].get('compile_wall_seconds', math.nan))} s" if k in warm
                    else "no cold compile on record (no warm-up, or its warm-ups found programs in the cache)")
            print(f"compile, {LABELS[k].split(' ')[0]}: the timed runs loaded {fmt(r['cache_hits'])} of {fmt(r['programs'])} "
                  f"programs from the cache (median; their lowerings {fmt(r['lowered'])} from the lowering cache), "
                  f"in {fmt(r['compile'])} s; {cold}")

    def fastest(key: str) -> str | None:
        """The real arm with the shortest judged median by ``key`` (a conservative denominator)."""
        real = [k for k in ARMS if ARMS[k][1] == "real" and rows[k]["seeds"] and math.isfinite(rows[k][key])]
        return min(real, key=lambda k: rows[k][key], default=None)

    for k, name, sb3 in (("D", "(d')", "d"), ("E", "(e')", "e"), ("T", "(t')", "d"), ("K", "(k')", "d")):
        if not rows[k]["seeds"]:
            continue
        ctl, ctl_name = CONTROL[k], LABELS[CONTROL[k]].split(" ")[0]
        for label, key in (("", "wall"), (", judged", "wall_judged")):
            print(f"compiled{label}: wall {name}/(b) = {ratio(k, 'b', key)} (compile excluded: {ratio(k, 'b', key + '_ex_compile')}), "
                  f"{name}/{ctl_name} = {ratio(k, ctl, key)} (compile excluded: {ratio(k, ctl, key + '_ex_compile')}), "
                  f"{name}/({sb3}) = {ratio(k, sb3, key)}")
        parts = [f"{ratio(k, f, key)} (of {LABELS[f].split(' ')[0]}{label})" for key, label in
                 (("wall_judged", ""), ("wall_judged_ex_compile", ", compile excluded")) if (f := fastest(key))]
        if parts:
            print(f"compiled, judged: {name}/the fastest real control = {'; '.join(parts)}")
        if k in warm:
            print(f"compiled, judged, every run of {name} compiling cold (the warm-up's compile): "
                  f"{name}/(b) = {ratio(k, 'b', 'wall_judged_cold', 'wall_judged')}, "
                  f"{name}/{ctl_name} = {ratio(k, ctl, 'wall_judged_cold', 'wall_judged')} (the real arms as measured)")
    if expert_seconds is not None:
        print(f"expert collector trained once before the arms: {expert_seconds:.0f} s wall (not in (c) or (d))")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", choices=sorted(PACKS), required=True)
    ap.add_argument("--seeds", default="0-4", help="e.g. 0-4 or 0,2")
    ap.add_argument("--workdir", default=".", help="where mlruns/ (store, experts cache) lives")
    ap.add_argument("--uri", default=None, help="tracking URI (default: <workdir>/mlruns/mlflow.db)")
    ap.add_argument("--arms", default="abcde", help="which arms to run, e.g. bd; B, D and E: (b'), (d') and (e'), the "
                    "compiled PPO (the [jax] extra); T: (t'), (d') in the env's terrain pack; K and R: (k') and (r'), the env's "
                    "compiled pack (a recipe chosen for the compiled loop) in the surrogate and in real envs")
    ap.add_argument("--jobs", type=int, default=2, help="jobs in parallel within an arm's sweep")
    ap.add_argument("--transitions", type=int, default=None, help="the surrogate arms' model data, real "
                    "transitions (n_transitions; default: the fast pack's)")
    ap.add_argument("--confirm", type=int, default=0, help="rl.confirm_episodes for every arm: an evaluation at the "
                    "threshold stops training only if this many fresh real episodes reach it too (0: none; the "
                    "table reads only runs with the same value)")
    ap.add_argument("--interleave", action="store_true", help="run the arms seed by seed (each seed's arms one after "
                    "the other, one sweep each) instead of arm by arm: a machine whose speed drifts over the run then "
                    "slows every arm alike; use with --jobs 1 for timings")
    ap.add_argument("--no-warm-up", action="store_true", help="skip the compiled arms' warm-up runs (one short run "
                    "each, before the timed ones, that fills JAX's compilation cache): the first timed run of each "
                    "compiled arm then compiles cold")
    ap.add_argument("--report-only", action="store_true")
    ap.add_argument("--rerun", action="store_true", help="run the arms again (resume=false); the table takes "
                    "each seed's latest run (e.g. after a code change the config does not show)")
    args = ap.parse_args()
    from sdrl_bench.cli.args import at_least, folder, jobs, seed_list, store

    seeds = seed_list(ap, args.seeds)
    unknown = sorted(set(args.arms) - set(ARMS))
    if unknown:
        ap.error(f"--arms: {', '.join(map(repr, unknown))} is not an arm ({''.join(ARMS)})")
    for k in dict.fromkeys(args.arms):
        if PACK_KIND.get(k, "fast") not in PACKS[args.env]:
            ap.error(f"--arms: {args.env} has no {PACK_KIND[k]} pack for arm {k} ({', '.join(PACKS[args.env].values())})")
    jobs(ap, args.jobs)
    at_least(ap, args, 1, "--transitions")
    at_least(ap, args, 0, "--confirm")
    workdir = folder(ap, args.workdir, "--workdir")
    if args.uri:
        store(ap, args.uri)
    workdir.mkdir(parents=True, exist_ok=True)
    # a relative sqlite:/// path is the user's, from where they ran this: made absolute, so that
    # the commands (run inside --workdir) and this script's table read and write the same store
    uri = resolve_uri(args.uri) if args.uri else f"sqlite:///{workdir / 'mlruns' / 'mlflow.db'}"
    (workdir / "mlruns").mkdir(exist_ok=True)
    expert = None
    if not args.report_only:
        if any(COLLECTOR.get(k) == "expert" for k in args.arms):
            expert = pretrain_expert(args.env, workdir, uri)
        if not args.no_warm_up:
            # the surrogate arms' first, so their warm-up compiles every program cold; (b') then finds the update cached
            for k in sorted((k for k in args.arms if ARMS[k][0] == "jax"), key=lambda k: ARMS[k][1] == "real"):
                warm_up(args.env, k, workdir, uri, args.transitions)
        order = [(k, [s]) for s in seeds for k in args.arms] if args.interleave else [(k, seeds) for k in args.arms]
        for k, some in order:
            cli(workdir, arm_overrides(args.env, k, some, uri, args.jobs, args.rerun, args.transitions, args.confirm))
    report(uri, args.env, seeds, expert, args.transitions, args.confirm)


if __name__ == "__main__":
    script_main(main, "time_to_solve.py")
