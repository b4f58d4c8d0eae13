"""SurrogateVecEnv: N copies of a surrogate env stepped by one batched model evaluation.

A stable-baselines3 ``VecEnv`` (SB3 does not take gymnasium's VectorEnv), so SB3 agents and
wrappers (VecMonitor, VecNormalize, ...) use it as they use a DummyVecEnv of real envs:

* ``step`` returns float32 observations, float32 rewards, ``dones`` and one info dict per env;
  a finished env is reset at once (auto-reset): its info holds ``terminal_observation`` and
  ``TimeLimit.truncated`` (truncated by the step limit or the divergence guard, and not
  terminated), plus ``surrogate_diverged`` when the model diverged. Envs still running share
  one empty, read-only info dict (``RUNNING_INFO``; SB3 only writes into finished envs' infos).
* One step for all copies: ``ModelEnv.step`` (or its one-state step per copy for a few copies),
  the same step the single env and Dyna use: noise, pessimism and learned events included.
* Seeding: ``seed(s)`` (or the ``seed`` argument) seeds the surrogate's streams at the next
  ``reset()`` (resets of every copy, step noise, event draws); same seed and actions, same
  trajectories.
* ``get_attr`` / ``set_attr`` / ``env_method`` act on light per-copy views (``SurrogateEnvView``:
  ``state``, ``elapsed_steps``, ``n_diverged``, ``reset()``, the spaces, the model and spec);
  ``env_is_wrapped`` is False (no gymnasium wrappers inside).
"""

from __future__ import annotations

from typing import Any
from collections.abc import Iterable

import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices

from sdrl_bench.envs.base import EnvSpec
from sdrl_bench.surrogate.model_env import ModelEnv


SCALAR_MAX_ENVS = 8
"""Up to this many copies, ``step`` runs the plain-Python one-state step per copy."""


class _RunningInfo(dict):
    """The info of every copy that did not finish this step: one shared, empty, read-only dict.

    Creating N fresh dicts per step costs as much as the model evaluation itself at N = 1024.
    SB3 writes only into the infos of finished envs (which get their own dicts); any write here
    raises instead of leaking into other copies' infos.
    """

    def _read_only(self, *args: Any, **kwargs: Any):
        raise TypeError("SurrogateVecEnv: the info of a running env is shared and read-only; use dict(info)")

    __setitem__ = __delitem__ = __ior__ = update = setdefault = pop = popitem = clear = _read_only


RUNNING_INFO = _RunningInfo()


class SurrogateEnvView:
    """One copy of a ``SurrogateVecEnv``, as ``get_attr`` / ``set_attr`` / ``env_method`` see it.

    Reads and writes go to the vectorized env's arrays; other attributes set with ``set_attr``
    are kept on the view (as they would be on a gymnasium env).
    """

    render_mode = None
    spec = None  # gymnasium's registration spec (none: not made by gym.make)

    def __init__(self, venv: SurrogateVecEnv, index: int):
        self._venv, self._index = venv, index

    observation_space = property(lambda self: self._venv.observation_space)
    action_space = property(lambda self: self._venv.action_space)
    env_spec = property(lambda self: self._venv.surrogate.spec)
    model = property(lambda self: self._venv.surrogate.model)
    elapsed_steps = property(lambda self: int(self._venv._t[self._index]))
    n_diverged = property(lambda self: int(self._venv.n_diverged[self._index]))

    @property
    def state(self) -> np.ndarray:
        return self._venv._states[self._index].copy()

    @state.setter
    def state(self, value: Any) -> None:
        value = np.asarray(value, dtype=float)
        if value.shape != self._venv._states.shape[1:] or not np.all(np.isfinite(value)):
            raise ValueError(f"state must be a finite array of shape {self._venv._states.shape[1:]}")
        self._venv._states[self._index] = value

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        """Start this copy's episode again (from ``options["state"]`` if given)."""
        v = self._venv
        rng = np.random.default_rng(seed) if seed is not None else None
        self.state = options["state"] if options and "state" in options else v.surrogate.initial_states(1, rng)[0]
        v._t[self._index] = 0
        return v.surrogate.observation(v._states[self._index][None])[0], {}


class SurrogateVecEnv(VecEnv):
    """``n_envs`` surrogate envs over one ``ModelEnv``; see the module docstring for the contract.

    Parameters
    ----------
    model, spec, initial_states, events : as for ``sdrl_bench.surrogate.model_env.ModelEnv`` (or
        pass a built ``ModelEnv`` as ``model`` and leave ``spec`` None).
    n_envs : number of copies.
    seed : the run seed (reset pool, random streams; None: fresh entropy).
    scalar_max_envs : up to this many copies, each steps by the one-state step
        (``ModelEnv.step_one``; same results to rounding), else all by the batched one.
    """

    def __init__(self, model: Any, spec: EnvSpec | str | None = None, n_envs: int = 1, *,
                 seed: int | None = None, initial_states: np.ndarray | None = None, events: dict | None = None,
                 scalar_max_envs: int = SCALAR_MAX_ENVS):
        if isinstance(model, ModelEnv) and spec is None:
            self.surrogate = model
            if seed is not None:
                model.seed(seed)
        else:
            self.surrogate = ModelEnv(model, spec, initial_states, events=events, seed=seed)
        if int(n_envs) < 1:
            raise ValueError(f"n_envs must be >= 1, got {n_envs}")
        n = int(n_envs)
        sur = self.surrogate
        self._views = [SurrogateEnvView(self, i) for i in range(n)]
        super().__init__(n, sur.observation_space, sur.action_space)
        self._scalar = n <= scalar_max_envs
        self._states = np.asarray(sur.initial_states(n), order=sur.state_order)
        self._t = np.zeros(n, dtype=np.int64)
        self._max_steps = sur.spec.max_episode_steps
        self.n_diverged = np.zeros(n, dtype=np.int64)
        """Episodes ended by the divergence guard, per copy."""
        self._actions: np.ndarray | None = None
        self.closed = False

    def swap_model(self, model: Any, events: dict | None = None, seed: int | None = None,
                   spec: EnvSpec | None = None) -> None:
        """Step on with a refitted ``model`` (and learned event models, and the spec with the
        constants learned from the same data): Dyna swaps the surrogate under an agent that keeps
        training. Episodes under way go on from their current states; the surrogate's flags
        stay; ``seed`` reseeds its streams (``ModelEnv.swap``)."""
        self.surrogate.swap(model, events, seed, spec)
        self._states = np.asarray(self._states, order=self.surrogate.state_order)

    @property
    def event_counts(self) -> dict[str, dict[str, int]]:
        """Learned-event outcomes drawn so far (``ModelEnv.event_counts``)."""
        return self.surrogate.event_counts

    @property
    def env_spec(self) -> EnvSpec:
        return self.surrogate.spec

    # ------------------------------------------------------------------ the VecEnv API
    def reset(self) -> np.ndarray:
        seeds = [s for s in self._seeds if s is not None]
        if seeds:  # SB3 seeds copy i with seed + i: the first copy's seed seeds the streams
            self.surrogate.seed(seeds[0])
        self._states = np.asarray(self.surrogate.initial_states(self.num_envs), order=self.surrogate.state_order)
        self._t[:] = 0
        self._reset_seeds()
        self._reset_options()
        self.reset_infos = [{} for _ in range(self.num_envs)]
        return self.surrogate.observation(self._states)

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = self.surrogate.raw_actions(actions, self.num_envs)

    def _transition_each(self, actions: np.ndarray) -> tuple[np.ndarray, ...]:
        """``ModelEnv.step`` by the one-state step, env by env: for a few envs, numpy's
        per-call overhead costs more than the plain-Python step (same results to rounding)."""
        step_one, rows = self.surrogate.step_one, self._states.tolist()
        acts = actions.astype(int).ravel().tolist() if self.surrogate.spec.n_discrete_actions else actions
        out = [step_one(rows[i], acts[i]) for i in range(self.num_envs)]
        nxt = np.array([o[1] for o in out], dtype=float, order=self.surrogate.state_order)
        rewards = np.array([o[2] for o in out], dtype=float)
        return nxt, rewards, np.array([o[3] for o in out], dtype=bool), np.array([o[4] for o in out], dtype=bool)

    def step_wait(self):
        if self._actions is None:
            raise RuntimeError("step_wait() called without step_async()")
        if self._scalar:
            nxt, rewards, terminated, diverged = self._transition_each(self._actions)
        else:
            nxt, rewards, terminated, diverged = self.surrogate.step(self._states, self._actions)
        self._actions = None
        self._t += 1
        truncated = (self._t >= self._max_steps) | diverged
        dones = terminated | truncated
        obs = self.surrogate.observation(nxt)
        infos: list[dict[str, Any]] = [RUNNING_INFO] * self.num_envs
        if dones.any():
            idx = np.flatnonzero(dones)
            final = obs[idx]  # a copy: its rows stay the terminal observations
            timeouts = (truncated & ~terminated)[idx].tolist()
            for i, o, timeout, div in zip(idx.tolist(), final, timeouts, diverged[idx].tolist(), strict=False):
                infos[i] = {"terminal_observation": o, "TimeLimit.truncated": timeout}
                if div:
                    infos[i]["surrogate_diverged"] = True
            self.n_diverged += diverged
            fresh = self.surrogate.initial_states(len(idx))
            nxt[idx] = fresh
            obs[idx] = self.surrogate.observation(fresh)
            self._t[idx] = 0
        self._states = nxt
        return obs, rewards.astype(np.float32), dones, infos

    def close(self) -> None:
        self.closed = True

    def _indices(self, indices: VecEnvIndices) -> Iterable[int]:
        if indices is None:
            return range(self.num_envs)
        if isinstance(indices, (int, np.integer)):
            return [int(indices)]
        return [int(i) for i in indices]

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return [getattr(self._views[i], attr_name) for i in self._indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        for i in self._indices(indices):
            setattr(self._views[i], attr_name, value)

    def env_method(self, method_name: str, *method_args, indices: VecEnvIndices = None, **method_kwargs) -> list[Any]:
        return [getattr(self._views[i], method_name)(*method_args, **method_kwargs) for i in self._indices(indices)]

    def env_is_wrapped(self, wrapper_class: type, indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._indices(indices)]

    def get_images(self) -> list[None]:
        return [None for _ in range(self.num_envs)]
