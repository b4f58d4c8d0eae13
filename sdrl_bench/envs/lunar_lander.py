"""LunarLander-v3, discrete (four actions, one-hot encoded as model inputs) or continuous.

The real env does not clip its observation, so no bounds are applied after a predicted step.
The two leg-contact flags are booleans: the dynamics model takes them as given inputs
(``exogenous_names``) and never regresses them; the surrogate environment derives them.
Engine impulses carry random dispersion and the terrain is random per episode, so one-step
prediction has a noise floor no deterministic model beats (see shared/REFERENCE.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from gymnasium.envs.box2d.lunar_lander import heuristic

from sdrl_bench.envs.base import EnvSpec, Policy, TestSetRecipe

STATE_NAMES = ("x", "y", "vx", "vy", "angle", "angvel", "leg_left", "leg_right")
LEGS = ("leg_left", "leg_right")


@dataclass(frozen=True)
class LunarLanderSpec(EnvSpec):
    """Discrete LunarLander: actions noop, left engine, main engine, right engine."""

    name: str = "lunar_lander"
    gym_id: str = "LunarLander-v3"
    state_names: tuple[str, ...] = STATE_NAMES
    action_names: tuple[str, ...] = ("a_noop", "a_left", "a_main", "a_right")
    n_discrete_actions: int = 4
    exogenous_names: tuple[str, ...] = LEGS
    max_episode_steps: int = 1000
    solved_threshold: float | None = 200.0

    def heuristic_policy(self, env) -> Policy:
        """gymnasium's built-in heuristic lander controller."""

        def policy(obs: np.ndarray):
            return heuristic(env, obs)

        return policy

    def divergence_limit(self) -> np.ndarray:
        # x, y in about +-2.5 (|x| >= 1 ends an episode), velocities and angle rates in +-10.
        return np.array([25.0, 25.0, 100.0, 100.0, 100.0, 100.0])

    def test_set_recipe(self) -> TestSetRecipe:
        """Twelve full episodes: the heuristic at eps 0 / 0.2 / 0.5 and uniform random actions,
        three of each (landings, crashes and flights off-screen)."""
        mix = (("heuristic", 0.0), ("heuristic", 0.2), ("heuristic", 0.5), ("random", 1.0)) * 3
        return TestSetRecipe(name=f"{self.name}-heldout-v1", seed=20_000, episodes=mix)


@dataclass(frozen=True)
class LunarLanderContinuousSpec(LunarLanderSpec):
    """Continuous LunarLander: main and lateral engine throttles in [-1, 1]."""

    name: str = "lunar_lander_continuous"
    action_names: tuple[str, ...] = ("main", "lateral")
    n_discrete_actions: int = 0
    gym_kwargs: dict = field(default_factory=lambda: {"continuous": True})
