"""Calibrate and measure the LunarLander surrogate's contact rules (``LanderRules``).

1. Collects calibration transitions from the real env (gymnasium's heuristic at eps 0 / 0.2 /
   0.5 and uniform random actions; seeds 100+, disjoint from the default training seed 0 and
   from the held-out test set's seeds 20000+).
2. Grid-searches the leg-contact rule (tilt, touch and release heights) for accuracy on the rows
   over the flat helipad (|x'| <= 0.2), where the surrogate's flat-ground world is the real
   one (``envs/lunar_lander/own_data.search_legs``, the search an own-data run makes on its own
   transitions); prints the best candidates next to the defaults in ``LanderRules``. (The touchdown
   event and the sleep counter are calibrated and scored on the touchdown test set:
   ``studies/touchdown_set.py``.)
3. Scores the default rules with ``surrogate_fidelity`` on the held-out test set, with the
   model ``sdrl-bench env=lunar_lander`` fits (or ``--model``).

    .venv/bin/python studies/calibrate_lunar_lander.py [--model model.json]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from sdrl_bench.data import Transitions, collect, heuristic_policy, held_out_test_set, random_policy
from sdrl_bench.envs.lunar_lander import LunarLanderSpec
from sdrl_bench.envs.lunar_lander.own_data import search_legs
from sdrl_bench.envs.lunar_lander.task import LanderRules
from sdrl_bench.models.base import load_model
from sdrl_bench.surrogate.fidelity import surrogate_fidelity

FIELDS = ("states", "actions", "rewards", "next_states", "terminated", "truncated", "episode", "step")


def calibration_data(spec: LunarLanderSpec) -> Transitions:
    parts = [collect(spec, heuristic_policy, 8000, eps, seed=100 + 50 * i) for i, eps in enumerate((0.0, 0.2, 0.5))]
    parts.append(collect(spec, random_policy, 4000, 1.0, seed=500))
    return Transitions(**{k: np.concatenate([getattr(p, k) for p in parts]) for k in FIELDS})


def fit_default_model():
    from sdrl_bench.cli.build import build_fit_job, compose
    from sdrl_bench.pipeline import fit_dynamics

    cfg = compose(["env=lunar_lander"])
    return fit_dynamics(build_fit_job(cfg)).model


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", type=Path, default=None, help="a saved LunarLander model (default: fit one)")
    args = ap.parse_args()
    if args.model is not None and not args.model.is_file():
        ap.error(f"--model: {args.model} is not a file (a saved LunarLander model)")
    spec, defaults = LunarLanderSpec(), LanderRules()
    d = calibration_data(spec)
    pad = np.abs(d.next_states[:, 0]) <= 0.2
    print(f"calibration: {len(d)} transitions, {pad.sum()} over the pad")
    print("legs (pad accuracy, tilt, touch, release), best 5:")
    for row in search_legs(d.states, d.next_states, np.flatnonzero(pad))[:5]:
        print("   ", np.round(row, 4).tolist())
    print(f"defaults: {defaults}")

    name, test = held_out_test_set(spec)
    model = load_model(args.model) if args.model else fit_default_model()
    print(f"\nsurrogate_fidelity on '{name}' ({len(test)} transitions, {int(test.terminated.sum())} terminations):")
    for key, value in surrogate_fidelity(model, spec, test).items():
        print(f"  {key:<45} {value:.6g}")


if __name__ == "__main__":
    main()
