"""Do the swing-up's data show the cart's end stops? Where the fitted law misses, by cart position.

The suite limits the cart's slider to +-1.8 m with a soft constraint (the cart overshoots to about
1.97 before it stops). A constraint force is in no term of ``cartpole_swingup_law``: if the data
reached the stops often, the fit's one-step error would concentrate there and an event (a
classifier of "at the stop" and its outcome, ``env.spec.events``) would be worth declaring. This
fits the env's default law on the uniform-random steps a Dyna run starts from (8,000: seed
``--seed``) and splits its one-step squared error on the held-out set (``cartpole_swingup-heldout-v1``,
random actions) and on on-policy steps (``--policy``: the final agent of a Dyna run, an SB3 zip)
into rows with |x| beyond ``--edge`` m and the rest.

    .venv/bin/python studies/cartpole_end_stops.py [--seed 0] [--edge 1.6] [--policy agents/dyna.zip]

Measured (seed 0, edge 1.6; the policy: the reference store's Dyna seed-0 agent, run c3aadda1,
``agents/dyna.zip``; 22 s): the 8,000 random steps reach |x| > 1.6 on 17.8% of rows (max 1.85).
Held-out (random actions, 2,210 of 6,000 rows beyond): one-step MSE beyond / inside, x 4.2e-8 /
3.9e-10, th 7.6e-8 / 7.9e-10, xdot 1.7e-3 / 1.6e-5, thdot 3.1e-3 / 3.2e-5: about 100 times,
and 98% of the velocities' squared error comes from the rows at the stops. On-policy (3 episodes
of the agent, 175 of 3,000 steps beyond, max |x| 1.90): xdot 2.4e-2 / 2.3e-4, thdot 6.2e-2 /
6.0e-4. The data show the stops; the law does not model them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from sdrl_bench.cli.build import build_fit_job, compose
from sdrl_bench.data import held_out_test_set
from sdrl_bench.pipeline import fit_dynamics


def split_errors(spec, model, states, actions, next_states, edge: float) -> dict[str, dict[str, float]]:
    """Mean one-step squared error per regressed state, rows beyond ``edge`` vs the rest."""
    x, u = spec.model_inputs(states, actions)
    pred = spec.apply_bounds(states, model.predict(x, u))
    err = (pred - next_states[:, spec.target_index]) ** 2
    far = np.abs(states[:, spec.state_names.index("x")]) > edge
    out = {"n_beyond": int(far.sum()), "n_inside": int((~far).sum())}
    for j, name in enumerate(spec.target_names):
        out[f"beyond/{name}"] = float(err[far, j].mean()) if far.any() else float("nan")
        out[f"inside/{name}"] = float(err[~far, j].mean())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--edge", type=float, default=1.6, help="|x| (m) beyond which a row counts as at the stops")
    ap.add_argument("--policy", default=None, help="an SB3 PPO zip: on-policy steps of it too")
    ap.add_argument("--episodes", type=int, default=3, help="on-policy episodes")
    args = ap.parse_args()
    from sdrl_bench.cli.args import at_least

    at_least(ap, args, 1, "--episodes")
    if args.policy is not None and not Path(args.policy).is_file():
        ap.error(f"--policy: {args.policy} is not a file (an SB3 PPO zip)")
    res = fit_dynamics(build_fit_job(compose(["env=cartpole_swingup", "collector=random", f"seed={args.seed}"])))
    spec, model, data = res.job.spec, res.model, res.data
    xs = np.abs(data.states[:, 0])
    print(f"fit data (8,000 random steps): |x| > {args.edge}: {np.mean(xs > args.edge):.1%} of rows; max |x| {xs.max():.2f}")
    name, test = held_out_test_set(spec, spec.test_set_recipe())
    print(name, split_errors(spec, model, test.states, test.actions, test.next_states, args.edge))
    if args.policy:
        from stable_baselines3 import PPO

        from sdrl_bench.seeds import reset_seed

        agent = PPO.load(args.policy, device="cpu")
        env = spec.make_env()
        rows = []
        for ep in range(args.episodes):
            obs, _ = env.reset(seed=reset_seed(10_000 + ep, "final_eval"))  # runs 10,000+: no run uses them
            for _ in range(spec.max_episode_steps):
                a, _ = agent.predict(obs, deterministic=True)
                nxt, _, term, trunc, _ = env.step(a)
                rows.append((obs, a, nxt))
                obs = nxt
                if term or trunc:
                    break
        o, a, n = (np.array(c) for c in zip(*rows, strict=True))
        s = spec.coordinates(o)
        s2 = spec.coordinates(n, s)
        print(f"on-policy ({len(rows)} steps): max |x| {np.abs(s[:, 0]).max():.2f}",
              split_errors(spec, model, s, a, s2, args.edge))


if __name__ == "__main__":
    main()
