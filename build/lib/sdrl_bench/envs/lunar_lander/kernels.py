"""Compiled (numba) loops of LunarLander's surrogate rules, for batches of states.

The rules themselves (leg contacts, crash, rest, the shaped reward) are documented in
``task``; this module evaluates them row by row in machine code. A numpy version
needs about a hundred array operations per batched step, each with its own pass over memory and
a microsecond of dispatch; one loop over the rows does the whole step in a few microseconds for
N = 1024 (see ``benchmarks/bench_throughput.py``).

The constants come in as one float64 vector (``rules_vector``; the indices are named below).
Arrays: states and next states (N, 8) in the observation's order (any memory layout), model
predictions (6, N). The plain-Python one-state step (``task.make_step_one``) follows
the same operations in the same order; the tests check that the two agree.

Compiled on first use and cached on disk next to this file (numba ``cache=True``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# Positions in the rules vector (see task.rules_vector).
TILT, TOUCH, RELEASE, FLOOR, IMPACT, CRASH_SPEED, TIP, REST_V2, REST_W, INV_VX, INV_VY = range(11)


@njit(cache=True)
def _phi(x, y, vx, vy, angle, leg_left, leg_right):
    """The real env's shaping potential, in its order of operations."""
    return (-100.0 * math.sqrt(x * x + y * y) - 100.0 * math.sqrt(vx * vx + vy * vy)
            - 100.0 * abs(angle) + 10.0 * leg_left + 10.0 * leg_right)


@njit(cache=True)
def _leg(height, touching, k):
    """A leg is down when its height drops to the touch height, and stays down (hysteresis)
    until it rises above the release height."""
    return 1.0 if (height <= k[TOUCH] or (touching > 0.5 and height <= k[RELEASE])) else 0.0


@njit(cache=True)
def _crash(y0, vy0, y, angle, k):
    """Sinking through the floor, arriving low too fast, or lying low tipped over."""
    return ((y <= k[FLOOR] and y0 > k[FLOOR])
            or (y <= k[IMPACT] and y0 > k[IMPACT] and vy0 <= -k[CRASH_SPEED])
            or (y <= k[IMPACT] and abs(angle) >= k[TIP]))


@njit(cache=True)
def _rest(vx, vy, angvel, leg_left, leg_right, k):
    """Both legs down and the body under Box2D's sleep tolerances."""
    rvx, rvy = vx * k[INV_VX], vy * k[INV_VY]
    return leg_left > 0.5 and leg_right > 0.5 and rvx * rvx + rvy * rvy <= k[REST_V2] and abs(angvel) <= k[REST_W]


@njit(cache=True)
def _reward(s, i, x, y, vx, vy, an, w, ll, lr, cost, k):
    """(reward, crash, out, rest) of the transition from s[i] to (x, ..., lr)."""
    crash = _crash(s[i, 1], s[i, 3], y, an, k)
    rest = _rest(vx, vy, w, ll, lr, k)
    out = abs(x) >= 1.0
    if rest:
        r = 100.0
    elif crash or out:
        r = -100.0
    else:
        r = _phi(x, y, vx, vy, an, ll, lr) - _phi(s[i, 0], s[i, 1], s[i, 2], s[i, 3], s[i, 4], s[i, 6], s[i, 7]) - cost
    return r, crash, out, rest


@njit(cache=True)
def leg_contacts(states, next_states, k, out):
    """Leg flags (N, 2) of s' into ``out``."""
    for i in range(states.shape[0]):
        y, t = next_states[i, 1], k[TILT] * math.sin(next_states[i, 4])
        out[i, 0] = _leg(y + t, states[i, 6], k)
        out[i, 1] = _leg(y - t, states[i, 7], k)


@njit(cache=True)
def events(states, next_states, k, crash, out, rest):
    """Per row: crash, |x'| >= 1, rest (leg flags of s' read from ``next_states``)."""
    for i in range(states.shape[0]):
        ns = next_states
        crash[i] = _crash(states[i, 1], states[i, 3], ns[i, 1], ns[i, 4], k)
        out[i] = abs(ns[i, 0]) >= 1.0
        rest[i] = _rest(ns[i, 2], ns[i, 3], ns[i, 5], ns[i, 6], ns[i, 7], k)


@njit(cache=True)
def reward_terminated(states, next_states, cost, k, reward, terminated):
    """Reward and termination of each transition into ``reward`` and ``terminated``."""
    for i in range(states.shape[0]):
        ns = next_states
        r, crash, out, rest = _reward(states, i, ns[i, 0], ns[i, 1], ns[i, 2], ns[i, 3], ns[i, 4],
                                      ns[i, 5], ns[i, 6], ns[i, 7], cost[i], k)
        reward[i] = r
        terminated[i] = crash or out or rest


@njit(cache=True)
def _bound(v, j, low, high):
    return min(max(v, low[j]), high[j])


@njit(cache=True)
def step(states, pred, cost, limit, low, high, k, nxt, reward, terminated, diverged):
    """Everything of a surrogate step after the model's prediction ``pred`` (6, N):
    divergence guard, float32 rounding, leg contacts, clipping to [low, high], reward and
    termination. Diverged rows keep their state, reward 0, not terminated."""
    for i in range(states.shape[0]):
        ok = True
        for j in range(6):
            if not abs(pred[j, i]) <= limit[j]:  # also False for NaN
                ok = False
        diverged[i] = not ok
        if not ok:
            for j in range(8):
                nxt[i, j] = states[i, j]
            reward[i] = 0.0
            terminated[i] = False
            continue
        # the real env's float32 observation
        x, y, vx, vy = float(np.float32(pred[0, i])), float(np.float32(pred[1, i])), float(np.float32(pred[2, i])), float(np.float32(pred[3, i]))
        an, w = float(np.float32(pred[4, i])), float(np.float32(pred[5, i]))
        t = k[TILT] * math.sin(an)
        ll, lr = _leg(y + t, states[i, 6], k), _leg(y - t, states[i, 7], k)
        x, y, vx, vy = _bound(x, 0, low, high), _bound(y, 1, low, high), _bound(vx, 2, low, high), _bound(vy, 3, low, high)
        an, w, ll, lr = _bound(an, 4, low, high), _bound(w, 5, low, high), _bound(ll, 6, low, high), _bound(lr, 7, low, high)
        r, crash, out, rest = _reward(states, i, x, y, vx, vy, an, w, ll, lr, cost[i], k)
        nxt[i, 0], nxt[i, 1], nxt[i, 2], nxt[i, 3] = x, y, vx, vy
        nxt[i, 4], nxt[i, 5], nxt[i, 6], nxt[i, 7] = an, w, ll, lr
        reward[i] = r
        terminated[i] = crash or out or rest
