"""LunarLander's touchdown event, as the functions its YAML names (``conf/env/lunar_lander.yaml``,
``events:``): where a touchdown happens, the features its outcome model sees, and the hand-set
rule that is this env's prior.

Generic code (``surrogate.events``) labels the run's own real touchdowns (crash: the episode
ends with -100 within 30 steps), fits the outcome model on those the prior leaves open, scores
it and draws from it in the surrogate. The prior itself, crash iff the pre-impact downward speed
exceeds ``rules.touchdown_speed`` or the tilt ``rules.tip_angle``, is applied inside this env's
kernels (``kernels.step``); here it only says which events it leaves open.

Each function takes numpy or jax arrays (``envs.functional.array_namespace``): the jax step
(``surrogate.jax_step``) traces them; numpy gives what plain numpy code gives.
"""

from __future__ import annotations

import numpy as np

from sdrl_bench.envs.functional import array_namespace
from sdrl_bench.envs.lunar_lander import array_rules

PAD_HALF_WIDTH = 0.2
"""The helipad spans |x| <= 0.2 in observation units (the real env's source: chunks 4 to 6 of 11
over 20 m; a prior). ``off_pad`` = max(|x| - 0.2, 0): where the random terrain begins."""
LEGS = (6, 7)
"""Columns of the leg-contact flags in the state."""


def touchdown(states: np.ndarray, actions: np.ndarray, next_states: np.ndarray) -> np.ndarray:
    """A touchdown: no leg flag in s, a leg flag in s'."""
    xp = array_namespace(states, next_states)
    s, ns = xp.asarray(states), xp.asarray(next_states)
    l, r = LEGS
    return (s[:, l] < 0.5) & (s[:, r] < 0.5) & ((ns[:, l] > 0.5) | (ns[:, r] > 0.5))


def in_flight(states: np.ndarray) -> np.ndarray:
    """Both legs up: the regime the flight law predicts (and where its uncertainty is penalized)."""
    xp = array_namespace(states)
    s = xp.asarray(states)
    return (s[:, LEGS[0]] <= 0.5) & (s[:, LEGS[1]] <= 0.5)


def touchdown_features(states: np.ndarray) -> np.ndarray:
    """The pre-impact state with the magnitudes a crash depends on either way (position off the
    pad, lateral speed, tilt, spin): the logistic model is linear in its features."""
    xp = array_namespace(states)
    s = xp.asarray(states, dtype=xp.float64)
    x = s[:, 0]
    return xp.stack([x, xp.abs(x), xp.maximum(xp.abs(x) - PAD_HALF_WIDTH, 0.0), s[:, 1], s[:, 2],
                     xp.abs(s[:, 2]), s[:, 3], s[:, 4], xp.abs(s[:, 4]), s[:, 5], xp.abs(s[:, 5])], axis=1)


def touchdown_prior(states: np.ndarray, spec) -> np.ndarray:
    """The hand-set touchdown rule on pre-impact states: 1 (crash) or 0 (survive)."""
    xp = array_namespace(states)
    s = xp.atleast_2d(xp.asarray(states, dtype=xp.float64))
    return array_rules.touchdown_crash(s[:, 3], s[:, 4], spec.rules).astype(np.int64)
