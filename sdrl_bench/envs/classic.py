"""Task functions of the worked examples ``conf/env/pendulum.yaml`` and ``conf/env/cartpole.yaml``.

Plain batched functions referenced by dotted path from YAML (``env.spec.reward_fn`` etc.), as
a user writes them for an env of their own: states in the spec's ``state_names`` order, raw
actions (N, width), nothing imported from sdrl_bench but a helper. Constants from gymnasium's
``classic_control/pendulum.py`` and ``cartpole.py``.

Written once for numpy and jax (``envs.functional.array_namespace``: jax.numpy for jax arrays,
numpy otherwise; a jax PRNG key for the resets), so that the surrogate's step runs as one JAX
function (``surrogate.jax_step``); their numpy results are those of plain numpy code.
"""

from __future__ import annotations

import numpy as np

from sdrl_bench.envs.functional import array_namespace, split_rng, uniform, wrap_angle

# ---------------------------------------------------------------------- Pendulum-v1: states (th, thdot)
PENDULUM_MAX_TORQUE = 2.0


def pendulum_reward(states: np.ndarray, actions: np.ndarray, next_states: np.ndarray) -> np.ndarray:
    """-(th^2 + 0.1 thdot^2 + 0.001 u^2) of the state before the step (th wrapped, u clipped)."""
    u = array_namespace(states, actions).clip(actions[:, 0], -PENDULUM_MAX_TORQUE, PENDULUM_MAX_TORQUE)
    return -(wrap_angle(states[:, 0]) ** 2 + 0.1 * states[:, 1] ** 2 + 0.001 * u**2)


def pendulum_initial_states(rng: np.random.Generator, n: int) -> np.ndarray:
    """th ~ U[-pi, pi], thdot ~ U[-1, 1] (a numpy Generator: th's draws, then thdot's)."""
    r_th, r_thdot = split_rng(rng, 2)
    th, thdot = uniform(r_th, -np.pi, np.pi, n), uniform(r_thdot, -1.0, 1.0, n)
    return array_namespace(th).stack([th, thdot], axis=1)


# ---------------------------------------------------------------------- CartPole-v1: states (x, xdot, th, thdot)
CART_X_LIMIT = 2.4
POLE_ANGLE_LIMIT = 12 * 2 * np.pi / 360


def cartpole_reward(states: np.ndarray, actions: np.ndarray, next_states: np.ndarray) -> np.ndarray:
    """+1 for every step, the last one included."""
    return array_namespace(states).ones(len(states))


def cartpole_terminated(states: np.ndarray, actions: np.ndarray, next_states: np.ndarray) -> np.ndarray:
    """The cart leaves [-2.4, 2.4] or the pole tilts beyond 12 degrees."""
    x, th = next_states[:, 0], next_states[:, 2]
    return (x < -CART_X_LIMIT) | (x > CART_X_LIMIT) | (th < -POLE_ANGLE_LIMIT) | (th > POLE_ANGLE_LIMIT)


def cartpole_initial_states(rng: np.random.Generator, n: int) -> np.ndarray:
    """Every state variable ~ U[-0.05, 0.05]."""
    return uniform(rng, -0.05, 0.05, (n, 4))


def cartpole_heuristic(obs: np.ndarray) -> int:
    """Push the cart under the pole: right (1) when the pole falls right."""
    return int(obs[2] + 0.5 * obs[3] > 0)
