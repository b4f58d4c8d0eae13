"""Steps per second of the real envs and of their SINDy surrogates, measured in one run.

For MountainCarContinuous-v0 and LunarLander-v3: the real env (``gymnasium.make``, single; and
SB3's DummyVecEnv with ``--dummy-n`` copies) and the surrogate (``gym.make("sdrl/Surrogate-v0")``,
single; and ``SurrogateVecEnv`` at N = 1, 64, 1024, 16384). For a spec with a fused batched
step (LunarLander's compiled loop), also the VecEnv at N = 1024 with the spec's numpy functions
composed instead ("numpy composition"): what the compiled loop buys. Uniform random actions,
drawn before timing; a finished episode is reset (auto-reset in the vectorized envs). Each configuration is
timed ``--repeats`` times, interleaved with the others (so that a busy machine slows all of them
alike), for about ``--seconds`` of this process's CPU time each (``--clock wall`` for elapsed
time); the table shows medians and ratios to the real single env.

The models are fitted as ``sdrl-bench`` fits them by default (the project's Hydra config:
MountainCar from 75 transitions, LunarLander from 1000), or loaded with ``--mc-model`` /
``--ll-model``.

    .venv/bin/python benchmarks/bench_throughput.py [--repeats 5] [--seconds 0.3]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from collections.abc import Callable

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env import DummyVecEnv

import sdrl_bench  # noqa: F401  (registers sdrl/Surrogate-v0)
from sdrl_bench.models.base import load_model
from sdrl_bench.surrogate.model_env import ModelEnv
from sdrl_bench.surrogate.vec import SurrogateVecEnv

ROOT = Path(__file__).resolve().parents[1]


def fit_default(env: str, overrides: list[str]):
    """The model ``sdrl-bench env=<env> <overrides>`` fits, from the project's config (no tracking)."""
    from sdrl_bench.cli.build import build_fit_job, compose
    from sdrl_bench.pipeline import fit_dynamics

    cfg = compose([f"env={env}", *overrides])
    return fit_dynamics(build_fit_job(cfg)).model


def single_stepper(env: gym.Env, seed: int) -> Callable[[int], int]:
    """A function running n steps of ``env`` (resetting finished episodes)."""
    env.reset(seed=seed)
    env.action_space.seed(seed)
    actions = [env.action_space.sample() for _ in range(4096)]

    def run(n: int) -> int:
        step, reset = env.step, env.reset
        for i in range(n):
            _, _, terminated, truncated, _ = step(actions[i & 4095])
            if terminated or truncated:
                reset()
        return n

    return run


def vec_stepper(venv, seed: int) -> Callable[[int], int]:
    """A function running n steps of a VecEnv (n * num_envs env steps)."""
    venv.seed(seed)
    venv.reset()
    venv.action_space.seed(seed)
    batches = [np.array([venv.action_space.sample() for _ in range(venv.num_envs)]) for _ in range(8)]

    def run(n: int) -> int:
        for i in range(n):
            venv.step(batches[i & 7])
        return n * venv.num_envs

    return run


def measure(run: Callable[[int], int], seconds: float, clock: Callable[[], float]) -> float:
    """Env steps per second of ``run``, calibrated to take about ``seconds``."""
    n = 1
    while True:
        t0 = clock()
        steps = run(n)
        dt = clock() - t0
        if dt >= seconds:
            return steps / dt
        n = max(n * 2, int(n * seconds / max(dt, 1e-6) * 1.1))


def configs(gym_id: str, model, spec: str, dummy_n: int, vec_ns: list[int], seed: int,
            compare_n: int = 1024) -> dict[str, Callable]:
    out = {
        "real, single": single_stepper(gym.make(gym_id), seed),
        f"real, DummyVecEnv N={dummy_n}": vec_stepper(DummyVecEnv([lambda: gym.make(gym_id)] * dummy_n), seed),
        "surrogate, single": single_stepper(gym.make("sdrl/Surrogate-v0", model=model, spec=spec), seed),
    }
    for n in vec_ns:
        out[f"surrogate, vectorized N={n}"] = vec_stepper(SurrogateVecEnv(model, spec, n, seed=seed), seed)
    composed = ModelEnv(model, spec, fused=False)
    if composed.state_order != ModelEnv(model, spec).state_order:  # the spec has a fused step
        n = compare_n
        out[f"  same, numpy composition N={n}"] = vec_stepper(SurrogateVecEnv(composed, n_envs=n, seed=seed), seed)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=0.3)
    ap.add_argument("--dummy-n", type=int, default=16)
    ap.add_argument("--vec-n", type=int, nargs="+", default=[1, 64, 1024, 16384])
    ap.add_argument("--mc-model", type=Path, default=None)
    ap.add_argument("--ll-model", type=Path, default=None)
    ap.add_argument("--ll-overrides", nargs="*", default=[], help="config overrides of the LunarLander fit, "
                    "e.g. library=polynomial")
    ap.add_argument("--clock", choices=("cpu", "wall"), default="cpu",
                    help="cpu: this process's CPU time (robust to other load on the machine; equal to "
                         "wall time for these single-threaded loops on an idle machine); wall: elapsed time")
    args = ap.parse_args()
    from sdrl_bench.cli.args import at_least

    at_least(ap, args, 1, "--repeats", "--dummy-n", "--vec-n")
    if not args.seconds > 0:
        ap.error(f"--seconds: a number > 0 is required, got {args.seconds}")
    for flag, path in (("--mc-model", args.mc_model), ("--ll-model", args.ll_model)):
        if path is not None and not path.is_file():
            ap.error(f"{flag}: {path} is not a file (a saved model)")
    clock = time.process_time if args.clock == "cpu" else time.perf_counter

    envs = [
        ("MountainCarContinuous-v0", "mountain_car", args.mc_model, []),
        ("LunarLander-v3", "lunar_lander", args.ll_model, args.ll_overrides),
    ]
    table: dict[tuple[str, str], list[float]] = {}
    runners = {}
    for gym_id, spec, path, overrides in envs:
        model = load_model(path) if path else fit_default(spec, overrides)
        for name, run in configs(gym_id, model, spec, args.dummy_n, args.vec_n, seed=0).items():
            run(50)  # warm-up
            runners[(gym_id, name)] = run
    for _ in range(args.repeats):
        for key, run in runners.items():
            table.setdefault(key, []).append(measure(run, args.seconds, clock))

    print(f"\nsteps per {args.clock} second, median of {args.repeats} interleaved runs of ~{args.seconds:g} s "
          "each; ratio = / real single env")
    print(f"{'env':<26} {'configuration':<32} {'steps/s':>14} {'ratio':>9}")
    for gym_id, *_ in envs:
        base = float(np.median(table[(gym_id, "real, single")]))
        for (gid, name), rates in table.items():
            if gid == gym_id:
                med = float(np.median(rates))
                print(f"{gym_id:<26} {name:<32} {med:>14,.0f} {med / base:>8.2f}x")


if __name__ == "__main__":
    main()
