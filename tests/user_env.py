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
    steps = 0  # every instance's steps (the tests check that a check takes none)

    def __init__(self):
        self.observation_space = gym.spaces.Box(-100.0, 100.0, (2,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.state = np.zeros(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.state = np.array([self.np_random.uniform(-1, 1), 0.0])
        return self.state.astype(np.float32), {}

    def step(self, action):
        Oscillator.steps += 1
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


# ---------------------------------------------------------------------- an env with an event
FALLER_MODULE = '''
import gymnasium as gym
import numpy as np

G, DT, V_BREAK = 1.0, 0.05, 0.6


class Faller(gym.Env):
    """A body above a floor: height h >= 0, velocity v, thrust u in [-1, 1] (up to 0.8 up,
    1.8 extra down). Hitting the floor faster than V_BREAK breaks it (-10, the end); slower, it
    stops there (h = v = 0) and may lift off again."""

    def __init__(self):
        self.observation_space = gym.spaces.Box(np.array([0.0, -10.0], np.float32), np.array([10.0, 10.0], np.float32))
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.state = np.zeros(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.state = np.array([self.np_random.uniform(0.02, 0.6), 0.0])
        return self.state.astype(np.float32), {}

    def step(self, action):
        u = float(np.clip(np.asarray(action).reshape(-1)[0], -1.0, 1.0))
        h, v = self.state
        v2 = v + DT * (1.8 * u - G)
        h2 = h + DT * v2
        reward, done = -0.01, False
        if h > 0 and h2 <= 0:
            if v2 < -V_BREAK:
                reward, done = -10.0, True
            v2 = 0.0
        if h2 <= 0:
            h2, v2 = 0.0, max(v2, 0.0)
        self.state = np.array([h2, v2])
        return self.state.astype(np.float32), reward, done, False, {}


gym.register("Faller-v0", entry_point="faller_envs:Faller", max_episode_steps=100)
'''

FALLER_TASK = '''
import numpy as np


def reward(states, actions, next_states):
    return np.full(len(states), -0.01)


def impact(states, actions, next_states):
    """The step reaches the floor from above."""
    return (states[:, 0] > 0) & (next_states[:, 0] <= 0)


def initial_states(rng, n):
    return np.column_stack([rng.uniform(0.02, 0.6, n), np.zeros(n)])
'''

FALLER_YAML = '''
defaults:
  - override /library@_global_.library: polynomial
  - _self_
spec:
  _target_: sdrl_bench.envs.EnvSpec
  name: faller
  gym_id: faller_envs:Faller-v0
  state_names: [h, v]
  action_names: [u]
  action_encoding: clip
  state_low: [0.0, null]        # the floor: the env clips h there
  state_high: [null, null]
  max_episode_steps: 100
  reward_fn: faller_envs.task.reward
  initial_state_fn: faller_envs.task.initial_states
  events:
    - name: impact
      trigger: faller_envs.task.impact
      features: [v]
      once_per_episode: false
      min_events: 8
      outcomes:
        - {name: rest}
        - {name: break, ends: true, reward: -10.0, within: 1, observed_reward: -10.0}
n_transitions: 600
poly_degree: 1
trig_inputs: states
trig_frequencies: [1.0]
sindy: {threshold: 0.001, alpha: 0.0, normalize_columns: false}
'''


def write_faller_dir(root: Path) -> tuple[Path, Path]:
    """A user's env with an event no built-in env has (a floor impact that ends the episode
    above a speed): package ``faller_envs`` and ``conf/env/faller.yaml``; (src, conf)."""
    pkg = root / "src" / "faller_envs"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text(FALLER_MODULE)
    (pkg / "task.py").write_text(FALLER_TASK)
    conf = root / "conf" / "env"
    conf.mkdir(parents=True)
    (conf / "faller.yaml").write_text(FALLER_YAML)
    return root / "src", root / "conf"
