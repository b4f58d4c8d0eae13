"""What limits the LunarLander surrogate arm: the same agents, the same 20 final real episodes
(reset seeds of the run's ``final_eval`` stream, ``seeds.reset_seed(seed, "final_eval", i)``), once on the real env's random terrain and once on
a flat one (the real env, every random draw identical, only the terrain heights replaced by the
pad's height). The surrogate's world is flat; if the flat real env scores far higher, the terrain
off the pad (not the dynamics model) is what the agents were never taught.

Per seed: mean return, crashes (and how many of them touched down off the pad, |x| > 0.2) and
rests, on both terrains; on the real terrain, the median downward speed (m/s) in the step before
the first touchdown and the median |slope| of the ground there, for crashed and for survived
touchdowns (a crash below the surrogate's touchdown speed, 3.05 m/s, on a slope is one the
surrogate cannot teach). Across seeds the IQM with a 95% bootstrap CI.

Any saved agent: each run's ``agent`` tag names its config group (``agent=ppo``, ``agent=ppo_jax``,
...), whose ``algo`` class loads the run's ``agents/surrogate.zip``. ``--where KEY=VALUE``
(repeatable) keeps the runs whose param or tag KEY is VALUE, for a store that holds several
packs (e.g. ``--where agent.name=ppo_jax --where collector.name=expert``).

    .venv/bin/python studies/lunar_lander_terrain.py --uri sqlite:///path/mlruns/mlflow.db [--where KEY=VALUE]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gymnasium as gym
import numpy as np
from gymnasium.envs.box2d.lunar_lander import VIEWPORT_H, LunarLander, SCALE
from hydra.utils import get_class

from sdrl_bench import seeds
from sdrl_bench.cli.build import compose
from sdrl_bench.tracking.read import find_runs

_PAD_HEIGHT = VIEWPORT_H / SCALE / 4  # the real env's helipad_y
_N_HEIGHTS = 12  # CHUNKS + 1 heights drawn in reset


class _FlatTerrain:
    """The env's generator, except that the terrain heights (the draw of 12 uniforms in reset)
    come back as the pad's height; the numbers are still drawn, so every later draw (initial
    push, engine dispersion) is what it is on the real terrain."""

    def __init__(self, rng: np.random.Generator):
        self._rng, self._done = rng, False

    def uniform(self, low=0.0, high=1.0, size=None):
        v = self._rng.uniform(low, high, size)
        if not self._done and size == (_N_HEIGHTS,):
            self._done = True
            return np.full_like(v, _PAD_HEIGHT)
        return v

    def __getattr__(self, name):
        return getattr(self._rng, name)


class FlatLunarLander(LunarLander):
    """LunarLander-v3 on flat ground at the pad's height (a diagnostic, not a benchmark env)."""

    def reset(self, *, seed=None, options=None):
        gym.Env.reset(self, seed=seed)
        self._np_random = _FlatTerrain(self.np_random)
        try:
            return super().reset(options=options)
        finally:
            self._np_random = self._np_random._rng


def ground_slope(env, x_obs: float) -> float:
    """The real ground's slope under x (observation units; world x = 10 x + 10 m): its chunk's."""
    polys = env.unwrapped.sky_polys  # one per chunk: [(x1, y1), (x2, y2), ...]
    wx = 10.0 * x_obs + 10.0
    for p in polys:
        if p[0][0] <= wx <= p[1][0]:
            return (p[1][1] - p[0][1]) / (p[1][0] - p[0][0])
    return float("nan")


def play(agent, env, seed: int) -> tuple[float, str, float | None, float, float]:
    """(return, end: rest / crash / out / truncated, x at the first touchdown, downward speed
    (m/s) the step before it, |slope| of the ground there)."""
    obs, _ = env.reset(seed=seed)
    total, done, x_td, r, term, speed, slope = 0.0, False, None, 0.0, False, float("nan"), float("nan")
    while not done:
        action = int(agent.predict(obs, deterministic=True)[0])
        before = obs
        obs, r, term, trunc, _ = env.step(action)
        total += float(r)
        done = term or trunc
        hit = obs[6] > 0.5 or obs[7] > 0.5 or (term and r == -100 and abs(obs[0]) < 1)
        if x_td is None and hit:
            x_td, speed, slope = float(obs[0]), -float(before[3]) * 7.5, abs(ground_slope(env, float(obs[0])))
    end = "truncated" if not term else ("rest" if r == 100 else ("out" if abs(obs[0]) >= 1 else "crash"))
    return total, end, x_td, speed, slope


def agent_class(name: str):
    """The class that saves and loads agents of the config group ``agent=<name>``."""
    return get_class(compose([f"agent={name}"]).agent.algo._target_)


def iqm_ci(v: np.ndarray) -> str:
    from scipy import stats

    iqm = lambda a, axis=-1: stats.trim_mean(a, 0.25, axis=axis)  # noqa: E731
    if len(v) < 2:
        return f"n={len(v)}"
    ci = stats.bootstrap((v,), iqm, n_resamples=10_000, method="percentile",
                         random_state=np.random.default_rng(0)).confidence_interval
    return f"IQM {iqm(v):.1f} [95% CI {ci.low:.1f}, {ci.high:.1f}], n={len(v)}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--uri", default="sqlite:///mlruns/mlflow.db")
    ap.add_argument("--experiment", default="sdrl-bench")
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--where", action="append", default=[], metavar="KEY=VALUE",
                    help="keep runs whose param or tag KEY equals VALUE, case aside (repeatable)")
    args = ap.parse_args()
    from sdrl_bench.cli.args import at_least, store

    at_least(ap, args, 1, "--episodes")
    store(ap, args.uri)
    bad = [w for w in args.where if "=" not in w]
    if bad:
        ap.error(f"--where takes KEY=VALUE, got {bad[0]!r}")
    where = dict(w.split("=", 1) for w in args.where)
    store = Path(args.uri.removeprefix("sqlite:///")).parent
    runs = [r for r in find_runs(args.uri, args.experiment) if r["tags"].get("env") == "lunar_lander"
            and r["status"] == "FINISHED" and "surrogate/final_return_mean" in r["metrics"]
            and all(str(r["params"].get(k, r["tags"].get(k))).lower() == v.lower() for k, v in where.items())]
    # both with the registered env's 1000-step limit, as the logged final evaluation
    envs = {"real terrain": gym.make("LunarLander-v3"),
            "flat terrain": gym.wrappers.TimeLimit(FlatLunarLander(), max_episode_steps=1000)}
    means: dict[str, list[float]] = {k: [] for k in envs}
    print(f"{'seed':>4} {'terrain':>13} {'mean':>7} {'crash':>6} {'off pad':>8} {'rest':>5} {'(logged)':>9}"
          f"  {'crashed: speed, |slope|':>24}  {'survived: speed, |slope|':>25}")
    pooled: dict[str, list] = {"crash": [], "survived": []}
    for r in sorted(runs, key=lambda r: int(r["tags"]["seed"])):
        seed = int(r["tags"]["seed"])
        zips = list((store / "artifacts").rglob(f"{r['run_id']}/artifacts/agents/surrogate.zip"))
        if not zips:
            print(f"{seed:>4} no agents/surrogate.zip under {store / 'artifacts'}")
            continue
        agent = agent_class(r["tags"].get("agent", "ppo")).load(zips[0], device="cpu")
        for name, env in envs.items():
            res = [play(agent, env, seeds.reset_seed(seed, "final_eval", i)) for i in range(args.episodes)]
            rets = np.array([t[0] for t in res])
            crashes = [t[2] for t in res if t[1] == "crash"]
            touch = {"crash": [t[3:] for t in res if t[1] == "crash" and t[2] is not None],
                     "survived": [t[3:] for t in res if t[1] != "crash" and t[2] is not None]}
            cells = ["" if name != "real terrain" else
                     (f"{np.median([v for v, _ in touch[k]]):.2f}, {np.median([g for _, g in touch[k]]):.2f} (n={len(touch[k])})"
                      if touch[k] else "-") for k in ("crash", "survived")]
            if name == "real terrain":
                for k in pooled:
                    pooled[k] += touch[k]
            means[name].append(float(rets.mean()))
            logged = r["metrics"]["surrogate/final_return_mean"] if name == "real terrain" else float("nan")
            print(f"{seed:>4} {name:>13} {rets.mean():>7.1f} {len(crashes):>6} "
                  f"{sum(x is not None and abs(x) > 0.2 for x in crashes):>8} "
                  f"{sum(t[1] == 'rest' for t in res):>5} {logged:>9.1f}  {cells[0]:>24}  {cells[1]:>25}")
    for k, rows in pooled.items():
        if rows:
            v, g = np.array(rows).T
            print(f"real terrain, {k} touchdowns (all seeds): n={len(rows)}, downward speed median {np.median(v):.2f} m/s "
                  f"[{v.min():.2f}, {v.max():.2f}], |slope| median {np.median(g):.2f}; on flat ground (|slope| < 0.05): "
                  f"{int((g < 0.05).sum())}")
    for name, v in means.items():
        arr = np.asarray(v)
        print(f"{name}: {iqm_ci(arr)}; seeds >= 200: {int((arr >= 200).sum())} of {len(arr)}")


if __name__ == "__main__":
    main()
