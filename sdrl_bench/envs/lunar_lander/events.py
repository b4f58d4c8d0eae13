"""LunarLander's touchdown event, as the functions its YAML names (``conf/env/lunar_lander.yaml``,
``events:``): where a touchdown happens, the features its outcome model sees, and the hand-set
rule that is this env's prior.

Generic code (``surrogate.events``) labels the run's own real touchdowns (crash: the episode
ends with -100 within 30 steps), fits the outcome model on those the prior leaves open, scores
it and draws from it in the surrogate. The prior itself, crash iff the pre-impact downward speed
exceeds ``rules.touchdown_speed`` or the tilt ``rules.tip_angle``, is applied inside this env's
kernels (``kernels.step``); here it only says which events it leaves open.
"""

from __future__ import annotations

import numpy as np

from sdrl_bench.envs.lunar_lander import kernels, task

PAD_HALF_WIDTH = 0.2
"""The helipad spans |x| <= 0.2 in observation units (the real env's source: chunks 4 to 6 of 11
over 20 m; a prior). ``off_pad`` = max(|x| - 0.2, 0): where the random terrain begins."""
LEGS = (6, 7)
"""Columns of the leg-contact flags in the state."""


def touchdown(states: np.ndarray, actions: np.ndarray, next_states: np.ndarray) -> np.ndarray:
    """A touchdown: no leg flag in s, a leg flag in s'."""
    s, ns = np.asarray(states), np.asarray(next_states)
    l, r = LEGS
    return (s[:, l] < 0.5) & (s[:, r] < 0.5) & ((ns[:, l] > 0.5) | (ns[:, r] > 0.5))


def in_flight(states: np.ndarray) -> np.ndarray:
    """Both legs up: the regime the flight law predicts (and where its uncertainty is penalized)."""
    s = np.asarray(states)
    return (s[:, LEGS[0]] <= 0.5) & (s[:, LEGS[1]] <= 0.5)


def touchdown_features(states: np.ndarray) -> np.ndarray:
    """The pre-impact state with the magnitudes a crash depends on either way (position off the
    pad, lateral speed, tilt, spin): the logistic model is linear in its features."""
    s = np.asarray(states, dtype=float)
    x = s[:, 0]
    return np.column_stack([x, np.abs(x), np.maximum(np.abs(x) - PAD_HALF_WIDTH, 0.0), s[:, 1], s[:, 2],
                            np.abs(s[:, 2]), s[:, 3], s[:, 4], np.abs(s[:, 4]), s[:, 5], np.abs(s[:, 5])])


def touchdown_prior(states: np.ndarray, spec) -> np.ndarray:
    """The hand-set touchdown rule on pre-impact states: 1 (crash) or 0 (survive)."""
    k = task.rules_vector(spec.rules)
    return np.array([kernels.touchdown_crash(float(p[3]), float(p[4]), k) for p in np.atleast_2d(states)], dtype=int)
