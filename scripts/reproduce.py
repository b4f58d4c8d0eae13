"""Rebuild the reproduction store and the reference report from nothing, in one command.

    .venv/bin/python scripts/reproduce.py [--workdir runs/reproduction] [--jobs 2] [--seeds 0-4]
                                          [--out reports] [--name reproduction]

Every stage is an ordinary ``sdrl-bench -m`` sweep into one MLflow store under ``--workdir``
(``<workdir>/mlruns/mlflow.db``; the experts cache and Hydra's folders live there too), run
with ``--jobs`` processes at a time, one thread each. The stages, in order:

  experts      the paper's collectors, trained once with their zoo settings (SAC on MountainCar,
               50k steps; PPO on LunarLander, 1M steps), both at once; then LunarLander's touchdown
               test set (studies/touchdown_set.py), which every LunarLander fit is scored on.
               The warm-up fits that train the experts go to experiment ``rebuild-setup``, not
               to the report's.
  fits         SINDy per library (polynomial, poly_trig, rational; LunarLander also its
               per-equation flight law), the NN surrogate, and Pendulum (random data), on the
               experts' data, every seed: one-step and 50-step fidelity, fit cost, parameters.
  transfer     the paper packs with SINDy, then with the NN surrogate (the real arm is reused,
               not retrained): MountainCar, SAC (zoo), the paper's budgets (65k surrogate / 100k
               real steps) as caps, each arm stopped at its first real evaluation >= 90;
               LunarLander, PPO (zoo, 16 envs), the paper's fixed budgets (800k / 1M), no stop.
  fast         the fast PPO recipe (experiment=fast_<env>) on the same data, both surrogates
               and the real arm, stopped at the first real evaluation at the threshold.
  dyna         Dyna-style refits (experiment=dyna_<env>), SINDy and NN, beside the fast real arm;
               LunarLander's SINDy loop and its fast real arm again on as many more seeds (5-9).
  own          LunarLander's Dyna loop from each run's own data (experiment=dyna_lunar_lander_own:
               contact rules, pessimism and touchdown outcome learned from its own transitions),
               on the same seeds as the dyna stage's LunarLander headline (0-9).
  pe           the probabilistic-ensemble NN surrogate (surrogate=pe): its fits on the fits stage's
               data (MountainCar, LunarLander, Pendulum), LunarLander's paper pack and both Dyna
               packs, seeds 0-4, beside SINDy and the MLP.
  cartpole     the DeepMind Control Suite's cartpole swing-up (pip install 'sdrl-bench[dmc]'): SINDy
               and MLP fits on 8,000 random steps, its Dyna loop (experiment=dyna_cartpole_swingup),
               the same PPO recipe in the real env stopped at its first 5-episode evaluation at
               700, the loop with the MLP, PPO with SB3's defaults (8 envs) in the real env, the
               loop with the PE ensemble, SINDy-RL's model form (env=cartpole_swingup_circle: its
               fits and its Dyna loop), and SB3's default SAC in the real env, seeds 0-4.
  search       one Optuna TPE study per env (sdrl-bench-search, seed 0) over the SINDy hyperparameters.
  fidelity     the fidelity-vs-transfer study (experiment=fidelity_<env>): per env 40-60 surrogates
               (data size x collector x noise clusters, SINDy / MLP / ensemble), 3 compiled-PPO agents
               each judged in the real env, every candidate fidelity metric (needs the [jax] extra).
  report       sdrl-bench-report on the store, with this run's provenance (command, seeds,
               budgets, per-stage wall and CPU seconds, commit) as its first section.

Resumable: a finished stage is recorded in ``<workdir>/rebuild.json`` with its commands and cost
and skipped on a rerun with the same commands; inside an unfinished stage each sweep adopts its
FINISHED jobs (``resume=true``) and runs only the rest. Stop it (Ctrl-C) and run it again.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shlex
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
STORE_EXPERIMENT = "sdrl-bench"
SETUP_EXPERIMENT = "rebuild-setup"
EXPERT_PACK = {"mountain_car": "paper_mountain_car", "lunar_lander": "paper_lunar_lander"}


def stages(seeds: list[int]) -> list[tuple[str, list[list[str]]]]:
    """(stage name, its commands in order); a command is ``sdrl-bench`` arguments, or starts
    with ``parallel:`` (several single runs at once) or ``python:`` (a script in the repo)."""
    s = "seed=" + ",".join(map(str, seeds))
    extra = [max(seeds) + 1 + i for i in range(len(seeds))]
    more = "seed=" + ",".join(map(str, extra))  # as many seeds again
    both = "seed=" + ",".join(map(str, [*seeds, *extra]))
    touchdowns = "mlruns/datasets/lunar_lander-touchdowns-v1.npz"
    return [
        ("experts", [
            ["parallel:", *[f"experiment={EXPERT_PACK[e]}" for e in ("mountain_car", "lunar_lander")]],
            ["python:", "studies/touchdown_set.py", "--out", touchdowns],
        ]),
        ("fits", [
            ["-m", "env=mountain_car", "collector=expert", "library=polynomial,poly_trig,rational", s],
            ["-m", "env=lunar_lander", "collector=expert", "library=polynomial,poly_trig,rational",
             "env.spec.fit_regime=null", f"+env.spec.touchdown_set={touchdowns}", s],
            ["-m", "env=lunar_lander", "collector=expert", f"+env.spec.touchdown_set={touchdowns}", s],
            ["-m", "env=mountain_car", "collector=expert", "surrogate=nn", s],
            ["-m", "env=lunar_lander", "collector=expert", "surrogate=nn", f"+env.spec.touchdown_set={touchdowns}", s],
            ["-m", "env=pendulum", "collector=random", "surrogate=sindy,nn", s],
        ]),
        ("transfer", [
            ["-m", "experiment=paper_mountain_car", "surrogate=sindy", "rl.stop_when_solved=true", s],
            ["-m", "experiment=paper_mountain_car", "surrogate=nn", "rl.stop_when_solved=true", s],
            ["-m", "experiment=paper_lunar_lander", "surrogate=sindy", s],
            ["-m", "experiment=paper_lunar_lander", "surrogate=nn", s],
        ]),
        ("fast", [
            ["-m", f"experiment=fast_{env}", f"surrogate={kind}", s]
            for env in ("mountain_car", "lunar_lander") for kind in ("sindy", "nn")
        ]),
        ("dyna", [
            *(["-m", f"experiment=dyna_{env}", "surrogate=sindy,nn", s] for env in ("mountain_car", "lunar_lander")),
            # LunarLander's Dyna headline on twice the seeds, beside the fast real arm on the same ones
            ["-m", "experiment=dyna_lunar_lander", "surrogate=sindy", more],
            ["-m", "experiment=fast_lunar_lander", "rl.arms=[real]", more],
        ]),
        ("own", [  # LunarLander's Dyna loop from the run's own data alone (no constant fitted on other real data)
            ["-m", "experiment=dyna_lunar_lander_own", both],
        ]),
        ("pe", [  # the probabilistic-ensemble NN surrogate beside SINDy and the MLP (same data, seeds, real arms)
            ["-m", "env=mountain_car", "collector=expert", "surrogate=pe", s],
            ["-m", "env=lunar_lander", "collector=expert", "surrogate=pe", f"+env.spec.touchdown_set={touchdowns}", s],
            ["-m", "env=pendulum", "collector=random", "surrogate=pe", s],
            ["-m", "experiment=paper_lunar_lander", "surrogate=pe", s],
            *(["-m", f"experiment=dyna_{env}", "surrogate=pe", s] for env in ("mountain_car", "lunar_lander")),
        ]),
        ("cartpole", [  # the DeepMind Control Suite's cartpole swing-up: the Dyna loop from 8,000 random steps, its real arm
            ["-m", "env=cartpole_swingup", "collector=random", "surrogate=sindy,nn", s],
            ["-m", "experiment=dyna_cartpole_swingup", s],
            ["-m", "experiment=dyna_cartpole_swingup", "task=train", "rl.arms=[real]", s],
            ["-m", "experiment=dyna_cartpole_swingup", "surrogate=nn", s],
            ["-m", "experiment=real_cartpole_swingup", s],
            ["-m", "experiment=dyna_cartpole_swingup", "surrogate=pe", s],
            ["-m", "env=cartpole_swingup_circle", "collector=random", s],
            ["-m", "experiment=dyna_cartpole_swingup_circle", s],
            ["-m", "experiment=real_cartpole_swingup_sac", s],
        ]),
        ("search", [  # one Optuna study per env (seed 0): TPE over library, degree, optimizer, threshold, alpha
            ["search:", "env=mountain_car", "collector=expert", f"tracking.experiment={STORE_EXPERIMENT}"],
            ["search:", "env=lunar_lander", "collector=expert", "env.spec.fit_regime=null", "search.n_trials=40",
             "search.space.poly_degree.high=2", f"tracking.experiment={STORE_EXPERIMENT}"],
        ]),
        ("fidelity", [  # which fidelity predicts transfer: each pack's own clusters (seeds in the pack), >= 40 surrogates per env
            ["-m", f"experiment=fidelity_{env}"] for env in ("mountain_car", "pendulum", "lunar_lander", "cartpole_swingup")
        ]),
    ]


def child_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


ENTRY_POINTS = {"sdrl_bench.cli.main": "sdrl-bench", "sdrl_bench.cli.search": "sdrl-bench-search"}


def as_typed(argv: list[str]) -> str:
    """A subprocess's argv as a user would type it: the entry point's name, repo paths relative."""
    if argv[1] == "-m" and argv[2] in ENTRY_POINTS:
        return " ".join([ENTRY_POINTS[argv[2]], *map(shlex.quote, argv[3:])])
    return " ".join(["python", *(shlex.quote(typed_path(Path(a)) if a.startswith(str(REPO)) else a) for a in argv[1:])])


def typed_path(path: Path) -> str:
    """A path as typed from the checkout (relative to it when inside, else absolute)."""
    try:
        return str(path.resolve().relative_to(REPO))
    except ValueError:
        return str(path.resolve())


def run_command(cmd: list[str], workdir: Path, uri: str, jobs: int, log) -> list[str]:
    """Run one stage command in ``workdir`` (output to ``log``); returns what ran, as typed."""
    from sdrl_bench.cli.args import wait_children

    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    sdrl = [sys.executable, "-m", "sdrl_bench.cli.main"]
    if cmd[0] == "python:":
        procs = [[sys.executable, str(REPO / cmd[1]), *cmd[2:]]]
    elif cmd[0] == "search:":
        procs = [[sys.executable, "-m", "sdrl_bench.cli.search", *cmd[1:], f"tracking.uri={uri}"]]
    elif cmd[0] == "parallel:":  # single warm-up runs side by side, outside the report's experiment
        procs = [[*sdrl, o, "task=fit", "progress_bar=false", f"tracking.uri={uri}",
                  f"tracking.experiment={SETUP_EXPERIMENT}", f"hydra.run.dir=outputs/{SETUP_EXPERIMENT}/{o.split('=')[-1]}"]
                 for o in cmd[1:]]
    else:
        procs = [[*sdrl, *cmd, f"tracking.uri={uri}", f"hydra.launcher.n_jobs={jobs}"]]
    running, shown = [], []
    for p in procs:
        typed = as_typed(p)
        shown.append(typed)
        print(f"  + {typed}", flush=True)
        log.write(f"\n+ {typed}\n")
        log.flush()
        running.append(subprocess.Popen(p, cwd=workdir, env=env, stdout=log, stderr=subprocess.STDOUT))
    codes = wait_children(running)  # a stop of this script stops them (their runs end KILLED)
    if any(codes):
        raise SystemExit(f"reproduce: a command failed (exit {max(codes)}); its output is in {log.name}. "
                         "Fix it and run this command again: finished work is kept and skipped.")
    return shown


def run_stage(name: str, commands: list[list[str]], state: dict, state_path: Path, workdir: Path, uri: str,
              jobs: int) -> float:
    """Run one stage's commands and record it in ``state`` (written to ``state_path``) as
    finished, or as interrupted when a command fails or the user stops it; the cost of earlier
    interrupted attempts of the same commands is added, not lost. Returns this attempt's wall s."""
    old = state["stages"].get(name) or {}
    before = old if old.get("commands") == commands else {}
    t0, c0 = time.time(), child_cpu()

    argv: list[str] = []

    def record(status: str) -> None:
        state["stages"][name] = {"commands": commands, "status": status, "jobs": jobs,
                                 "argv": before.get("argv", []) + [a for a in argv if a not in before.get("argv", [])],
                                 "wall_seconds": before.get("wall_seconds", 0.0) + time.time() - t0,
                                 "cpu_seconds": before.get("cpu_seconds", 0.0) + child_cpu() - c0,
                                 "attempts": before.get("attempts", 0) + 1,
                                 "finished_at": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
        state_path.write_text(json.dumps(state, indent=1))

    try:
        with open(workdir / "logs" / f"{name}.log", "a") as log:
            for cmd in commands:
                argv.extend(run_command(cmd, workdir, uri, jobs, log))
    except BaseException:  # a failed command, Ctrl-C: keep what this attempt cost
        record("interrupted")
        raise
    record("finished")
    return time.time() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--workdir", type=Path, default=REPO / "runs" / "reproduction", help="store, experts, logs "
                    "(default: runs/reproduction in the checkout)")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="processes per sweep (default: cores)")
    ap.add_argument("--seeds", default="0-4", help="seeds of every stage (default 0-4)")
    ap.add_argument("--out", type=Path, default=REPO / "reports", help="report folder's parent")
    ap.add_argument("--name", default="reproduction", help="report folder name")
    ap.add_argument("--only", default=None, help="run only these stages (comma-separated), then the report")
    ap.add_argument("--report-only", action="store_true", help="build the report from the store; run nothing")
    args = ap.parse_args()
    from sdrl_bench import ConfigError
    from sdrl_bench.cli.args import folder, jobs, seed_list
    from sdrl_bench.report.folder import report_files

    seeds = seed_list(ap, args.seeds)
    jobs(ap, args.jobs)
    workdir = folder(ap, args.workdir, "--workdir")
    try:  # the report's folder, as sdrl-bench-report checks it, before the stages rather than after them
        report_files(args.out.resolve(), args.name)
    except ConfigError as exc:
        ap.error(str(exc))
    plan = stages(seeds)
    only = set(args.only.split(",")) if args.only else None
    if only and only - {n for n, _ in plan}:
        ap.error(f"--only: unknown stage(s) {', '.join(sorted(only - {n for n, _ in plan}))} "
                 f"(stages: {', '.join(n for n, _ in plan)})")
    (workdir / "logs").mkdir(parents=True, exist_ok=True)
    uri = f"sqlite:///{workdir / 'mlruns' / 'mlflow.db'}"
    state_path = workdir / "rebuild.json"
    state = json.loads(state_path.read_text()) if state_path.is_file() else {"stages": {}}
    if not args.report_only:  # the record names the command that ran the stages, not a later --report-only
        state["command"] = "python scripts/reproduce.py " + " ".join(shlex.quote(a) for a in sys.argv[1:])
        state.update(seeds=seeds, jobs=args.jobs, machine=f"{os.cpu_count()} cores")
    for i, (name, commands) in enumerate([] if args.report_only else plan):
        if only and name not in only:
            continue
        unfinished = [n for n, _ in plan[:i] if state["stages"].get(n, {}).get("status") != "finished"]
        if unfinished:  # e.g. fits before the experts exist: every job would train its own expert
            raise SystemExit(f"reproduce: stage {name} needs {', '.join(unfinished)} finished first "
                             f"(run without --only, or --only {','.join(unfinished + [name])})")
        done = state["stages"].get(name)
        if done and done.get("commands") == commands and done.get("status") == "finished":
            print(f"{name}: finished before ({done['wall_seconds']:.0f} s), skipped", flush=True)
            continue
        print(f"{name}: {len(commands)} command(s)", flush=True)
        seconds = run_stage(name, commands, state, state_path, workdir, uri, args.jobs)
        print(f"{name}: done in {seconds:.0f} s", flush=True)
    state_path.write_text(json.dumps(state, indent=1))
    report = [sys.executable, "-m", "sdrl_bench.cli.report", "--uri", f"sqlite:///{typed_path(workdir / 'mlruns' / 'mlflow.db')}",
              "--experiment", STORE_EXPERIMENT, "--name", args.name, "--out", typed_path(args.out),
              "--ui-url", "http://127.0.0.1:5000"]  # links open in `mlflow ui` served on this store
    if state["stages"]:  # how the store was made (a --report-only on a store made otherwise has no record)
        report += ["--provenance", typed_path(state_path)]
    print("report: " + " ".join(report[2:]), flush=True)
    return subprocess.run(report, cwd=REPO).returncode  # the store path as typed from the checkout


if __name__ == "__main__":
    from sdrl_bench.cli.args import script_main

    script_main(main, "reproduce.py")
