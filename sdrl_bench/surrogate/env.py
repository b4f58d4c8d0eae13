"""The single surrogate env: a gymnasium env over one ``ModelEnv`` (``surrogate.model_env``).

It keeps one episode (its state, step count, truncation at the real env's limit) and steps it
with ``ModelEnv.step_one``, the same step the vector env and Dyna use. Registered as
``sdrl/Surrogate-v0`` (``import sdrl_bench`` first)::

    env = gym.make("sdrl/Surrogate-v0", model="model.json", spec="my_env")
    env = gym.make("sdrl/Surrogate-v0", model="model.json", spec="my_env", config_dir="my_conf")

A spec name is an ``env/<name>.yaml`` of the config tree (``envs.base.find_spec``).

States and observations: the surrogate steps the spec's states (the model's coordinates) and
emits the real env's observations (an angle's cos and sin, clipped to the observation space).
A diverged step (the model left its divergence limit) ends the episode as truncated, reward 0,
``info["surrogate_diverged"] = True``, and counts in ``n_diverged``.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from sdrl_bench import ConfigError
from sdrl_bench.envs.base import EnvSpec
from sdrl_bench.surrogate.model_env import ModelEnv


class SurrogateEnv(gym.Env):
    """A gymnasium env stepping a fitted dynamics model with the real env's task and spaces.

    ``reset(options={"state": s})`` starts from a given state; ``n_diverged`` counts episodes
    ended by the divergence guard. Same arguments as ``Surrogate``.
    """

    metadata = {"render_modes": []}

    def __init__(self, model: Any, spec: EnvSpec | str | None = None, initial_states: np.ndarray | None = None,
                 render_mode: str | None = None, config_dir: str | None = None, events: dict | None = None,
                 seed: int | None = None):
        if render_mode is not None:
            raise ConfigError(f"render_mode: the surrogate env does not render ({render_mode!r})")
        if isinstance(model, ModelEnv) and spec is None:
            self.surrogate = model
        else:
            self.surrogate = ModelEnv(model, spec, initial_states, events=events, seed=seed, config_dir=config_dir)
        self.observation_space = self.surrogate.observation_space
        self.action_space = self.surrogate.action_space
        self.render_mode = None
        self.n_diverged = 0
        self._max_steps = self.surrogate.spec.max_episode_steps
        self._state: list | None = None
        self._t = 0

    @property
    def env_spec(self) -> EnvSpec:
        return self.surrogate.spec

    @property
    def state(self) -> np.ndarray | None:
        return None if self._state is None else np.array(self._state, dtype=float)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:  # every stream: same seed and actions, same episode
            self.surrogate.seed(seed)
        if options and "state" in options:  # a state (state_names order), not an observation
            s = np.asarray(options["state"], dtype=float)
            shape = (len(self.surrogate.spec.state_names),)
            if s.shape != shape or not np.all(np.isfinite(s)):
                raise ValueError(f"options['state'] must be a finite array of shape {shape}")
        else:
            s = self.surrogate.initial_states(1)[0]
        # numpy scalars, as the real env keeps its state (float64 after a reset): a spec's
        # one-state step may compute in the real env's arithmetic (see MountainCarSpec)
        self._state, self._t = list(s), 0
        return self.surrogate.observation(s[None])[0], {}

    def step(self, action: Any):
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        obs, nxt, reward, terminated, diverged = self.surrogate.step_one(self._state, action)
        self._t += 1
        if diverged:
            self.n_diverged += 1
            return obs, 0.0, False, True, {"surrogate_diverged": True}
        self._state = nxt
        return obs, reward, terminated, self._t >= self._max_steps, {}
