"""LunarLander's reward, termination and leg contacts as pure functions of (s, a, s').

The reward is exact up to rounding: the real env's shaping potential
``-100 |(x, y)| - 100 |(vx, vy)| - 100 |angle| + 10 leg_left + 10 leg_right`` is a function of
the observation, and its "previous value" is the potential of s, so the shaped reward is
``phi(s') - phi(s)`` minus the engine costs (0.3 per frame of main engine, 0.03 of side engine,
scaled by throttle for the continuous env). (The real env evaluates phi before rounding the
observation to float32; here it sees the float32 observation: differences of order 1e-5.)

What a dynamics model cannot give is *contact*: the real env's leg flags, its crash
(``game_over``: the lander's body touched the ground) and its rest (Box2D put the body to sleep)
are contact events of a physics engine on a random terrain. The surrogate replaces them with
deliberate rules in a world whose ground is flat at the helipad's height (y = 0); every constant
is in ``LanderRules`` and was calibrated on real transitions from the flat pad (|x| <= 0.2) of
calibration episodes disjoint from the held-out test set (``benchmarks/calibrate_lunar_lander.py``):

* **Leg contacts** (approximation 1): leg i touches when its height ``y' +- leg_tilt sin(angle')``
  (the left leg is lower when the lander tilts to positive angles) drops to ``touch_height``,
  and a touching leg stays down until that height rises above ``release_height`` (legs bounce
  and spring; the hysteresis follows the real flags better than any single threshold). Real
  terrain off the pad is higher or lower than the pad: those contacts are missed or invented.
* **Crash** (approximation 2): the body hits the flat ground when the lander sinks through the
  floor (``y`` crosses ``floor`` downward), arrives at ``impact_height`` faster than
  ``crash_speed`` (vy of s), or lies at ``impact_height`` tilted beyond ``tip_angle``.
* **Rest** (approximation 3): Box2D sleeps a body whose speed stays under its tolerances
  (0.01 m/s, 2 deg/s) for 0.5 s. Here: both legs touch and s' is under the same tolerances,
  converted to observation units; the 0.5 s wait is dropped, so the surrogate's episode ends
  (with +100) up to 25 steps earlier than the real one would.
* ``|x'| >= 1`` ends the episode with -100, as in the real env; a rest overrides a crash, as in
  the real env (its sleep check comes last).

The batched functions run compiled loops (``kernels``, numba): a surrogate's
vectorized step does all of the above in one pass over the rows. ``make_step_one`` is the same
step for one state in plain Python (a single env's step is too short to pay for a call into
compiled code with arrays); the tests check that the two agree.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from functools import cache
from operator import le
from collections.abc import Callable, Sequence

import numpy as np

# Observation units per SI unit, from the real env's observation formula (VIEWPORT_W = 600,
# VIEWPORT_H = 400, SCALE = 30, FPS = 50): vx = 0.2 v_x, vy = (2/15) v_y, angvel = 0.4 omega.
_VX_PER_MPS, _VY_PER_MPS, _W_PER_RADPS = 0.2, 2.0 / 15.0, 0.4
_B2_LINEAR_SLEEP_TOL, _B2_ANGULAR_SLEEP_TOL = 0.01, 2.0 / 180.0 * math.pi


@dataclass(frozen=True)
class LanderRules:
    """Constants of the contact approximations (observation units; see the module docstring)."""

    leg_tilt: float = 0.15
    """Height offset of a leg per unit sin(angle)."""
    touch_height: float = -0.015
    """A leg touches when its height drops to this."""
    release_height: float = 0.075
    """A touching leg leaves the ground when its height rises above this."""
    floor: float = -0.04
    """Sinking through this height is a crash (the lowest y seen on the pad without one)."""
    impact_height: float = -0.03
    """Arriving at this height faster than ``crash_speed``, or tilted, is a crash."""
    crash_speed: float = 0.6
    """Downward speed (-vy of s) above which arriving at ``impact_height`` is a crash."""
    tip_angle: float = 1.2
    """|angle| (rad) at which a lander at ``impact_height`` has tipped over."""
    rest_speed: float = _B2_LINEAR_SLEEP_TOL
    """Box2D's linear sleep tolerance (m/s)."""
    rest_angvel: float = _B2_ANGULAR_SLEEP_TOL * _W_PER_RADPS
    """Box2D's angular sleep tolerance, in observation units."""


_DISCRETE_COST = np.array([0.0, 0.03, 0.30, 0.03])  # noop, left, main, right: 0.3 main + 0.03 side


def engine_cost(actions: np.ndarray, discrete: bool) -> np.ndarray:
    """0.3 x main engine power + 0.03 x side engine power, as the real env computes the powers
    from the raw action (continuous: main 0.5..1 when a0 > 0, side 0.5..1 when |a1| > 0.5)."""
    a = np.asarray(actions)
    if discrete:
        return _DISCRETE_COST[a.reshape(len(a), -1)[:, 0].astype(np.intp)]
    a = np.clip(a.astype(float).reshape(len(a), -1), -1.0, 1.0)
    main = np.where(a[:, 0] > 0.0, (np.clip(a[:, 0], 0.0, 1.0) + 1.0) * 0.5, 0.0)
    side = np.where(np.abs(a[:, 1]) > 0.5, np.clip(np.abs(a[:, 1]), 0.5, 1.0), 0.0)
    return main * 0.30 + side * 0.03


@cache
def rules_vector(rules: LanderRules) -> np.ndarray:
    """The constants the compiled loops take (``kernels``: indices named there)."""
    k = np.array([rules.leg_tilt, rules.touch_height, rules.release_height, rules.floor,
                  rules.impact_height, rules.crash_speed, rules.tip_angle, rules.rest_speed**2,
                  rules.rest_angvel, 1.0 / _VX_PER_MPS, 1.0 / _VY_PER_MPS])
    k.setflags(write=False)
    return k


def _kernels():
    """The compiled loops (numba compiles them on first use; imported lazily so that code not
    touching LunarLander's rules does not load numba)."""
    from sdrl_bench.envs.lunar_lander import kernels

    return kernels


def leg_contacts(rules: LanderRules, states: np.ndarray, next_states: np.ndarray) -> np.ndarray:
    """Leg flags (N, 2) of s' from its height and attitude, with hysteresis on s's flags."""
    s, ns = np.asarray(states, dtype=float), np.asarray(next_states, dtype=float)
    out = np.empty((len(s), 2))
    _kernels().leg_contacts(s, ns, rules_vector(rules), out)
    return out


def events(rules: LanderRules, states: np.ndarray, next_states: np.ndarray) -> tuple[np.ndarray, ...]:
    """(crash, out of bounds, at rest) per row; leg flags of s' are read from ``next_states``."""
    s, ns = np.asarray(states, dtype=float), np.asarray(next_states, dtype=float)
    crash, out, rest = (np.empty(len(s), dtype=bool) for _ in range(3))
    _kernels().events(s, ns, rules_vector(rules), crash, out, rest)
    return crash, out, rest


def reward_terminated(rules: LanderRules, discrete: bool, states, actions, next_states):
    """(reward, terminated): +100 at rest, else -100 on crash or |x'| >= 1, else
    phi(s') - phi(s) - engine costs; terminated on any of the three."""
    s, ns = np.asarray(states, dtype=float), np.asarray(next_states, dtype=float)
    reward, ended = np.empty(len(s)), np.empty(len(s), dtype=bool)
    _kernels().reward_terminated(s, ns, engine_cost(actions, discrete), rules_vector(rules), reward, ended)
    return reward, ended


def reward(rules: LanderRules, discrete: bool, states, actions, next_states) -> np.ndarray:
    return reward_terminated(rules, discrete, states, actions, next_states)[0]


def terminated(rules: LanderRules, states, actions, next_states) -> np.ndarray:
    return reward_terminated(rules, False, states, np.zeros((len(states), 2)), next_states)[1]


def make_step_batch(rules: LanderRules, discrete: bool, limit, obs_low, obs_high):
    """The surrogate's batched step after the model's prediction, in one compiled loop:
    ``step(states, actions, pred)`` with predictions (6, N) -> (next states (N, 8) in C order,
    rewards, terminated, diverged); the same rules as the functions above, in the order
    of ``sdrl_bench.surrogate.env.Surrogate.transition`` (see ``kernels.step``)."""
    kern, k = _kernels(), rules_vector(rules)
    limit, low, high = (np.array(v, dtype=float) for v in (limit, obs_low, obs_high))

    def step(states: np.ndarray, actions: np.ndarray, pred: np.ndarray):
        n = len(states)
        nxt = np.empty((n, 8))
        reward, ended, diverged = np.empty(n), np.empty(n, dtype=bool), np.empty(n, dtype=bool)
        kern.step(states, pred, engine_cost(actions, discrete), limit, low, high, k, nxt, reward, ended, diverged)
        return nxt, reward, ended, diverged

    return step


def make_step_one(
    rules: LanderRules,
    discrete: bool,
    predictor: Callable[..., Callable[[Sequence[float]], list]],
    limit: Sequence[float],
    obs_low: Sequence[float],
    obs_high: Sequence[float],
):
    """The rules above for one state in plain floats (same operations, same order as the
    compiled loops of ``kernels``).

    ``predictor(fixed)`` gives the model's one-state evaluator with inputs ``fixed`` held at
    given values: for discrete actions, one evaluator per action, taking the 8 state values.
    """
    lims, lows, highs = tuple(map(float, limit)), tuple(map(float, obs_low)), tuple(map(float, obs_high))
    if discrete:  # model inputs: 6 regressed states, 2 legs, 4 one-hot actions
        per_action = [predictor({8 + i: float(i == k) for i in range(4)}) for k in range(4)]
        costs = _DISCRETE_COST.tolist()
    else:
        predict = predictor()
    f6, f32, sqrt, sin = struct.Struct("6f"), np.float32, math.sqrt, math.sin
    tilt_k, touch, release = rules.leg_tilt, rules.touch_height, rules.release_height
    floor, impact, crash_speed, tip = rules.floor, rules.impact_height, rules.crash_speed, rules.tip_angle
    rest_v2, rest_w = rules.rest_speed**2, rules.rest_angvel
    inv_vx, inv_vy = 1.0 / _VX_PER_MPS, 1.0 / _VY_PER_MPS
    last = [None, 0.0]  # (the state returned last, its shaping potential): phi(s) is not recomputed

    def phi(x, y, vx, vy, an, ll, lr):
        return -100 * sqrt(x * x + y * y) - 100 * sqrt(vx * vx + vy * vy) - 100 * abs(an) + 10 * ll + 10 * lr

    def step_one(state: list, action):
        if discrete:
            k = int(action)
            if not 0 <= k < 4:
                raise ValueError(f"action {action!r} is not one of 0, 1, 2, 3")
            pred = per_action[k](state)
            cost = costs[k]
        else:
            a0, a1 = (min(max(float(v), -1.0), 1.0) for v in action)
            pred = predict((*state, a0, a1))
            main = (min(max(a0, 0.0), 1.0) + 1.0) * 0.5 if a0 > 0.0 else 0.0
            side = min(max(abs(a1), 0.5), 1.0) if abs(a1) > 0.5 else 0.0
            cost = main * 0.30 + side * 0.03
        if not all(map(le, map(abs, pred), lims)):  # non-finite or beyond the limit
            return np.array(state, dtype=f32), state, 0.0, False, True
        x, y, vx, vy, an, w = f6.unpack(f6.pack(*pred))  # float32 observation
        t = tilt_k * sin(an)
        ll = 1.0 if (y + t <= touch or (state[6] > 0.5 and y + t <= release)) else 0.0
        lr = 1.0 if (y - t <= touch or (state[7] > 0.5 and y - t <= release)) else 0.0
        nxt = [x, y, vx, vy, an, w, ll, lr]
        if not all(map(le, lows, nxt)) or not all(map(le, nxt, highs)):
            nxt = [lo if v < lo else (hi if v > hi else v) for v, lo, hi in zip(nxt, lows, highs, strict=False)]
            x, y, vx, vy, an, w, ll, lr = nxt
        y0 = state[1]
        crash = (
            (y <= floor and y0 > floor)
            or (y <= impact and y0 > impact and state[3] <= -crash_speed)
            or (y <= impact and abs(an) >= tip)
        )
        rvx, rvy = vx * inv_vx, vy * inv_vy
        rest = ll > 0.5 and lr > 0.5 and rvx * rvx + rvy * rvy <= rest_v2 and abs(w) <= rest_w
        phi0 = last[1] if state is last[0] else phi(*state[:5], state[6], state[7])
        phi1 = phi(x, y, vx, vy, an, ll, lr)
        last[0], last[1] = nxt, phi1
        if rest:
            r = 100.0
        elif crash or abs(x) >= 1.0:
            r = -100.0
        else:
            r = phi1 - phi0 - cost
        return np.array(nxt, dtype=f32), nxt, r, bool(crash or rest or abs(x) >= 1.0), False

    return step_one
