"""The touchdown test set: real LunarLander touchdowns from varied policies, and how the
surrogate's touchdown event and sleep counter score on them.

``generate`` plays real episodes, episode i with config ``CONFIGS[i % 27]`` and reset seed
``seed + i`` (the exploration generator seeded the same): gymnasium's heuristic at eps 0 / 0.2 /
0.4 / 0.6; steering to x = +-0.35, +-0.6 (off the pad, eps 0.1); holding a tilt of +-0.1,
+-0.25; a weak main engine (fires with probability 0.5 / 0.7 / 0.85); engines cut below y =
0.1 / 0.25 / 0.5 / 0.8 (free fall from there); the PPO expert at eps 0 / 0.2 / 0.5 (when an
expert policy is given); uniform random. Each episode's first touchdown (the first row whose s'
has a leg flag, or that ends in a crash inside the screen) is recorded: the pre-impact state
(s of that row) and action, the outcome (crash within ``CRASH_WINDOW`` steps of first contact,
else survive), the steps from contact to rest (+100), and the post-contact trajectory (up to
``POST`` steps). Deterministic by seed. Named ``lunar_lander-touchdowns-v1`` (400 episodes from
seed 30000, the expert included: 374 touchdowns; ``studies/touchdown_set.py``).

Scoring: ``score_events`` (confusion matrix of the touchdown event on the pre-impact states),
``score_rest`` (the sleep counter along the post-contact trajectories: rest precision, recall,
timing error in steps).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
from gymnasium.envs.box2d.lunar_lander import heuristic

from sdrl_bench.envs.lunar_lander import kernels, task
from sdrl_bench.envs.lunar_lander.task import LanderRules

NAME, SEED0, EPISODES = "lunar_lander-touchdowns-v1", 30_000, 400
POST = 300
CRASH_WINDOW = 30

CONFIGS: tuple[dict, ...] = tuple(
    [{"base": "heuristic", "eps": e} for e in (0.0, 0.2, 0.4, 0.6)]
    + [{"base": "heuristic", "eps": 0.1, "x_target": dx} for dx in (-0.6, -0.35, 0.35, 0.6)]
    + [{"base": "heuristic", "eps": 0.0, "tilt": t} for t in (-0.25, -0.1, 0.1, 0.25)]
    + [{"base": "heuristic", "eps": 0.0, "main_prob": p} for p in (0.5, 0.7, 0.85)]
    + [{"base": "heuristic", "eps": 0.0, "cut_below": h} for h in (0.1, 0.25, 0.5, 0.8)]
    + [{"base": "expert", "eps": e} for e in (0.0, 0.2, 0.5)]
    + [{"base": "random"}]
)


@dataclass
class TouchdownSet:
    """One row per touchdown; post-contact rows concatenated (``offsets`` delimit them)."""

    pre: np.ndarray
    action: np.ndarray
    crash: np.ndarray
    rest_after: np.ndarray
    seed: np.ndarray
    config: np.ndarray
    offsets: np.ndarray
    post_states: np.ndarray
    post_actions: np.ndarray

    def __len__(self) -> int:
        return len(self.crash)

    def save(self, path) -> None:
        np.savez_compressed(path, **self.__dict__)

    @classmethod
    def load(cls, path) -> TouchdownSet:
        with np.load(path) as d:
            return cls(**{k: d[k] for k in cls.__dataclass_fields__})


def _policy(kind: dict, env, rng: np.random.Generator, expert: Callable | None) -> Callable:
    eps = kind.get("eps", 0.0)
    if kind["base"] == "random":
        return lambda obs: int(rng.integers(4))
    if kind["base"] == "expert":
        base = expert
    else:
        dx, tilt = kind.get("x_target", 0.0), kind.get("tilt", 0.0)

        def base(obs):
            o = np.array(obs, dtype=float)
            o[0] -= dx  # steer to x_target (off the pad when |dx| > 0.2)
            o[4] -= tilt  # hold a tilted attitude
            return int(heuristic(env, o))
    cut, weak = kind.get("cut_below"), kind.get("main_prob", 1.0)

    def policy(obs):
        if rng.random() < eps:
            return int(rng.integers(4))
        if cut is not None and obs[1] < cut:
            return 0  # engines off: free fall from here
        a = int(base(obs))
        if a == 2 and rng.random() > weak:
            return 0  # weak main engine
        return a

    return policy


def play(kind: dict, seed: int, expert: Callable | None = None) -> dict | None:
    """One real episode of config ``kind`` from reset seed ``seed`` (the exploration generator
    seeded the same): its first touchdown's record (None without one); ``steps``: the real
    steps played."""
    env = gym.make("LunarLander-v3").unwrapped
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    policy = _policy(kind, env, rng, expert)
    s, a, r, ns, term = [], [], [], [], []
    first = None
    try:
        for t in range(1000):
            act = policy(obs)
            nxt, rew, done, _, _ = env.step(act)
            s.append(obs), a.append(act), r.append(rew), ns.append(nxt), term.append(done)
            if first is None and (nxt[6] > 0.5 or nxt[7] > 0.5 or (done and rew == -100 and abs(nxt[0]) < 1)):
                first = t
            obs = nxt
            if done or (first is not None and t - first >= POST):
                break
    finally:
        env.close()
    if first is None:
        return None
    r, term = np.asarray(r), np.asarray(term)
    crash_t = next((t for t in range(first, len(s)) if term[t] and r[t] == -100), None)
    rest_t = next((t for t in range(first, len(s)) if term[t] and r[t] == 100), None)
    return {"pre": s[first], "action": a[first], "crash": crash_t is not None and crash_t - first < CRASH_WINDOW,
            "rest_after": -1 if rest_t is None else rest_t - first,
            "post_states": np.asarray(ns[first:]), "post_actions": np.asarray(a[first:]), "steps": len(s)}


def generate(n_episodes: int = EPISODES, seed: int = SEED0, expert: Callable | None = None) -> TouchdownSet:
    """The touchdown set (see the module docstring); without ``expert`` its configs are skipped."""
    configs = [c for c in CONFIGS if expert is not None or c["base"] != "expert"]
    recs, seeds, names = [], [], []
    for i in range(n_episodes):
        kind = configs[i % len(configs)]
        rec = play(kind, seed + i, expert)
        if rec is not None:
            recs.append(rec), seeds.append(seed + i), names.append(json.dumps(kind, sort_keys=True))
    lens = np.array([len(r["post_states"]) for r in recs])
    return TouchdownSet(
        pre=np.array([r["pre"] for r in recs], dtype=float), action=np.array([r["action"] for r in recs]),
        crash=np.array([r["crash"] for r in recs], dtype=bool), rest_after=np.array([r["rest_after"] for r in recs]),
        seed=np.array(seeds), config=np.array(names), offsets=np.cumsum(np.r_[0, lens]),
        post_states=np.concatenate([r["post_states"] for r in recs]).astype(float),
        post_actions=np.concatenate([r["post_actions"] for r in recs]),
    )


def event_crash(rules: LanderRules, pre: np.ndarray) -> np.ndarray:
    """The surrogate's touchdown decision on pre-impact states (N, 8)."""
    k = task.rules_vector(rules)
    return np.array([kernels.touchdown_crash(float(p[3]), float(p[4]), k) for p in np.atleast_2d(pre)], dtype=bool)


def confusion(pred: np.ndarray, true: np.ndarray) -> dict[str, float]:
    return {"tp_crash": float((pred & true).sum()), "fn_crash": float((~pred & true).sum()),
            "fp_crash": float((pred & ~true).sum()), "tn_survive": float((~pred & ~true).sum()),
            "accuracy": float(np.mean(pred == true)) if len(true) else float("nan"), "n": float(len(true))}


def score_events(rules: LanderRules, d: TouchdownSet, rows: np.ndarray | None = None) -> dict[str, float]:
    """Confusion matrix and accuracy of the touchdown event (``rows``: a subset, e.g. odd seeds)."""
    rows = np.arange(len(d)) if rows is None else rows
    return confusion(event_crash(rules, d.pre[rows]), d.crash[rows])


def score_rest(rules: LanderRules, d: TouchdownSet, engines_off: bool = True, tol: int = 2) -> dict[str, float]:
    """The sleep counter along each post-contact trajectory (real states): the predicted rest is
    the first step its count reaches ``rules.rest_frames``; the real one the +100 step. A hit is
    within ``tol`` steps. ``engines_off``: the surrogate's rule (a step that fires an engine is
    not quiet); False: Box2D's (speeds only)."""
    off = d.offsets
    episode = np.repeat(np.arange(len(d)), np.diff(off))
    actions = d.post_actions.reshape(-1, 1) if engines_off else None
    counts = task.sleep_counts(rules, episode, d.post_states, actions, True)
    pred = np.full(len(d), -1)
    for i in range(len(d)):
        fire = np.flatnonzero(counts[off[i]:off[i + 1]] >= rules.rest_frames)
        pred[i] = fire[0] if len(fire) else -1
    real = d.rest_after
    both = (pred >= 0) & (real >= 0)
    hit = both & (np.abs(pred - real) <= tol)
    err = (pred - real)[both]
    return {"n_pred": float((pred >= 0).sum()), "n_real": float((real >= 0).sum()),
            "precision": float(hit.sum() / max(1, (pred >= 0).sum())), "recall": float(hit.sum() / max(1, (real >= 0).sum())),
            "timing_err_median": float(np.median(err)) if len(err) else float("nan"),
            "timing_err_abs_mean": float(np.mean(np.abs(err))) if len(err) else float("nan")}
