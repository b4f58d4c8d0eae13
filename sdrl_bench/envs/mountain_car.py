"""MountainCarContinuous-v0: what the real environment does at its bounds.

Real dynamics (gymnasium source): v' = clip(v + 0.0015 clip(a) - 0.0025 cos(3x), -0.07, 0.07);
x' = clip(x + v', -1.2, 0.6); if x' == -1.2 and v' < 0 then v' = 0 (an inelastic left wall).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sdrl_bench.envs.base import EnvSpec, Policy, TestSetRecipe

MIN_POSITION, MAX_POSITION, MAX_SPEED = -1.2, 0.6, 0.07


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
        pred = np.asarray(predicted_targets, dtype=float)
        x_pred, v_pred = pred[:, 0], pred[:, 1]
        v = np.clip(v_pred, -MAX_SPEED, MAX_SPEED)
        x = np.clip(x_pred - (v_pred - v), MIN_POSITION, MAX_POSITION)
        v = np.where((x <= MIN_POSITION) & (v < 0), 0.0, v)
        return self.round_obs(np.stack([x, v], axis=1))

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
