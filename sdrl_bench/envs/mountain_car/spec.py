"""MountainCarContinuous-v0: what the real environment does at its bounds.

Real dynamics (gymnasium source): v' = clip(v + 0.0015 clip(a) - 0.0025 cos(3x), -0.07, 0.07);
x' = clip(x + v', -1.2, 0.6); if x' == -1.2 and v' < 0 then v' = 0 (an inelastic left wall).
Terminated when x' >= 0.45 and v' >= 0; reward 100 * terminated - 0.1 a^2 (a unclipped);
reset x ~ U[-0.6, -0.4], v = 0. The task functions below reproduce these exactly, including the
real env's float32 state (see ``terminated``). The bounds, action encoding, reward, termination and
resets are written once for numpy and jax (``envs.functional.array_namespace``): numpy gives plain
numpy's bits, jax arrays give the same step traceably (``surrogate.jax_step``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from collections.abc import Callable

import numpy as np

from sdrl_bench.envs.base import EnvSpec, Policy, StepOne, TestSetRecipe
from sdrl_bench.envs.functional import array_namespace, uniform
from sdrl_bench.envs.task import Task

MIN_POSITION, MAX_POSITION, MAX_SPEED = -1.2, 0.6, 0.07
GOAL_POSITION = 0.45
# The real env's state is float32 and numpy compares it with the Python float 0.45 in float32:
# a position of float32(0.45) = 0.449999988... reaches the goal.
_GOAL_F32 = float(np.float32(GOAL_POSITION))


@dataclass(frozen=True)
class MountainCarSpec(EnvSpec):
    name: str = "mountain_car"
    gym_id: str = "MountainCarContinuous-v0"
    state_names: tuple[str, ...] = ("x", "v")
    action_names: tuple[str, ...] = ("u",)
    state_low: tuple[float, ...] | None = (MIN_POSITION, -MAX_SPEED)
    state_high: tuple[float, ...] | None = (MAX_POSITION, MAX_SPEED)
    max_episode_steps: int = 999
    solved_threshold: float | None = 90.0
    policy_map_slices: tuple = (("x", (MIN_POSITION, MAX_POSITION), "v", (-MAX_SPEED, MAX_SPEED)),)

    def build_task(self) -> Task:
        """The exact task: reward and goal in the real env's arithmetic, its reset distribution,
        and a one-state kernel that replays the real env bit for bit under the exact law."""
        return Task(reward_terminated=self.reward_terminated, initial_states=self.initial_states,
                    step_one=self.make_step_one)

    def is_success(self, episode_return: float, terminated: bool) -> bool:
        """The goal was reached: the episode terminated (a return of 90 can miss it)."""
        return bool(terminated)

    def heuristic_policy(self, env) -> Policy:
        """Push with the sign of the velocity (full force; +1 at rest)."""

        def policy(obs: np.ndarray) -> np.ndarray:
            return np.array([1.0 if obs[1] >= 0 else -1.0], dtype=np.float32)

        return policy

    def apply_bounds(self, states: np.ndarray, predicted_targets: np.ndarray) -> np.ndarray:
        """Clip velocity, integrate the clipped part into position, clip position, stop at the wall.

        The model predicts x' = x + v'_unclipped; when the real env clips v' it moves x by the
        clipped velocity, so the excess is taken off x' before x' itself is clipped.
        """
        xp = array_namespace(predicted_targets)  # numpy, or jax.numpy in a compiled step
        pred = xp.asarray(predicted_targets, dtype=float)
        x_pred, v_pred = pred[:, 0], pred[:, 1]
        v = xp.clip(v_pred, -MAX_SPEED, MAX_SPEED)
        x = xp.clip(x_pred - (v_pred - v), MIN_POSITION, MAX_POSITION)
        v = xp.where((x <= MIN_POSITION) & (v < 0), 0.0, v)
        return self.round_obs(xp.stack([x, v], axis=1))

    def encode_actions(self, actions: np.ndarray) -> np.ndarray:
        """The force the real env applies: the action clipped to [-1, 1]."""
        enc = super().encode_actions(actions)
        return array_namespace(enc).clip(enc, -1.0, 1.0)

    # ------------------------------------------------------------------ the task
    def reward_terminated(self, states, actions, next_states) -> tuple[np.ndarray, np.ndarray]:
        """100 on reaching the goal, minus 0.1 a^2 of the *unclipped* action (the env's order of
        operations, so the values are bit-identical)."""
        xp = array_namespace(states, actions, next_states)
        a = xp.asarray(actions, dtype=float).reshape(len(states), -1)[:, 0]
        terminated = self.terminated(states, actions, next_states)
        return 100.0 * terminated - a * a * 0.1, terminated

    def terminated(self, states: np.ndarray, actions: np.ndarray, next_states: np.ndarray) -> np.ndarray:
        """x' >= 0.45 and v' >= 0, compared in float32 as the real env compares its state."""
        ns = array_namespace(next_states).asarray(next_states, dtype=float)
        return (ns[:, 0] >= _GOAL_F32) & (ns[:, 1] >= 0.0)

    def initial_states(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """x ~ U[-0.6, -0.4], v = 0, drawn exactly as the real env draws them: with the same
        generator and seed, the same (float64, not yet rounded) start (a jax PRNG key: the same
        distribution)."""
        x = uniform(rng, -0.6, -0.4, n)
        xp = array_namespace(x)
        return xp.stack([x, xp.zeros(n)], axis=1)

    def make_step_one(self, predictor: Callable[..., Callable], obs_low=None, obs_high=None) -> StepOne:
        """``apply_bounds``, ``terminated`` and the reward for one state, in the real env's own
        arithmetic (the bounds are the observation space's: no further clipping needed).

        gymnasium's step computes with numpy scalars: the float64 start after a reset, the
        float32 state after a step, the action's own dtype, Python floats for its constants and
        ``math.cos``. This step takes and returns the same scalars (the state list holds numpy
        scalars, the action is not converted) and the model's evaluator imposes no type of its
        own, so numpy's promotion rules round every operation as the real env does. When the
        model's position equation is x + v' (``integrates``), the position moves by the bounded
        new velocity as in gymnasium; with the exact law a replay is then bit-identical.
        """
        predict_one = predictor()
        semi_implicit = getattr(predict_one, "integrates", {}).get(0) == 1
        lim_x, lim_v = (float(v) for v in self.divergence_limit())
        lo, hi, ms, goal, f32, power = MIN_POSITION, MAX_POSITION, MAX_SPEED, GOAL_POSITION, np.float32, math.pow

        def step_one(state: list, action) -> tuple[np.ndarray, list, float, bool, bool]:
            a = action[0]
            force = -1.0 if a < -1.0 else (1.0 if a > 1.0 else a)  # min(max(a, -1), 1), NaN kept
            x = state[0]
            x_pred, v_pred = predict_one((x, state[1], force))
            if not (-lim_x <= x_pred <= lim_x and -lim_v <= v_pred <= lim_v):  # also catches NaN
                return np.array(state, dtype=f32), state, 0.0, False, True
            v = -ms if v_pred < -ms else (ms if v_pred > ms else v_pred)
            x = x + v if semi_implicit else x_pred - (v_pred - v)
            x = lo if x < lo else (hi if x > hi else x)
            if x == lo and v < 0:
                v = 0.0
            term = bool(x >= goal and v >= 0.0)
            obs = np.array((x, v), dtype=f32)
            return obs, [obs[0], obs[1]], (100.0 if term else 0.0) - power(a, 2) * 0.1, term, False

        return step_one

    def at_bound(self, next_states: np.ndarray) -> np.ndarray:
        ns = np.asarray(next_states, dtype=float)
        return (
            (ns[:, 0] <= MIN_POSITION)
            | (ns[:, 0] >= MAX_POSITION)
            | (np.abs(ns[:, 1]) >= np.float32(MAX_SPEED))
        )

    def test_set_recipe(self) -> TestSetRecipe:
        """Twelve episodes of at most 300 steps: the heuristic at eps 0 / 0.2 / 0.5 and uniform
        random actions, three of each; several reach the goal, several hit the left wall."""
        mix = (("heuristic", 0.0), ("heuristic", 0.2), ("heuristic", 0.5), ("random", 1.0)) * 3
        return TestSetRecipe(name="mountain_car-heldout-v1", seed=10_000, episodes=mix, max_steps=300)
