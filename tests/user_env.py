"""A user's own environment, written into a temp directory as a user would lay it out: a package
``my_envs`` that registers ``Oscillator-v0`` with gymnasium (an env gymnasium does not ship, of
known law) with its task functions, and ``conf/env/oscillator.yaml`` for ``--config-dir``.

Law (float64 inside, float32 observations): x' = x + 0.1 v, v' = v - 0.1 x + 0.1 clip(u, -1, 1);
reward -x^2; 50 steps; reset x ~ U[-1, 1], v = 0.
"""

from __future__ import annotations

from pathlib import Path

MODULE = '''
import gymnasium as gym
import numpy as np


class Oscillator(gym.Env):
    def __init__(self):
        self.observation_space = gym.spaces.Box(-100.0, 100.0, (2,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.state = np.zeros(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.state = np.array([self.np_random.uniform(-1, 1), 0.0])
        return self.state.astype(np.float32), {}

    def step(self, action):
        u = float(np.clip(np.asarray(action).reshape(-1)[0], -1.0, 1.0))
        x, v = self.state
        reward = -x * x
        self.state = np.array([x + 0.1 * v, v - 0.1 * x + 0.1 * u])
        return self.state.astype(np.float32), reward, False, False, {}


gym.register("Oscillator-v0", entry_point="my_envs:Oscillator", max_episode_steps=50)
'''

TASK = '''
import numpy as np


def reward(states, actions, next_states):
    return -states[:, 0] ** 2


def initial_states(rng, n):
    return np.column_stack([rng.uniform(-1, 1, n), np.zeros(n)])
'''

YAML = '''
defaults:
  - override /library@_global_.library: polynomial
  - _self_
spec:
  _target_: sdrl_bench.envs.EnvSpec
  name: oscillator
  gym_id: my_envs:Oscillator-v0
  state_names: [x, v]
  action_names: [u]
  action_encoding: clip
  max_episode_steps: 50
  reward_fn: my_envs.task.reward
  initial_state_fn: my_envs.task.initial_states
n_transitions: 60
poly_degree: 1
trig_inputs: states
trig_frequencies: [1.0]
sindy: {threshold: 0.01, alpha: 0.0, normalize_columns: false}
'''

LAW = {"x": {"x": 1.0, "v": 0.1}, "v": {"x": -0.1, "v": 1.0, "u": 0.1}}


def write_user_dir(root: Path) -> tuple[Path, Path]:
    """(the directory to put on PYTHONPATH, the config dir for --config-dir)."""
    pkg = root / "src" / "my_envs"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text(MODULE)
    (pkg / "task.py").write_text(TASK)
    conf = root / "conf" / "env"
    conf.mkdir(parents=True)
    (conf / "oscillator.yaml").write_text(YAML)
    return root / "src", root / "conf"
