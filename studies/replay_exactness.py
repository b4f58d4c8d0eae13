"""How exactly the MountainCar surrogate replays the real env, over fits and episodes.

For each data seed, the model ``sdrl-bench`` fits by default (75 heuristic eps-0.2 transitions,
poly_trig, STLSQ; ``--overrides`` changes the config) is fitted twice, with the coefficient
snapping on (the default) and off (``surrogate.model.snap_alpha=null``). Each model drives a
``SurrogateEnv`` through real episodes replayed action for action from the same start: uniform
random actions (float32 and float64) for 999 steps, and the greedy heuristic with eps 0.2
until the goal. Printed per setting: fits whose law was snapped exactly, episodes replayed
bit-identically (every state, reward and flag equal), the largest state difference, and
episodes whose rewards or termination step differ.

    .venv/bin/python studies/replay_exactness.py [--seeds 20] [--episodes 10]
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np

import sdrl_bench  # noqa: F401
from sdrl_bench.surrogate.env import SurrogateEnv

TRUE = {"x": {"x": 1.0, "v": 1.0, "u": 0.0015, "cos(3 x)": -0.0025},
        "v": {"v": 1.0, "u": 0.0015, "cos(3 x)": -0.0025}}


def fit(seed: int, overrides: list[str]):
    from sdrl_bench.cli.build import build_fit_job, compose
    from sdrl_bench.pipeline import fit_dynamics

    cfg = compose([f"seed={seed}", *overrides])
    return fit_dynamics(build_fit_job(cfg)).model


def real_episode(seed: int, kind: str):
    """States, rewards, flags and actions of one real episode."""
    env, rng = gym.make("MountainCarContinuous-v0"), np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    states, rewards, flags, actions = [obs], [], [], []
    for _ in range(999):
        if kind == "greedy" and rng.random() > 0.2:
            a = np.array([1.0 if obs[1] >= 0 else -1.0], np.float32)
        else:
            a = rng.uniform(-1.2, 1.2, 1).astype(np.float64 if kind == "uniform64" else np.float32)
        obs, r, term, trunc, _ = env.step(a)
        states.append(obs), rewards.append(r), flags.append((term, trunc)), actions.append(a)
        if term or trunc:
            break
    return np.array(states, float), rewards, flags, actions


def replay(model, seed: int, actions):
    env = SurrogateEnv(model, "mountain_car")
    obs, _ = env.reset(seed=seed)
    states, rewards, flags = [obs], [], []
    for a in actions:
        obs, r, term, trunc, _ = env.step(a)
        states.append(obs), rewards.append(r), flags.append((term, trunc))
        if term or trunc:
            break
    return np.array(states, float), rewards, flags


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=20, help="data seeds 0 .. seeds-1")
    ap.add_argument("--episodes", type=int, default=10, help="real episodes per kind and fit")
    ap.add_argument("--overrides", nargs="*", default=[], help="config overrides of the fit")
    args = ap.parse_args()
    from sdrl_bench.cli.args import at_least

    at_least(ap, args, 1, "--seeds", "--episodes")
    kinds = ("uniform32", "uniform64", "greedy")
    episodes = {(k, e): real_episode(50_000 + e, k) for k in kinds for e in range(args.episodes)}
    print(f"{args.seeds} fits x {len(episodes)} real episodes ({args.episodes} each of {', '.join(kinds)}); "
          f"{sum(len(v[1]) for v in episodes.values())} real steps per fit")
    print(f"{'snapping':10} {'exact law':>10} {'bit-identical':>16} {'max |state diff|':>17} {'reward/flag differ':>19}")
    for label, extra in (("on", []), ("off", ["surrogate.model.snap_alpha=null"])):
        exact = identical = total = differ = 0
        worst = 0.0
        for seed in range(args.seeds):
            model = fit(seed, [*args.overrides, *extra])
            exact += model.coefficients_by_name() == TRUE
            for (_kind, e), (s_real, r_real, f_real, acts) in episodes.items():
                s_sur, r_sur, f_sur = replay(model, 50_000 + e, acts)
                same_len = len(s_sur) == len(s_real)
                gap = float(np.abs(s_sur - s_real).max()) if same_len else float("inf")
                worst = max(worst, gap)
                identical += gap == 0.0 and r_sur == r_real and f_sur == f_real
                differ += not (r_sur == r_real and f_sur == f_real)
                total += 1
        print(f"{label:10} {exact:>4} / {args.seeds:<4} {identical:>7} / {total:<7} {worst:>17.3g} {differ:>11} / {total}")


if __name__ == "__main__":
    main()
