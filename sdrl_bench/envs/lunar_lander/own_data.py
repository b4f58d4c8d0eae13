"""LunarLander's contact constants (``LanderRules``) learned from a run's own transitions.

With ``env.spec.own_data: true`` every fit replaces the constants the calibration studies fitted
on other real data (``studies/calibrate_lunar_lander.py``: 28,000 steps; the touchdown set:
102,914 steps and an expert) by the same estimates on the run's own data, and a constant the
data cannot identify keeps its prior value (that prior's real steps then still count):

* the leg rule (``leg_tilt``, ``touch_height``, ``release_height``): the grid of the calibration
  study, scored by leg-flag accuracy on the rows over the pad (where the surrogate's flat world
  is the real one); needs ``MIN_CONTACT_ROWS`` pad rows with a leg down;
* ``floor``: the lowest y on the legs over the pad;
* ``settle``: the settle model's 14 coefficients (``task.SETTLE_TERMS``) by least squares, one
  equation at a time, on the rows standing on both legs (s and s') that do not end the episode;
  needs ``MIN_SETTLE_ROWS``;
* ``stick``: the stiction that best times the real rests (+100) of the run's landings, each
  rolled on the legs from its first both-legs state with the real actions (the surrogate's
  settle step and sleep counter; ``choose_stick``); needs one real rest (when no candidate
  times any, 0: no stiction);
* ``touchdown_speed``: none (infinite): the touchdown event's outcome model, learned from the
  run's own touchdowns by the generic event code, decides crash or survive.

Box2D's sleep thresholds, friction and the legs' tip angle stay (simulator knowledge, declared).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import replace
from typing import Any

import numpy as np

from sdrl_bench.envs.lunar_lander import task
from sdrl_bench.envs.lunar_lander.task import LanderRules

PAD = 0.2
"""|x'| <= PAD: over the helipad (observation units; the real env's source, a knowledge prior)."""
MIN_CONTACT_ROWS = 20
MIN_SETTLE_ROWS = 50
LEG_GRID = ((0.0, 0.05, 0.1, 0.15, 0.2, 0.3), np.round(np.arange(-0.03, 0.0301, 0.005), 4),
            np.round(np.arange(0.0, 0.101, 0.025), 4))
"""(tilt, touch height, release height) candidates of the leg rule (the calibration study's grid)."""
STICK_GRID = tuple(np.round(np.arange(0.0, 0.1501, 0.01), 3))
STICK_BAND = 0
"""Grid steps below a stiction candidate whose rest timings count too, each landing scoring the
worst of the band's (``choose_stick``); 0: the least mean error. A band of 2 was measured and not
kept (docs/dyna.md, "What they fail to identify"; ``studies/own_data_ablation.py --band 2``)."""
MAX_ROLL = 300


def search_legs(states: np.ndarray, next_states: np.ndarray, rows: np.ndarray | None = None) -> list[tuple]:
    """(flag accuracy, tilt, touch, release) of every leg rule of ``LEG_GRID`` on ``rows``
    (default: all), best first (ties: the larger tilt, touch, release, as sorted)."""
    s, ns = np.asarray(states, float), np.asarray(next_states, float)
    rows = np.arange(len(s)) if rows is None else rows
    true = ns[rows, 6:8] > 0.5
    out = []
    for k, touch, release in itertools.product(*LEG_GRID):
        if release >= touch:
            rules = LanderRules(leg_tilt=float(k), touch_height=float(touch), release_height=float(release))
            acc = float(np.mean(task.leg_contacts(rules, s[rows], ns[rows]) == true))
            out.append((acc, float(k), float(touch), float(release)))
    return sorted(out, reverse=True)


def _settle_design(s: np.ndarray, ns: np.ndarray, eng: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """(features, target) of the six settle equations, in ``task.SETTLE_TERMS`` order."""
    x, y, vx, vy, an, w = s[:, :6].T
    nx, ny, nvx, nvy, nan_, nw = ns[:, :6].T
    left, main, right = eng.T
    return [(np.column_stack([vx, np.sign(vx), left, right, np.sin(an) * main]), nvx - vx),
            (np.column_stack([vy, main]), nvy - vy),
            (np.column_stack([w, an, left, right]), nw - w),
            (nvx[:, None], nx - x), (nvy[:, None], ny - y), (nw[:, None], nan_ - an)]


def fit_settle(states, actions, next_states, terminated, discrete: bool = True) -> tuple[float, ...] | None:
    """The settle coefficients by least squares on the both-legs rows that go on (None: too few)."""
    s, ns = np.asarray(states, float), np.asarray(next_states, float)
    both = (s[:, 6] > 0.5) & (s[:, 7] > 0.5) & (ns[:, 6] > 0.5) & (ns[:, 7] > 0.5) & ~np.asarray(terminated, bool)
    if both.sum() < MIN_SETTLE_ROWS:
        return None
    eng = task.engine_powers(np.asarray(actions)[both], discrete)
    coef: list[float] = []
    for a, b in _settle_design(s[both], ns[both], eng):
        coef.extend(np.linalg.lstsq(a, b, rcond=None)[0].tolist())
    return tuple(coef)


def _landings(data: Any) -> list[tuple[np.ndarray, int]]:
    """Per episode with a real rest: (its row indices from the first both-legs state, the rest's
    offset in them)."""
    out = []
    rest = np.asarray(data.terminated, bool) & (np.asarray(data.rewards) == 100)
    for ep in np.unique(data.episode):
        idx = np.flatnonzero(data.episode == ep)
        both = np.flatnonzero((data.states[idx, 6] > 0.5) & (data.states[idx, 7] > 0.5))
        hit = np.flatnonzero(rest[idx])
        if len(both) and len(hit) and hit[0] >= both[0]:
            rows = idx[both[0]:]
            out.append((rows, int(hit[0] - both[0])))
    return out


def rest_errors(rules: LanderRules, data: Any, landings: list, discrete: bool = True) -> np.ndarray:
    """|predicted - real| rest step of each of ``landings``, each rolled on the legs from its
    first both-legs state with its real actions (a flight step, after a lift-off, takes the real
    next state); a landing the rollout never rests counts its length."""
    errs = []
    for rows, real in landings:
        step = task.make_step_batch(rules, discrete, [1e9] * 6, [-np.inf] * 8, [np.inf] * 8)
        state = data.states[rows[0]][None, :].astype(float)
        got = len(rows) + MAX_ROLL
        for t, r in enumerate(rows[:MAX_ROLL]):
            act = np.asarray(data.actions[r])[None]
            pred = task.regime_dynamics(rules, discrete, state, act, data.next_states[r][None, :6].T.astype(float))
            state, reward, ended, _ = step(state, act, pred)
            state = np.array(state)
            if ended[0]:
                got = t if reward[0] == 100.0 else len(rows) + MAX_ROLL
                break
        errs.append(abs(got - real))
    return np.asarray(errs, float)


def choose_stick(errors: np.ndarray, band: int = 0) -> int:
    """The row of ``errors`` (stiction grid x landings, ``rest_errors``) whose mean over the
    landings of the worst error over itself and the ``band`` rows below is least (ties: the
    smaller stiction); ``band=0`` is the least mean error.

    Why a band: every stiction that rests a replayed landing rests it early, so the mean error
    alone is least at an edge, the smallest stiction that still rests the run's landings, where
    landings in states the replays did not visit may not rest. A band asks a candidate to time
    its landings with the values below it too, which moves the choice off that edge."""
    e = np.asarray(errors, float)
    worst = np.stack([e[max(0, g - band):g + 1].max(axis=0) for g in range(len(e))])
    return int(np.argmin(worst.mean(axis=1)))


def learn_rules(rules: LanderRules, data: Any, discrete: bool = True) -> tuple[LanderRules, dict[str, float]]:
    """``rules`` with every constant the run's transitions identify replaced (module docstring),
    and {``rules.<name>``: its learned value} for those (the settle model: its row count)."""
    s, ns = np.asarray(data.states, float), np.asarray(data.next_states, float)
    learned: dict[str, float] = {"rules.touchdown_speed": math.inf}
    rules = replace(rules, touchdown_speed=math.inf)
    pad_legs = (np.abs(ns[:, 0]) <= PAD) & ((ns[:, 6] > 0.5) | (ns[:, 7] > 0.5))
    if pad_legs.sum() >= MIN_CONTACT_ROWS:
        pad = np.flatnonzero(np.abs(ns[:, 0]) <= PAD)
        acc, tilt, touch, release = search_legs(s, ns, pad)[0]
        floor = float(ns[pad_legs, 1].min())
        rules = replace(rules, leg_tilt=tilt, touch_height=touch, release_height=release, floor=floor)
        learned.update({"rules.leg_tilt": tilt, "rules.touch_height": touch, "rules.release_height": release,
                        "rules.floor": floor, "rules.leg_accuracy": acc, "rules.contact_rows": float(pad_legs.sum())})
    settle = fit_settle(s, data.actions, ns, data.terminated, discrete)
    if settle is not None:
        rules = replace(rules, settle=settle)
        learned["rules.settle"] = float(len(settle))
    landings = _landings(data)
    if landings:
        errors = np.stack([rest_errors(replace(rules, stick=float(v)), data, landings, discrete) for v in STICK_GRID])
        g = choose_stick(errors, STICK_BAND)  # none rests any landing: stick 0 (no stiction), timing unknown
        stick, err = float(STICK_GRID[g]), float(errors[g].mean())
        rules = replace(rules, stick=stick)
        learned.update({"rules.stick": stick, "rules.rest_timing_error": err if err < MAX_ROLL else math.nan,
                        "rules.rests": float(len(landings))})
    return rules, learned
