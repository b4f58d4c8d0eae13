"""LunarLander's surrogate step after the prediction as array functions, for numpy and jax alike.

The compiled loops of ``kernels`` (numba) walk the rows one by one and keep each row's sleep
count in the step's own memory; a jax step (``surrogate.jax_step``) needs the same rules as
whole-array operations with the memory passed in and out. These are those rules, written once with
``envs.functional.array_namespace`` (numpy arrays in: numpy; jax arrays or tracers in: jax.numpy),
in the kernels' operations and order (``kernels.settle``, ``_legs``, ``_quiet``, ``_outcome``,
``_reward``, ``step``), on flat ground or on each row's terrain:

* ``regime_dynamics(rules, discrete, states, actions, pred)``: the settle step on the legs,
  predictions in the jax step's layout (N, 6);
* ``make_step(rules, discrete, limit, obs_low, obs_high, terrain=False)`` -> ``step(states, actions, pred, aux)``
  -> (next states (N, 8), rewards, terminated, diverged, aux): the divergence guard, float32
  rounding, leg flags with hysteresis, the touchdown prior, clipping, the sleep count, crash,
  out of bounds, rest and the shaped reward. ``aux`` (N,) int is each row's sleep count (0 for a
  fresh episode: ``init_aux``); the kernel's ``last``/``count`` memory made explicit, so the
  caller resets it where an episode ends. With terrain, ``aux`` also holds each row's ground
  (the kernel's ``ground`` memory), drawn for a fresh episode from a key (``init_aux(n, key,
  terrain=True)``), and the slope rule (``rules.slope_crash``) applies.

Branches become ``where``; the float32 observation is ``functional.round_through``'s. The
constants are ``task.rules_vector``'s, indexed by the kernels' names. The tests check these against
the kernels on random states (tests/surrogate/test_jax_step_lunar.py).
"""

from __future__ import annotations

from functools import cache
from typing import Any

import numpy as np

from sdrl_bench.envs.functional import array_namespace, round_through
from sdrl_bench.envs.lunar_lander import kernels as kn
from sdrl_bench.envs.lunar_lander import task
from sdrl_bench.envs.lunar_lander.task import LanderRules

REST_REWARD, CRASH_REWARD = 100.0, -100.0
"""The real env's rewards of a body at rest and of a crash (or |x| >= 1): the kernels' ``_reward``."""


@cache
def _constants(rules: LanderRules) -> dict[str, Any]:
    """The rules vector's values by the kernels' names (the same floats the kernels read)."""
    k = task.rules_vector(rules)
    names = ("TILT", "TOUCH", "RELEASE", "FLOOR", "V_FREE", "TIP", "REST_V2", "REST_W", "INV_VX", "INV_VY",
             "INV_W", "FRAMES", "COULOMB", "STICK", "SLOPE")
    out: dict[str, Any] = {n: float(k[getattr(kn, n)]) for n in names}
    out["SETTLE"] = tuple(float(v) for v in k[kn.SETTLE:])
    return out


def touchdown_crash(vy: Any, angle: Any, rules: LanderRules) -> Any:
    """The touchdown prior on pre-impact columns (``kernels.touchdown_crash``): the downward
    speed beyond ``touchdown_speed`` or the lander on its side."""
    c = _constants(rules)
    xp = array_namespace(vy, angle)
    return (-vy * c["INV_VY"] > c["V_FREE"]) | (xp.abs(angle) > c["TIP"])


def slope_crash(gl: Any, gr: Any, angle: Any, rules: LanderRules) -> Any:
    """``kernels.slope_crash`` on columns: the ground under the legs (heights ``gl``, ``gr``)
    slopes more than ``rules.slope_crash`` (metres) at attitude ``angle``."""
    xp = array_namespace(gl, gr, angle)
    return xp.abs(gr - gl) > _constants(rules)["SLOPE"] * 2.0 * kn.LEG_X * xp.abs(xp.cos(angle)) * kn.X_PER_Y


def _sign(xp: Any, v: Any) -> Any:
    """``kernels._sign``: 0 for 0 and NaN (``xp.sign`` gives NaN there)."""
    return xp.where(v > 0.0, 1.0, xp.where(v < 0.0, -1.0, 0.0))


def settle(c: dict, x, y, vx, vy, an, w, left, main, right) -> tuple:
    """``kernels.settle`` on columns: the settle model, Coulomb friction with the main engine off,
    stiction on idle steps, the floor."""
    xp = array_namespace(x, y, vx, vy, an, w, left, main, right)
    k = c["SETTLE"]
    sx = _sign(xp, vx)
    nvx = vx + k[0] * vx + k[1] * sx + k[2] * left + k[3] * right + k[4] * xp.sin(an) * main
    nvy = vy + k[5] * vy + k[6] * main
    nw = w + k[7] * w + k[8] * an + k[9] * left + k[10] * right
    if c["COULOMB"] > 0.0:  # a constant: the kernel's branch on it is fixed per rules
        nvx = xp.where(main == 0.0, vx - sx * xp.minimum(xp.abs(vx), c["COULOMB"]), nvx)
    idle = (left == 0.0) & (main == 0.0) & (right == 0.0)
    stick = c["STICK"]
    nvx = xp.where(idle & ((nvx * vx < 0.0) | (xp.abs(nvx) < stick)), 0.0, nvx)
    nvy = xp.where(idle & ((nvy * vy < 0.0) | (xp.abs(nvy) < stick)), 0.0, nvy)
    nw = xp.where(idle & ((nw * w < 0.0) | (xp.abs(nw) < 2.0 * stick)), 0.0, nw)
    ny = xp.maximum(y + k[12] * nvy, c["FLOOR"])
    return x + k[11] * nvx, ny, nvx, nvy, an + k[13] * nw, nw


def on_legs(states: Any) -> Any:
    """(N,) bool: a leg flag set in s (the contact regime)."""
    return (states[:, 6] > 0.5) | (states[:, 7] > 0.5)


def regime_dynamics(rules: LanderRules, discrete: bool, states: Any, actions: Any, pred: Any) -> Any:
    """Predictions (N, 6) with the rows of landers on their legs replaced by the settle step
    (``task.regime_dynamics``, whose predictions are (6, N))."""
    xp = array_namespace(states, actions, pred)
    s = xp.asarray(states, dtype=xp.float64)
    p = task.engine_powers(actions, discrete)
    cols = settle(_constants(rules), *(s[:, j] for j in range(6)), p[:, 0], p[:, 1], p[:, 2])
    return xp.where(on_legs(s)[:, None], xp.stack(cols, axis=1), xp.asarray(pred, dtype=xp.float64))


def _phi(x, y, vx, vy, an, ll, lr, xp: Any) -> Any:
    """``kernels._phi``: the real env's shaping potential, in its order of operations."""
    return (-100.0 * xp.sqrt(x * x + y * y) - 100.0 * xp.sqrt(vx * vx + vy * vy)
            - 100.0 * xp.abs(an) + 10.0 * ll + 10.0 * lr)


def init_aux(n: int, key: Any = None, terrain: bool = False) -> Any:
    """The memory of n fresh episodes: (n,) int64 sleep counts (0); with ``terrain`` the pair
    (counts, (n, 11) ground heights drawn from ``key``: ``task.draw_terrain``, a numpy Generator
    or a jax key, required)."""
    count = np.zeros(n, dtype=np.int64)
    if not terrain:
        return count
    if key is None:
        raise ValueError("init_aux: with terrain each fresh episode draws its ground: a key is needed")
    return count, task.draw_terrain(key, n)


def ground_at(ground: Any, x: Any) -> Any:
    """``kernels.ground_at`` on columns: each row's ground (N, chunks) at its x (N,)."""
    xp = array_namespace(ground, x)
    n = ground.shape[1]
    u = xp.minimum(xp.maximum((x - kn.CHUNK_X0) / kn.CHUNK_DX, 0.0), n - 1.0)
    i = xp.minimum(xp.floor(u), n - 2.0)  # the kernel's int(u) (u >= 0), at most n - 2
    at = i.astype(np.int64)[:, None]
    g0 = xp.take_along_axis(ground, at, axis=1)[:, 0]
    return g0 + (u - i) * (xp.take_along_axis(ground, at + 1, axis=1)[:, 0] - g0)


def make_step(rules: LanderRules, discrete: bool, limit: Any, obs_low: Any, obs_high: Any, terrain: bool = False):
    """``step(states, actions, pred, aux) -> (next states, rewards, terminated, diverged, aux)``:
    ``kernels.step`` for predictions ``pred`` (N, 6; ``regime_dynamics`` applied), with the
    sleep count ``aux`` (N,) in and out; with ``terrain``, ``aux`` is (counts, ground (N, 11))
    and the legs, the floor on them and the slope rule read each row's ground, as the kernel's
    (``init_aux`` draws it; the ground passes through unchanged). Diverged rows keep their state
    and count, reward 0, not terminated."""
    c = _constants(rules)
    limit = np.asarray(limit, dtype=float)
    low, high = np.asarray(obs_low, dtype=float), np.asarray(obs_high, dtype=float)

    def step(states, actions, pred, aux):
        aux, ground = aux if terrain else (aux, None)
        xp = array_namespace(states, actions, pred, aux)
        s = xp.asarray(states, dtype=xp.float64)
        pred = xp.asarray(pred, dtype=xp.float64)
        ok = xp.all(xp.abs(pred) <= limit, axis=1)  # False for NaN
        # placeholders for diverged rows (their state is kept): no overflow in the float32 cast
        obs = round_through(xp.where(ok[:, None], pred, 0.0), np.float32)
        x, y, vx, vy, an, w = (obs[:, j] for j in range(6))
        t = c["TILT"] * xp.sin(an)
        if terrain:
            cos = xp.cos(an)
            gl, gr = ground_at(ground, x - kn.LEG_X * cos), ground_at(ground, x + kn.LEG_X * cos)
            y = xp.where(on_legs(s), xp.maximum(y, c["FLOOR"] + 0.5 * (gl + gr)), y)
            hl, hr = y + t - gl, y - t - gr
        else:
            hl, hr = y + t, y - t
        ll = xp.where((hl <= c["TOUCH"]) | ((s[:, 6] > 0.5) & (hl <= c["RELEASE"])), 1.0, 0.0)
        lr = xp.where((hr <= c["TOUCH"]) | ((s[:, 7] > 0.5) & (hr <= c["RELEASE"])), 1.0, 0.0)
        down = ~on_legs(s) & ((ll > 0.5) | (lr > 0.5))
        x, y, vx, vy, an, w, ll, lr = (xp.minimum(xp.maximum(v, low[j]), high[j])
                                       for j, v in enumerate((x, y, vx, vy, an, w, ll, lr)))
        legs = (ll > 0.5) | (lr > 0.5)
        cost = task.engine_cost(actions, discrete)
        rvx, rvy = vx * c["INV_VX"], vy * c["INV_VY"]
        quiet = legs & (cost == 0.0) & (rvx * rvx + rvy * rvy <= c["REST_V2"]) & (xp.abs(w * c["INV_W"]) <= c["REST_W"])
        crash = xp.where(down, touchdown_crash(s[:, 3], s[:, 4], rules), legs & (xp.abs(an) > c["TIP"]))
        if terrain:  # on the clipped attitude, as the kernel
            crash = crash | (down & slope_crash(gl, gr, an, rules))
        out = xp.abs(x) >= 1.0
        count = xp.where(quiet, xp.asarray(aux) + 1, 0)
        rest = count >= c["FRAMES"]
        shaped = _phi(x, y, vx, vy, an, ll, lr, xp) - _phi(*(s[:, j] for j in (0, 1, 2, 3, 4, 6, 7)), xp) - cost
        reward = xp.where(rest, REST_REWARD, xp.where(crash | out, CRASH_REWARD, shaped))
        nxt = xp.stack([x, y, vx, vy, an, w, ll, lr], axis=1)
        count = xp.where(ok, count, aux).astype(np.int64)
        return (xp.where(ok[:, None], nxt, s), xp.where(ok, reward, 0.0), (crash | out | rest) & ok, ~ok,
                (count, ground) if terrain else count)

    return step
