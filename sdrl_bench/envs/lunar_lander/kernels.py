"""Compiled (numba) loops of LunarLander's surrogate rules, for batches of states.

The rules themselves (flight and contact regimes, the touchdown event, settling on the legs,
Box2D's sleep counter, the shaped reward) are documented in ``task``; this module evaluates them
row by row in machine code. One loop over the rows does the whole step in a few microseconds for
N = 1024 (see ``benchmarks/bench_throughput.py``).

The constants come in as one float64 vector (``rules_vector``; the indices are named below).
Arrays: states and next states (N, 8) in the observation's order (any memory layout), model
predictions (6, N), engine powers (N, 3: left, main, right). The plain-Python one-state step
(``task.make_step_one``) follows the same operations in the same order; the tests check that
the two agree.

Compiled on first use and cached on disk next to this file (numba ``cache=True``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# Positions in the rules vector (see task.rules_vector).
(TILT, TOUCH, RELEASE, FLOOR, V_FREE, TIP, REST_V2, REST_W, INV_VX, INV_VY, INV_W,
 FRAMES, COULOMB, STICK, SLOPE) = range(15)
SETTLE = 15  # 14 settle coefficients follow (task.SETTLE_TERMS)

# Terrain (``task.draw_terrain``): ground heights at 11 chunk edges x = -1, -0.8, ..., 1
# (observation units, relative to the pad); the legs stand LEG_X either side of the centre.
CHUNK_X0, CHUNK_DX, LEG_X = -1.0, 0.2, 20.0 / 30.0 / 10.0
X_PER_Y = 1.5  # metres per observation unit of x (10) over those per unit of y (20 / 3): rise / run in metres
# = (rise / run in observation units) / X_PER_Y


@njit(cache=True)
def _phi(x, y, vx, vy, angle, leg_left, leg_right):
    """The real env's shaping potential, in its order of operations."""
    return (-100.0 * math.sqrt(x * x + y * y) - 100.0 * math.sqrt(vx * vx + vy * vy)
            - 100.0 * abs(angle) + 10.0 * leg_left + 10.0 * leg_right)


@njit(cache=True)
def touchdown_crash(vy, angle, k):
    """The touchdown event from the pre-impact state: the hull reaches the ground when the
    downward speed exceeds ``v_free`` (m/s) or the lander arrives lying on its side."""
    return -vy * k[INV_VY] > k[V_FREE] or abs(angle) > k[TIP]


@njit(cache=True)
def slope_crash(gl, gr, angle, k):
    """A touchdown on ground that slopes more than ``slope_crash`` (metres) under the legs, whose
    heights there are ``gl`` and ``gr`` (observation units) at attitude ``angle``."""
    return abs(gr - gl) > k[SLOPE] * 2.0 * LEG_X * abs(math.cos(angle)) * X_PER_Y


@njit(cache=True)
def _sign(v):
    return 1.0 if v > 0.0 else (-1.0 if v < 0.0 else 0.0)


@njit(cache=True)
def settle(x, y, vx, vy, an, w, left, main, right, k):
    """One step on the legs (contact regime): the fitted settle model, Coulomb friction (prior)
    when the main engine is off, stiction on idle steps, the floor."""
    c = k[SETTLE:]
    nvx = vx + c[0] * vx + c[1] * _sign(vx) + c[2] * left + c[3] * right + c[4] * math.sin(an) * main
    nvy = vy + c[5] * vy + c[6] * main
    nw = w + c[7] * w + c[8] * an + c[9] * left + c[10] * right
    if k[COULOMB] > 0.0 and main == 0.0:  # side engines do not push a lander standing on its legs
        nvx = vx - _sign(vx) * min(abs(vx), k[COULOMB])
    if left == 0.0 and main == 0.0 and right == 0.0:  # static friction stops, never reverses
        if nvx * vx < 0.0 or abs(nvx) < k[STICK]:
            nvx = 0.0
        if nvy * vy < 0.0 or abs(nvy) < k[STICK]:
            nvy = 0.0
        if nw * w < 0.0 or abs(nw) < 2.0 * k[STICK]:
            nw = 0.0
    ny = max(y + c[12] * nvy, k[FLOOR])
    return x + c[11] * nvx, ny, nvx, nvy, an + c[13] * nw, nw


@njit(cache=True)
def ground_at(g, x):
    """Ground height at x on a terrain row g (heights at the chunk edges, linear between; 0
    everywhere for an empty row: the flat world)."""
    n = g.shape[0]
    if n == 0:
        return 0.0
    u = min(max((x - CHUNK_X0) / CHUNK_DX, 0.0), n - 1.0)
    i = min(int(u), n - 2)
    return g[i] + (u - i) * (g[i + 1] - g[i])


@njit(cache=True)
def _legs(s, y, an, k, gl=0.0, gr=0.0):
    """(left flag, right flag, touchdown) after a step to height y, attitude an. Leg i touches
    when its height ``y +- leg_tilt sin(an)`` (the left leg is lower at positive angles) above
    the ground under it (``gl``, ``gr``: 0 in the flat world) drops to ``touch_height`` and,
    once down, stays down until that height rises above ``release_height``; flags set in s mean
    the lander stands on its legs (contact regime). A touchdown is the first flag set from
    flight (both flags 0 in s)."""
    t = k[TILT] * math.sin(an)
    hl, hr = y + t - gl, y - t - gr
    ll = 1.0 if (hl <= k[TOUCH] or (s[6] > 0.5 and hl <= k[RELEASE])) else 0.0
    lr = 1.0 if (hr <= k[TOUCH] or (s[7] > 0.5 and hr <= k[RELEASE])) else 0.0
    flight = s[6] <= 0.5 and s[7] <= 0.5
    return ll, lr, flight and (ll > 0.5 or lr > 0.5)


@njit(cache=True)
def _flags(s, ns):
    """(on the legs after the step, touchdown) from the leg flags of s and s'."""
    legs = ns[6] > 0.5 or ns[7] > 0.5
    return legs, legs and s[6] <= 0.5 and s[7] <= 0.5


@njit(cache=True)
def _outcome(s, x, an, legs, touchdown, cost, quiet, k):
    """(crash, out, quiet): the touchdown event, tipping over on the legs, |x| >= 1; quiet: on
    the legs, engines off and under Box2D's sleep tolerances (counted by the caller)."""
    if touchdown:
        crash = touchdown_crash(s[3], s[4], k)
    else:
        crash = legs and abs(an) > k[TIP]
    return crash, abs(x) >= 1.0, quiet


@njit(cache=True)
def _quiet(vx, vy, w, legs, cost, k):
    rvx, rvy = vx * k[INV_VX], vy * k[INV_VY]
    return legs and cost == 0.0 and rvx * rvx + rvy * rvy <= k[REST_V2] and abs(w * k[INV_W]) <= k[REST_W]


@njit(cache=True)
def regime_dynamics(states, pred, eng, k, out):
    """Predictions (6, N) with the contact regime's rows replaced by the settle step."""
    for i in range(states.shape[0]):
        s = states[i]
        if s[6] > 0.5 or s[7] > 0.5:
            r = settle(s[0], s[1], s[2], s[3], s[4], s[5], eng[i, 0], eng[i, 1], eng[i, 2], k)
            for j in range(6):
                out[j, i] = r[j]
        else:
            for j in range(6):
                out[j, i] = pred[j, i]


@njit(cache=True)
def leg_contacts(states, next_states, k, out):
    """Leg flags (N, 2) of s' into ``out``."""
    for i in range(states.shape[0]):
        ll, lr, _ = _legs(states[i], next_states[i, 1], next_states[i, 4], k)
        out[i, 0] = ll
        out[i, 1] = lr


@njit(cache=True)
def events(states, next_states, cost, k, crash, out, quiet):
    """Per row: crash (touchdown event or tipping over), |x'| >= 1, quiet (one step of the
    sleep counter; rest needs ``rest_frames`` of them in a row); leg flags read from s and s'."""
    for i in range(states.shape[0]):
        ns = next_states[i]
        legs, down = _flags(states[i], ns)
        q = _quiet(ns[2], ns[3], ns[5], legs, cost[i], k)
        crash[i], out[i], quiet[i] = _outcome(states[i], ns[0], ns[4], legs, down, cost[i], q, k)


@njit(cache=True)
def _reward(s, x, y, vx, vy, an, w, ll, lr, cost, crash, out, rest):
    if rest:
        return 100.0
    if crash or out:
        return -100.0
    return _phi(x, y, vx, vy, an, ll, lr) - _phi(s[0], s[1], s[2], s[3], s[4], s[6], s[7]) - cost


@njit(cache=True)
def reward_terminated(states, next_states, cost, k, reward, terminated):
    """Reward and termination of each transition (a fresh sleep counter: rest only when
    ``rest_frames`` <= 1)."""
    for i in range(states.shape[0]):
        ns = next_states[i]
        legs, down = _flags(states[i], ns)
        q = _quiet(ns[2], ns[3], ns[5], legs, cost[i], k)
        crash, out, _ = _outcome(states[i], ns[0], ns[4], legs, down, cost[i], q, k)
        rest = q and 1.0 >= k[FRAMES]
        reward[i] = _reward(states[i], ns[0], ns[1], ns[2], ns[3], ns[4], ns[5], ns[6], ns[7], cost[i], crash, out, rest)
        terminated[i] = crash or out or rest


@njit(cache=True)
def sleep_counter(episode, next_states, cost, k, out):
    """Box2D's sleep rule along recorded episodes (rows in order): ``out[i]`` is the number of
    consecutive quiet steps ending at row i (a new episode starts the count again)."""
    q = 0
    for i in range(next_states.shape[0]):
        if i > 0 and episode[i] != episode[i - 1]:
            q = 0
        ns = next_states[i]
        legs = ns[6] > 0.5 or ns[7] > 0.5
        q = q + 1 if _quiet(ns[2], ns[3], ns[5], legs, cost[i], k) else 0
        out[i] = q


@njit(cache=True)
def _bound(v, j, low, high):
    return min(max(v, low[j]), high[j])


@njit(cache=True)
def step(states, pred, cost, limit, low, high, k, last, count, nxt, reward, terminated, diverged, ground):
    """Everything of a surrogate step after the prediction ``pred`` (6, N; the model's in
    flight, the settle step's on the legs: ``regime_dynamics``): divergence guard, float32 rounding,
    leg flags and the touchdown event, clipping to [low, high], the sleep counter, reward and
    termination. ``last`` (N, 8) holds each row's state returned last and ``count`` its sleep
    count: a row whose state is not the one returned last (a reset) counts from 0. Diverged
    rows keep their state, reward 0, not terminated. ``ground`` (N, chunks): each row's terrain
    (``ground_at``); with 0 columns the world is flat and the settle step's floor holds, else a
    lander on its legs stands at least ``floor`` above the ground under its legs."""
    terrain = ground.shape[1] > 0
    for i in range(states.shape[0]):
        s = states[i]
        fresh = False
        for j in range(8):
            if s[j] != last[i, j]:
                fresh = True
        if fresh:
            count[i] = 0
        ok = True
        for j in range(6):
            if not abs(pred[j, i]) <= limit[j]:  # also False for NaN
                ok = False
        diverged[i] = not ok
        if not ok:
            for j in range(8):
                nxt[i, j] = s[j]
                last[i, j] = s[j]
            reward[i] = 0.0
            terminated[i] = False
            continue
        # the real env's float32 observation
        # (np.float64: numba types float(np.float32(v)) as float32, and a float64 later assigned to
        # such a variable, the ground's floor below, would be rounded to float32)
        x, y, vx, vy = np.float64(np.float32(pred[0, i])), np.float64(np.float32(pred[1, i])), np.float64(np.float32(pred[2, i])), np.float64(np.float32(pred[3, i]))
        an, w = np.float64(np.float32(pred[4, i])), np.float64(np.float32(pred[5, i]))
        gl = gr = 0.0
        if terrain:
            c = math.cos(an)
            gl, gr = ground_at(ground[i], x - LEG_X * c), ground_at(ground[i], x + LEG_X * c)
            if s[6] > 0.5 or s[7] > 0.5:
                y = max(y, k[FLOOR] + 0.5 * (gl + gr))
        ll, lr, down = _legs(s, y, an, k, gl, gr)
        x, y, vx, vy = _bound(x, 0, low, high), _bound(y, 1, low, high), _bound(vx, 2, low, high), _bound(vy, 3, low, high)
        an, w, ll, lr = _bound(an, 4, low, high), _bound(w, 5, low, high), _bound(ll, 6, low, high), _bound(lr, 7, low, high)
        legs = ll > 0.5 or lr > 0.5
        q = _quiet(vx, vy, w, legs, cost[i], k)
        crash, out, _ = _outcome(s, x, an, legs, down, cost[i], q, k)
        if terrain and down and slope_crash(gl, gr, an, k):
            crash = True
        count[i] = count[i] + 1 if q else 0
        rest = count[i] >= k[FRAMES]
        r = _reward(s, x, y, vx, vy, an, w, ll, lr, cost[i], crash, out, rest)
        nxt[i, 0], nxt[i, 1], nxt[i, 2], nxt[i, 3] = x, y, vx, vy
        nxt[i, 4], nxt[i, 5], nxt[i, 6], nxt[i, 7] = an, w, ll, lr
        for j in range(8):
            last[i, j] = nxt[i, j]
        reward[i] = r
        terminated[i] = crash or out or rest
