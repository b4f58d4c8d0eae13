"""Task functions of ``conf/env/cartpole_swingup.yaml``: the DeepMind Control Suite's cartpole
swing-up (``dm_control`` through ``shimmy``), written from the suite's documented task
(``dm_control/suite/cartpole.py``) as a user writes them for an env of their own.

States in the spec's order (x, th, xdot, thdot): cart position (m), pole angle (rad, 0 upright,
pi hanging), their velocities; or, for SINDy-RL's model form (``cartpole_swingup_circle``), the
suite's observations (x, cos th, sin th, xdot, thdot). Actions: the force command in [-1, 1]. dt 0.01 s, 1000 steps, no
termination. The suite's reward is a smooth product of ``tolerance`` terms (a knowledge prior:
the task's published definition); ``tolerance`` is written here because ``dm_control.utils.rewards``
evaluates one value at a time and would tie these functions to dm_control's import.

Written once for numpy and jax (``envs.functional.array_namespace``: jax.numpy for jax arrays,
numpy otherwise; a jax PRNG key for the resets), so that the surrogate's step runs as one JAX
function (``surrogate.jax_step``); their numpy results are those of plain numpy code.
"""

from __future__ import annotations

import logging
import os
import warnings

import numpy as np

from sdrl_bench.envs.functional import array_namespace, standard_normal

# The suite is used without rendering: no OpenGL backend is loaded (and none warns for want of a
# display). Set before dm_control is imported: gym_id names this module first
# ("sdrl_bench.envs.dmc:dm_control/..."), and importing it registers the suite's envs (shimmy).
os.environ.setdefault("MUJOCO_GL", "disabled")
logging.getLogger("absl").setLevel(logging.WARNING)  # no import notes on the OpenGL backend
with warnings.catch_warnings():  # the suite's imports reset the warning filters; keep the user's
    try:
        import shimmy  # noqa: E402,F401  (registers dm_control/* with gymnasium)
        import dm_control  # noqa: E402,F401
    except ImportError as exc:  # an optional extra: the config's error line says which
        raise ImportError(f"the dm_control envs need the [dmc] extra ({exc.name} is missing): "
                          "pip install 'sdrl-bench[dmc]'") from exc

CART_MARGIN = 2.0
"""``centered``: tolerance margin on the cart position (m)."""
CONTROL_MARGIN = 1.0
"""``small_control``: tolerance margin on the force command."""
ANGVEL_MARGIN = 5.0
"""``small_velocity``: tolerance margin on the pole's angular velocity (rad/s)."""


def tolerance_gaussian(x: np.ndarray, margin: float, value_at_margin: float = 0.1) -> np.ndarray:
    """1 at 0, ``value_at_margin`` at |x| = margin, a Gaussian in between and beyond
    (``dm_control.utils.rewards.tolerance`` with bounds (0, 0) and sigmoid 'gaussian')."""
    xp = array_namespace(x)
    scale = np.sqrt(-2.0 * np.log(value_at_margin))  # a constant
    return xp.exp(-0.5 * (xp.abs(x) / margin * scale) ** 2)


def tolerance_quadratic(x: np.ndarray, margin: float) -> np.ndarray:
    """1 - (x / margin)^2 within the margin, 0 beyond (sigmoid 'quadratic', value_at_margin 0)."""
    xp = array_namespace(x)
    d = xp.abs(x) / margin
    return xp.where(d < 1.0, 1.0 - d**2, 0.0)


def _reward(x: np.ndarray, cos_th: np.ndarray, thdot: np.ndarray, actions: np.ndarray) -> np.ndarray:
    u = array_namespace(actions, x).asarray(actions, dtype=float)[:, 0]
    upright = (cos_th + 1.0) / 2.0
    centered = (1.0 + tolerance_gaussian(x, CART_MARGIN)) / 2.0
    small_control = (4.0 + tolerance_quadratic(u, CONTROL_MARGIN)) / 5.0
    small_velocity = (1.0 + tolerance_gaussian(thdot, ANGVEL_MARGIN)) / 2.0
    return upright * centered * small_control * small_velocity


def swingup_reward(states: np.ndarray, actions: np.ndarray, next_states: np.ndarray) -> np.ndarray:
    """The suite's smooth swing-up reward of the state after the step and the action taken:
    upright (cos th + 1) / 2 x centered (1 + tol(x, 2)) / 2 x small control (4 + tol(u, 1)) / 5
    x small velocity (1 + tol(thdot, 5)) / 2; in [0, 1] per step."""
    return _reward(next_states[:, 0], array_namespace(next_states).cos(next_states[:, 1]), next_states[:, 3], actions)


def swingup_initial_states(rng: np.random.Generator, n: int) -> np.ndarray:
    """The suite's swing-up reset: x ~ 0.01 N(0, 1), th ~ pi + 0.01 N(0, 1), velocities ~ 0.01 N(0, 1)."""
    out = 0.01 * standard_normal(rng, (n, 4))
    return array_namespace(out).stack([out[:, 0], out[:, 1] + np.pi, out[:, 2], out[:, 3]], axis=1)


# ---------------------------------------------------------------- SINDy-RL's model form
# conf/env/cartpole_swingup_circle.yaml: the states are the suite's observations
# (x, cos th, sin th, xdot, thdot), the pole's angle modelled by its cos and sin (circle_pairs).

def swingup_reward_circle(states: np.ndarray, actions: np.ndarray, next_states: np.ndarray) -> np.ndarray:
    """``swingup_reward`` of states in observation form (x, cos th, sin th, xdot, thdot)."""
    return _reward(next_states[:, 0], next_states[:, 1], next_states[:, 4], actions)


def swingup_initial_circle(rng: np.random.Generator, n: int) -> np.ndarray:
    """``swingup_initial_states`` in observation form (the same draws)."""
    s = swingup_initial_states(rng, n)
    xp = array_namespace(s)
    return xp.stack([s[:, 0], xp.cos(s[:, 1]), xp.sin(s[:, 1]), s[:, 2], s[:, 3]], axis=1)
