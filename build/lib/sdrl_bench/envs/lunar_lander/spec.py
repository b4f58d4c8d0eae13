"""LunarLander-v3, discrete (four actions, one-hot encoded as model inputs) or continuous.

The real env does not clip its observation, so no bounds are applied after a predicted step.
The two leg-contact flags are booleans: the dynamics model takes them as given inputs
(``exogenous_names``) and never regresses them; the surrogate environment derives them
(``lunar_lander_task``: leg contacts, crash and rest are approximated there, and documented).
Engine impulses carry random dispersion and the terrain is random per episode, so one-step
prediction has a noise floor no deterministic model beats (measured by replay: README, fidelity results).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar
from collections.abc import Callable

import numpy as np
from gymnasium.envs.box2d.lunar_lander import heuristic

from sdrl_bench.envs.lunar_lander import task
from sdrl_bench.envs.base import EnvSpec, Policy, StepOne, TestSetRecipe
from sdrl_bench.envs.lunar_lander.task import LanderRules

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
    rules: LanderRules = LanderRules()
    """Constants of the surrogate's contact approximations (legs, crash, rest)."""
    action_labels: tuple[str, ...] = ("noop", "left engine", "main engine", "right engine")
    # policy maps: a lander descending slowly above the pad, legs up, over three slices
    policy_map_slices: tuple = (("x", (-1.0, 1.0), "y", (0.0, 1.4)), ("vx", (-1.0, 1.0), "vy", (-1.5, 0.5)),
                                ("angle", (-0.8, 0.8), "angvel", (-1.0, 1.0)))
    policy_map_hold: dict = field(default_factory=lambda: {"y": 0.7, "vy": -0.3})

    has_task: ClassVar[bool] = True

    def heuristic_policy(self, env) -> Policy:
        """gymnasium's built-in heuristic lander controller."""

        def policy(obs: np.ndarray):
            return heuristic(env, obs)

        return policy

    def divergence_limit(self) -> np.ndarray:
        # x, y in about +-2.5 (|x| >= 1 ends an episode), velocities and angle rates in +-10.
        return np.array([25.0, 25.0, 100.0, 100.0, 100.0, 100.0])

    # ------------------------------------------------------------------ the task
    def reward(self, states: np.ndarray, actions: np.ndarray, next_states: np.ndarray) -> np.ndarray:
        return task.reward(self.rules, bool(self.n_discrete_actions), states, actions, next_states)

    def terminated(self, states: np.ndarray, actions: np.ndarray, next_states: np.ndarray) -> np.ndarray:
        return task.terminated(self.rules, states, actions, next_states)

    def reward_terminated(self, states, actions, next_states) -> tuple[np.ndarray, np.ndarray]:
        return task.reward_terminated(self.rules, bool(self.n_discrete_actions), states, actions, next_states)

    def termination_causes(self, states, actions, next_states) -> dict[str, np.ndarray]:
        """Why the surrogate ends each transition: crash (or |x'| >= 1) and rest."""
        crash, out, rest = task.events(self.rules, states, next_states)
        return {"crash": crash | out, "rest": rest}

    def observed_termination_causes(self, rewards: np.ndarray, terminated: np.ndarray) -> dict[str, np.ndarray]:
        """Why the real env ended each transition, read off its reward (-100 crash or out, +100 rest)."""
        return {"crash": terminated & (rewards == -100), "rest": terminated & (rewards == 100)}

    def exogenous(self, states: np.ndarray, actions: np.ndarray, next_states: np.ndarray) -> np.ndarray:
        """Leg contacts derived from height and attitude (never regressed)."""
        return task.leg_contacts(self.rules, states, next_states)

    def make_step_one(self, predictor: Callable[..., Callable], obs_low=None, obs_high=None) -> StepOne:
        n = len(self.state_names)
        low = obs_low if obs_low is not None else [-np.inf] * n
        high = obs_high if obs_high is not None else [np.inf] * n
        return task.make_step_one(
            self.rules, bool(self.n_discrete_actions), predictor, self.divergence_limit(), low, high
        )

    def make_step_batch(self, limit, obs_low, obs_high) -> Callable:
        return task.make_step_batch(self.rules, bool(self.n_discrete_actions), limit, obs_low, obs_high)

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
    action_labels: tuple[str, ...] = ()
    gym_kwargs: dict = field(default_factory=lambda: {"continuous": True})

    def encode_actions(self, actions: np.ndarray) -> np.ndarray:
        """Throttles as the real env uses them: clipped to [-1, 1]."""
        return np.clip(super().encode_actions(actions), -1.0, 1.0)
