"""Real LunarLander touchdowns between 1 and 3 m/s, on the pad, on flat ground and on slopes: how
often they crash, beside the surrogate's touchdown prior (``LanderRules.touchdown_speed``).

Why: the prior's speed (3.05 m/s) was fitted on ``lunar_lander-touchdowns-v1``
(``studies/touchdown_set.py``), whose policies touch down either slowly (the heuristic, the
expert, mostly cushioned by the main engine) or in free fall from high up (over 3 m/s): few of its
touchdowns lie between 1.5 and 3 m/s, where the threshold sits. Agents trained long in the
surrogate land at about 2.2 m/s, and stopped ones crash off the pad on slopes
(``studies/lunar_lander_terrain.py``). This probe fills that range: gymnasium's heuristic
(eps 0.1) steered to 11 x targets (-0.75 to 0.75: the pad, flat ground and hills) with its
engines cut below 6 heights (never, 0.02, 0.04, 0.06, 0.08, 0.12: free fall from there), one
config per episode in turn (``touchdowns.play``; reset seeds from ``--seed``, 60,000, a range
no other study uses). Per first touchdown: the downward speed (m/s) in the step before it, the
slope of the real ground's chunk under the lander (``lunar_lander_terrain.ground_slope``) and
the outcome (a crash within ``touchdowns.CRASH_WINDOW`` steps).

Printed: crashes per (slope, speed) cell; the threshold on speed alone that best separates crash
from survival on the even seeds (touchdowns with |angle| <= ``tip_angle``), its accuracy on the
odd seeds beside the prior's; the real steps played. A diagnostic: nothing in the harness reads
its output.

    .venv/bin/python studies/lunar_lander_touchdown_probe.py [--episodes 1320] [--seed 60000]
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np
from lunar_lander_terrain import ground_slope

from sdrl_bench.envs.lunar_lander import touchdowns
from sdrl_bench.envs.lunar_lander.task import LanderRules

TARGETS = (-0.75, -0.6, -0.45, -0.3, -0.1, 0.0, 0.1, 0.3, 0.45, 0.6, 0.75)
CUTS = (None, 0.02, 0.04, 0.06, 0.08, 0.12)
CONFIGS = tuple({"base": "heuristic", "eps": 0.1, "x_target": dx, **({"cut_below": c} if c else {})}
                for dx in TARGETS for c in CUTS)
SLOPES = ((0.0, 0.05), (0.05, 0.15), (0.15, 0.3), (0.3, np.inf))
SPEEDS = ((-np.inf, 0.5), (0.5, 1.0), (1.0, 1.5), (1.5, 2.0), (2.0, 3.05), (3.05, np.inf))
MPS = 7.5  # m/s per observation unit of vy (the real env's vy = (2/15) v_y)


def best_threshold(speed: np.ndarray, crash: np.ndarray) -> float:
    """The speed threshold (0.5-3.5 m/s, 0.05 apart) of the highest accuracy of ``speed > t``
    as a crash; the lowest of ties."""
    grid = np.round(np.arange(0.5, 3.55, 0.05), 2)
    acc = [np.mean((speed > t) == crash) for t in grid]
    return float(grid[int(np.argmax(acc))])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--episodes", type=int, default=20 * len(CONFIGS))
    ap.add_argument("--seed", type=int, default=60_000)
    args = ap.parse_args()
    from sdrl_bench.cli.args import at_least

    at_least(ap, args, 1, "--episodes")
    env = gym.make("LunarLander-v3").unwrapped
    rows, steps, t0 = [], 0, time.perf_counter()
    for i in range(args.episodes):
        seed = args.seed + i
        rec = touchdowns.play(CONFIGS[i % len(CONFIGS)], seed)
        if rec is None:
            continue
        steps += rec["steps"]
        env.reset(seed=seed)  # the same terrain
        pre = rec["pre"]
        rows.append((seed, -pre[3] * MPS, abs(pre[4]), abs(ground_slope(env, float(pre[0]))), rec["crash"]))
    seed, speed, angle, slope, crash = (np.array(c) for c in zip(*rows, strict=True))
    crash = crash.astype(bool)
    print(f"{len(rows)} touchdowns from {args.episodes} episodes (reset seeds {args.seed}+), {steps:,} real steps, "
          f"{time.perf_counter() - t0:.0f} s")
    print("crashes / touchdowns, by the ground's slope (rows) and the downward speed, m/s (columns):")
    print(f"{'|slope|':>12} " + " ".join(f"{f'{lo:g}-{hi:g}':>9}" for lo, hi in SPEEDS))
    for slo, shi in SLOPES:
        cells = []
        for lo, hi in SPEEDS:
            m = (slope >= slo) & (slope < shi) & (speed >= lo) & (speed < hi)
            cells.append(f"{int(crash[m].sum()):>4}/{int(m.sum()):<4}")
        print(f"{f'{slo:g}-{shi:g}':>12} " + " ".join(cells))
    rules = LanderRules()
    upright = angle <= rules.tip_angle
    even, odd = upright & (seed % 2 == 0), upright & (seed % 2 == 1)
    for name, where in (("flat ground (|slope| < 0.05)", slope < 0.05), ("all ground", slope >= 0.0)):
        t = best_threshold(speed[even & where], crash[even & where])
        acc = lambda v, m: float(np.mean((speed[m] > v) == crash[m]))  # noqa: E731
        print(f"{name}: speed threshold fitted on the even seeds {t:.2f} m/s (accuracy {acc(t, even & where):.3f}); "
              f"odd seeds: {acc(t, odd & where):.3f}, the prior's {rules.touchdown_speed:.2f} m/s: "
              f"{acc(rules.touchdown_speed, odd & where):.3f} (n={int((odd & where).sum())})")


if __name__ == "__main__":
    main()
