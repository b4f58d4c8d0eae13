"""The replay noise floor of LunarLander's one-step prediction per regime, on the held-out set.

``fidelity.replay_noise_floor``: reset each held-out episode with its seed, replay its actions
to a sampled row, give the env a fresh generator, step the row's action again (``--k`` times):
the engine dispersion alone is redrawn. The floor is the mean unbiased variance of the k + 1
draws of s' per regime; it is what ``LunarLanderSpec.noise_floor`` returns and what every fit's
``floor_ratio_<regime>/<state>`` divides by. Also checks the replay is bit-exact (must print 0).

    .venv/bin/python studies/noise_floor.py [--rows 400] [--k 2]

Measured (400 rows per episode, k = 2: 2518 rows, 1015 in flight; 132 s on an idle core):
flight 5.78e-9 3.56e-8 5.37e-5 7.02e-5 1.30e-7 5.21e-5 (x, y, vx, vy, angle, angvel);
all 3.21e-9 2.07e-8 2.98e-5 4.08e-5 8.14e-8 3.25e-5; contact (a lower bound) 1.48e-9 1.06e-8
1.37e-5 2.09e-5 4.85e-8 1.93e-5; replay max |diff| 0.0.
"""

from __future__ import annotations

import argparse
import json
import time

from sdrl_bench.data import held_out_test_set
from sdrl_bench.envs.lunar_lander import LunarLanderSpec
from sdrl_bench.fidelity import replay_noise_floor


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rows", type=int, default=400, help="rows sampled per episode")
    ap.add_argument("--k", type=int, default=2, help="redraws per row")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    from sdrl_bench.cli.args import at_least, out_file

    at_least(ap, args, 1, "--rows", "--k")
    out_file(ap, args.out)
    spec = LunarLanderSpec()
    recipe = spec.test_set_recipe()
    name, test = held_out_test_set(spec, recipe)
    seeds = {i: recipe.seed + i for i in range(len(recipe.episodes))}
    t0 = time.time()
    res = replay_noise_floor(spec, test, seeds, args.rows, args.k)
    print(f"{name}: {time.time() - t0:.0f} s, replay max |diff| {res['replay_max_abs_diff']}")
    known = spec.noise_floor(name)
    for regime in ("all", "flight", "contact"):
        print(f"  {regime:8s} n={res[f'n_{regime}']:5.0f} " + " ".join(f"{v:.2e}" for v in res[regime])
              + "   / package: " + " ".join(f"{v / k:.2f}" for v, k in zip(res[regime], known[regime], strict=True)))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
