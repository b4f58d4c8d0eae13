"""Surrogate environments: a real env's task with a fitted dynamics model in place of its physics.

``Surrogate`` binds a model to an env spec once (validation, spaces, compiled evaluators) and
steps it: ``transition`` is the batched step that ``SurrogateVecEnv`` (``surrogate.vec``) uses,
and ``step_one`` the plain-Python step of one state that ``SurrogateEnv`` uses. A step is:

1. model inputs from (s, a) -> the model's prediction of the regressed variables;
2. **divergence guard**: a non-finite prediction, or one beyond ``spec.divergence_limit()``,
   ends the episode as *truncated* (not terminated: the task did not end, the model failed;
   an agent bootstraps from the last valid state, which is what it observes), with reward 0,
   ``info["surrogate_diverged"] = True`` and the env's ``n_diverged`` counter incremented;
3. the spec's bounds (``apply_bounds``, which also rounds to the real env's float32);
4. exogenous variables derived by the spec (LunarLander's leg contacts);
5. clipping to the real env's observation space (a no-op for MountainCar, whose bounds are
   the space; for LunarLander it keeps e.g. y <= 2.5, which the real lander never exceeds);
6. reward and termination from the spec's pure functions of (s, a, s'); truncation at the
   real env's step limit (999 MountainCar, 1000 LunarLander), as gymnasium's TimeLimit does.

``SurrogateEnv`` is registered as ``sdrl/Surrogate-v0`` (``import sdrl_bench`` first)::

    env = gym.make("sdrl/Surrogate-v0", model="model.json", spec="mountain_car")
    env = gym.make("sdrl/Surrogate-v0", model="model.json", spec="my_env", config_dir="my_conf")

A spec name is a spec class's or an ``env/<name>.yaml`` of the config tree (``envs.base.find_spec``).

States and observations: the surrogate steps the spec's states (the model's coordinates) and
emits the real env's observations (``EnvSpec.observe``: an angle's cos and sin, clipped to the
observation space); angles are wrapped to [-pi, pi) after each step.

Over the project's ~300-line habit: ``Surrogate`` (one step, its noise and disagreement
penalty) and ``SurrogateEnv`` are kept with the step they wrap; moving the uncertainty hooks to
their own module is the next tidy-up.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from sdrl_bench import ConfigError
from sdrl_bench.envs import EnvSpec
from sdrl_bench.envs.base import find_spec, observed_initial_states, wrap_angle
from sdrl_bench.models.base import load_model
from sdrl_bench.models.fast import batch_predictor, scalar_predictor

_SPACES: dict[tuple, tuple[gym.Space, gym.Space]] = {}


def resolve_spec(spec: EnvSpec | str, config_dir: str | None = None) -> EnvSpec:
    if isinstance(spec, str):
        return find_spec(spec, [config_dir] if config_dir else [])
    if not isinstance(spec, EnvSpec):
        raise ConfigError(f"spec: expected an EnvSpec or an env name, got {type(spec).__name__}")
    return spec


def real_spaces(spec: EnvSpec) -> tuple[gym.Space, gym.Space]:
    """(observation space, action space) of the real env, cached per env and process."""
    key = (spec.gym_id, repr(sorted(spec.gym_kwargs.items())))
    if key not in _SPACES:
        env = spec.make_env()
        _SPACES[key] = (env.observation_space, env.action_space)
        env.close()
    return _SPACES[key]


def _as_slice(index: np.ndarray) -> slice | np.ndarray:
    """``index`` as a slice if it is a contiguous ascending range, else unchanged."""
    index = np.asarray(index)
    if len(index) and np.array_equal(index, np.arange(index[0], index[0] + len(index))):
        return slice(int(index[0]), int(index[0]) + len(index))
    return index


class Surrogate:
    """A fitted dynamics model bound to an env spec, validated at construction.

    Parameters
    ----------
    model : a fitted model (``predict(x, u)``, ``state_names_``, ``control_names_``) or the path
        of a saved one.
    spec : an ``EnvSpec`` with a task (reward, termination), or the ``name`` of a spec class (``envs.base.find_spec``).
    initial_states : optional (K, n_state) states to reset from (uniformly); default: the spec's
        initial-state distribution.
    fused : use the spec's fused batched step when it has one (``EnvSpec.make_step_batch``);
        False composes the spec's numpy functions instead (same results; for comparisons).
    noise : add the model's step noise (``noise_``), seeded by ``seed_noise``; False: deterministic.
    penalty : apply the ensemble's disagreement penalty (``members_`` and the spec's
        ``uncertainty_scale``); False: the task's reward as it is.
    config_dir : a config directory holding ``env/<spec>.yaml``, for a spec given by name.
    """

    def __init__(self, model: Any, spec: EnvSpec | str, initial_states: np.ndarray | None = None,
                 fused: bool = True, noise: bool = True, penalty: bool = True, config_dir: str | None = None):
        self.spec = spec = resolve_spec(spec, config_dir)
        source = f"model file {model}" if isinstance(model, (str, Path)) else "model"
        self.model = model = load_model(model) if isinstance(model, (str, Path)) else model
        if not callable(getattr(model, "predict", None)) or not hasattr(model, "state_names_"):
            raise ConfigError(f"{source}: {type(model).__name__} is not a fitted dynamics model")
        for what, got, want in (("regresses states", model.state_names_, spec.target_names),
                                ("takes inputs", model.control_names_, spec.control_names)):
            if list(got) != list(want):
                raise ConfigError(f"{source} {what} {list(got)} ({len(got)}), but env.spec "
                                  f"'{spec.name}' needs {list(want)} ({len(want)})")
        if not spec.defines_task:
            raise ConfigError(f"env.spec.reward_fn: '{spec.name}' ({type(spec).__name__}) defines no reward / termination; "
                              "a surrogate needs env.spec.reward_fn (and termination_fn) or an EnvSpec subclass with reward()")
        self.observation_space, self.action_space = obs_space, act_space = real_spaces(spec)
        self._check_spaces(obs_space, act_space)
        self.obs_low, self.obs_high = obs_space.low.astype(float), obs_space.high.astype(float)
        # Clipping to the observation space is skipped when the spec bounds every variable inside it.
        # With an observation map the states are not observations: the spec's bounds (apply_bounds)
        # hold them, and the emitted observations are clipped to the space instead.
        inside = spec.state_low is not None and spec.state_high is not None and not spec.exogenous_names
        self._clip = not spec.maps_observations and not (inside and np.all(np.asarray(spec.state_low) >= self.obs_low)
                          and np.all(np.asarray(spec.state_high) <= self.obs_high))
        self.limit = np.asarray(spec.divergence_limit(), dtype=float)
        if self.limit.shape != (len(spec.target_names),) or not np.all(self.limit > 0):
            raise ConfigError(f"env.spec '{spec.name}': divergence_limit() must be positive, one per regressed state")
        self._initial = None
        if initial_states is not None:
            init = np.asarray(initial_states, dtype=float)
            if init.ndim != 2 or init.shape[1] != len(spec.state_names) or not len(init) or not np.all(np.isfinite(init)):
                raise ConfigError(f"initial_states: need a finite (K, {len(spec.state_names)}) array, got shape {init.shape}")
            self._initial = init
        # The default reset distribution (states observed after real resets), looked up once.
        self._pool = self._initial
        if self._pool is None and type(spec).initial_states is EnvSpec.initial_states and spec.initial_state_fn is None:
            self._pool = observed_initial_states(spec)
        self._setup_uncertainty(noise, penalty)
        self.step_one = spec.make_step_one(self.predictor, self.obs_low, self.obs_high) or self._generic_step_one
        self._step_batch = (spec.make_step_batch(self.limit, self.obs_low, self.obs_high, rng=lambda: self.noise_rng)
                            if fused else None)
        self.state_order = "F" if self._step_batch is None else "C"
        """Memory layout of the states ``transition`` returns (and steps fastest): a spec's fused
        step reads states row by row ("C"); the numpy composition works column by column ("F")."""
        # The batched step feeds the model input columns (EnvSpec.model_inputs, without copies).
        self._columnar = type(spec).model_inputs is EnvSpec.model_inputs
        self._predict_rows = batch_predictor(model)
        index = np.concatenate([spec.target_index, spec.exogenous_index])
        self._n_state_inputs = len(index)
        # slice(None) when the states are the model's first inputs, in order (no copy needed)
        self._input_index = slice(None) if np.array_equal(index, np.arange(len(index))) else index
        self._one_hot = spec.action_encoding == "one_hot" and type(spec).encode_actions is EnvSpec.encode_actions
        self._action_ids = np.arange(spec.n_discrete_actions)[:, None]
        self._limit_col = self.limit[:, None]
        # Columns of the regressed and the derived (exogenous) variables: slices where they are
        # contiguous (cheaper to assign than index arrays).
        self._targets, self._exogenous = _as_slice(spec.target_index), _as_slice(spec.exogenous_index)
        self._angles = spec.angle_index if len(spec.angle_index) else None
        if self._members:
            self.step_one = self._penalized_step_one(self.step_one)

    def _check_spaces(self, obs_space: gym.Space, act_space: gym.Space) -> None:
        spec = self.spec
        n = len(spec.obs_names)
        if not isinstance(obs_space, gym.spaces.Box) or obs_space.shape != (n,):
            key = "observation_names" if spec.maps_observations else "state_names"
            raise ConfigError(f"env.spec.{key}: {n} names for {spec.gym_id}'s observation space {obs_space}")
        observed = [i for i, name in enumerate(spec.state_names) if name in spec.obs_names]
        where = np.array([spec.obs_names.index(spec.state_names[i]) for i in observed], dtype=int)
        for key, bound in (("state_low", spec.state_low), ("state_high", spec.state_high)):
            if bound is None:
                continue
            b = np.asarray(bound)[observed].astype(obs_space.dtype)
            bad = np.flatnonzero(np.isfinite(b) & ((b < obs_space.low[where]) | (b > obs_space.high[where])))
            if len(bad):
                i, j = observed[int(bad[0])], int(where[bad[0]])
                raise ConfigError(f"env.spec.{key}[{i}] = {bound[i]} ({spec.state_names[i]}) lies outside "
                                  f"{spec.gym_id}'s observation space [{obs_space.low[j]}, {obs_space.high[j]}]")
        if isinstance(act_space, gym.spaces.Discrete):
            if spec.n_discrete_actions != act_space.n:
                raise ConfigError(f"env.spec.n_discrete_actions: {spec.n_discrete_actions}, but {spec.gym_id} has {act_space.n} actions")
        elif spec.n_discrete_actions or act_space.shape != (spec.raw_action_width,):
            raise ConfigError(f"env.spec.action_names: {len(spec.action_names)} names for {spec.gym_id}'s action space {act_space}")

    def observation(self, states: np.ndarray) -> np.ndarray:
        """States (N, n_state) -> the observations the agent sees (the real env's dtype)."""
        dtype = self.observation_space.dtype
        if not self.spec.maps_observations:
            return states.astype(dtype, order="C")
        return np.clip(self.spec.observe(states), self.obs_low, self.obs_high).astype(dtype)

    def predictor(self, fixed: dict[int, float] | None = None):
        """The model's fast one-state evaluator (see ``models.fast.scalar_predictor``), with the
        model's step noise for a discrete action held fixed (``noise_``)."""
        predict = scalar_predictor(self.model, fixed)
        chol = self._noise_for_fixed(fixed)
        if chol is None:
            return predict
        rng_of, m = (lambda: self.noise_rng), chol.shape[0]

        def noisy(z):
            out = predict(z)
            d = chol @ rng_of().standard_normal(m)
            return [v + float(e) for v, e in zip(out, d, strict=True)]

        return noisy

    def __reduce__(self):  # compiled functions are rebuilt, not pickled
        return (Surrogate, (self.model, self.spec, self._initial, self._step_batch is not None, self._noise_on,
                            self._penalty_on))

    # ------------------------------------------------------------------ noise and uncertainty
    def _setup_uncertainty(self, noise: bool, penalty: bool) -> None:
        """Step noise (``model.noise_``: {one-hot action column: covariance of the fit's
        residuals}; the engine dispersion of LunarLander) and the ensemble's disagreement
        penalty (``model.members_`` with ``spec.uncertainty_scale()``)."""
        spec, model = self.spec, self.model
        self._noise_on, self._penalty_on = bool(noise), bool(penalty)
        self.noise_rng = np.random.default_rng()
        self._chol: np.ndarray | None = None
        cov = getattr(model, "noise_", None) or {}
        if noise and cov and spec.n_discrete_actions:
            m = len(spec.target_names)
            chol = np.zeros((spec.n_discrete_actions, m, m))
            for name, c in cov.items():
                if name in spec.action_names:
                    c = np.asarray(c, dtype=float)
                    w, v = np.linalg.eigh((c + c.T) / 2)  # PSD square root (covariances may be singular)
                    chol[spec.action_names.index(name)] = v * np.sqrt(np.clip(w, 0.0, None))
            self._chol = chol if np.any(chol) else None
        self._members: list = []
        scale = spec.uncertainty_scale() if penalty else None
        members = getattr(model, "members_", None) or []
        if scale is not None and len(members) > 1:
            self._scale = np.asarray(scale, dtype=float)[:, None]
            shim = [type("Member", (), {"terms_": model.terms_, "coef_": np.asarray(c), "state_names_": model.state_names_,
                                        "control_names_": model.control_names_})() for c in members]
            self._members = [batch_predictor(mb) for mb in shim]
            self._penalty = float(getattr(spec, "uncertainty_penalty", 0.0))
            self._limit_u = float(getattr(spec, "uncertainty_limit", np.inf))
            self._free = float(getattr(spec, "uncertainty_free", 0.0))

    def seed_noise(self, seed: Any) -> None:
        """Seed the step noise (same seed and actions: the same trajectory)."""
        self.noise_rng = np.random.default_rng(seed)

    def _noise_for_fixed(self, fixed: dict[int, float] | None) -> np.ndarray | None:
        if self._chol is None or not fixed:
            return None
        first = len(self.spec.input_names) - self.spec.n_discrete_actions
        hot = [i - first for i, v in fixed.items() if i >= first and v == 1.0]
        return self._chol[hot[0]] if len(hot) == 1 and np.any(self._chol[hot[0]]) else None

    def disagreement(self, z: np.ndarray) -> np.ndarray:
        """(N,) the ensemble's disagreement at model inputs z (n_inputs, N): the largest over
        regressed states of the members' standard deviation, in units of the spec's scale."""
        preds = np.stack([p(z) for p in self._members])
        return (preds.std(axis=0) / self._scale).max(axis=0)

    def _penalize(self, states, z, nxt, rewards, terminated, diverged):
        """MOPO-style: in flight (the model's regime: the spec's regime_dynamics leaves a row to
        the model when its prediction passes through unchanged), reward minus penalty x
        disagreement; beyond the limit the episode ends as a crash (-100)."""
        u = self.disagreement(z)
        flight = ~diverged & ~terminated
        if hasattr(self.spec, "rules"):  # LunarLander: legs up in s
            flight &= (states[:, 6] <= 0.5) & (states[:, 7] <= 0.5)
        rewards = np.where(flight, rewards - self._penalty * np.maximum(u - self._free, 0.0), rewards)
        over = flight & (u > self._limit_u)
        if over.any():
            rewards = np.where(over, -100.0, rewards)
            terminated = terminated | over
        return rewards, terminated

    def _penalized_step_one(self, step_one):
        n_s = self._n_state_inputs

        def step(state, action):
            obs, nxt, r, term, div = step_one(state, action)
            if div or term:
                return obs, nxt, r, term, div
            s = np.asarray([state], dtype=float)
            z = np.empty((n_s + len(self.spec.action_names), 1))
            z[:n_s] = s.T[self._input_index]
            z[n_s:] = self.spec.encode_actions(self.raw_actions(action, 1)).T
            rew, ter = self._penalize(s, z, np.asarray([nxt]), np.array([r]), np.array([False]), np.array([False]))
            return obs, nxt, float(rew[0]), bool(ter[0]), div

        return step

    def _add_noise(self, rows: np.ndarray, actions: np.ndarray) -> np.ndarray:
        a = np.asarray(actions).reshape(len(actions), -1)[:, 0].astype(np.intp)
        eps = self.noise_rng.standard_normal((len(a), rows.shape[0]))
        return rows + np.einsum("nij,nj->in", self._chol[a], eps)

    # ------------------------------------------------------------------ stepping
    def initial_states(self, rng: np.random.Generator, n: int) -> np.ndarray:
        if self._pool is not None:  # the same draws as EnvSpec.initial_states
            return self._pool[rng.integers(len(self._pool), size=n)]
        return self.spec.initial_states(rng, n)

    def raw_actions(self, actions: Any, n: int) -> np.ndarray:
        """Actions as (n, raw width) floats (integer arrays of discrete actions stay integers);
        discrete actions must be valid indices."""
        raw = np.asarray(actions)
        k = self.spec.n_discrete_actions
        if k and raw.dtype.kind in "iu":  # integer indices stay integers (no float copy)
            a = raw.reshape(n, 1)
            if a.min() < 0 or a.max() >= k:
                raise ValueError(f"actions must be integers in [0, {k}), got {actions!r}")
            return a
        a = raw.astype(float).reshape(n, self.spec.raw_action_width)
        if k and (a.min() < 0 or a.max() >= k or (raw.dtype.kind != "b" and np.any(a != np.round(a)))):
            raise ValueError(f"actions must be integers in [0, {k}), got {actions!r}")
        return a

    def transition(self, states: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, ...]:
        """One batched step: (next states, rewards, terminated, diverged), all (N, ...).

        Diverged rows keep their state, get reward 0 and terminated False (see module doc).
        The next states are laid out in ``state_order``: Fortran order (each variable a
        contiguous column) for the numpy composition, C order from a spec's fused step.
        """
        spec, states = self.spec, np.asarray(states, dtype=float)
        with np.errstate(all="ignore"):
            if self._columnar:  # model inputs as rows of z (inputs x N) -> predictions (m, N)
                n_s = self._n_state_inputs
                z = np.empty((n_s + len(spec.action_names), len(states)))
                z[:n_s] = states.T[self._input_index]
                if self._one_hot:
                    np.equal(actions[:, 0], self._action_ids, out=z[n_s:], casting="unsafe")
                else:
                    z[n_s:] = spec.encode_actions(actions).T
                rows = self._predict_rows(z)
            else:
                z = None
                rows = np.asarray(self.model.predict(*spec.model_inputs(states, actions)), dtype=float).T
            if self._chol is not None:  # the step noise (e.g. engine dispersion), seeded
                rows = self._add_noise(rows, actions)
            if type(spec).regime_dynamics is not EnvSpec.regime_dynamics:
                rows = spec.regime_dynamics(states, actions, rows)
            if self._step_batch is not None:  # the spec's fused step does the rest
                out = self._step_batch(states, actions, rows)
                if self._members and z is not None:
                    rewards, terminated = self._penalize(states, z, *out)
                    out = (out[0], rewards, terminated, out[3])
                return out
            ok = (np.abs(rows) <= self._limit_col).all(axis=0)  # False for NaN and inf
        bad = None if ok.all() else np.flatnonzero(~ok)
        pred = rows.T  # (N, m), Fortran order
        if bad is not None:  # placeholders (the current state) so that the rules see finite values
            pred = np.array(pred, order="F")
            pred[bad] = states[bad][:, spec.target_index]
        nxt = np.array(states, order="F")  # columns contiguous: cheap per-variable work
        nxt[:, self._targets] = spec.apply_bounds(states, pred)
        if spec.exogenous_names:
            nxt[:, self._exogenous] = spec.exogenous(states, actions, nxt)
        if self._clip:  # only the columns that leave the space (np.clip on all is slow)
            outside = (nxt.min(axis=0) < self.obs_low) | (nxt.max(axis=0) > self.obs_high)
            for j in np.flatnonzero(outside):
                np.clip(nxt[:, j], self.obs_low[j], self.obs_high[j], out=nxt[:, j])
        if self._angles is not None:
            nxt[:, self._angles] = wrap_angle(nxt[:, self._angles])
        rewards, terminated = spec.reward_terminated(states, actions, nxt)
        rewards = np.asarray(rewards, dtype=float)
        terminated = np.asarray(terminated, dtype=bool)
        if bad is not None:
            rewards, terminated = rewards.copy(), terminated.copy()
            nxt[bad] = states[bad]
            rewards[bad], terminated[bad] = 0.0, False
        return nxt, rewards, terminated, ~ok

    def _generic_step_one(self, state: list, action: Any):
        s = np.asarray([state], dtype=float)
        nxt, r, term, div = self.transition(s, self.raw_actions(action, 1))
        return self.observation(nxt[:1])[0], nxt[0].tolist(), float(r[0]), bool(term[0]), bool(div[0])


class SurrogateEnv(gym.Env):
    """A gymnasium env stepping a fitted dynamics model with the real env's task and spaces.

    ``reset(options={"state": s})`` starts from a given state; ``n_diverged`` counts episodes
    ended by the divergence guard. Same arguments as ``Surrogate``.
    """

    metadata = {"render_modes": []}

    def __init__(self, model: Any, spec: EnvSpec | str, initial_states: np.ndarray | None = None,
                 render_mode: str | None = None, config_dir: str | None = None):
        if render_mode is not None:
            raise ConfigError(f"render_mode: the surrogate env does not render ({render_mode!r})")
        self.surrogate = Surrogate(model, spec, initial_states, config_dir=config_dir)
        self.observation_space = self.surrogate.observation_space
        self.action_space = self.surrogate.action_space
        self.render_mode = None
        self.n_diverged = 0
        self._step_one = self.surrogate.step_one
        self._max_steps = self.surrogate.spec.max_episode_steps
        self._state: list | None = None
        self._t = 0

    @property
    def env_spec(self) -> EnvSpec:
        return self.surrogate.spec

    def __getstate__(self) -> dict:  # the compiled step is rebuilt, not pickled
        return {k: v for k, v in self.__dict__.items() if k != "_step_one"}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._step_one = self.surrogate.step_one

    @property
    def state(self) -> np.ndarray | None:
        return None if self._state is None else np.array(self._state, dtype=float)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:  # the step noise too: same seed and actions, same episode
            self.surrogate.seed_noise(seed)
        if options and "state" in options:  # a state (state_names order), not an observation
            s = np.asarray(options["state"], dtype=float)
            shape = (len(self.surrogate.spec.state_names),)
            if s.shape != shape or not np.all(np.isfinite(s)):
                raise ValueError(f"options['state'] must be a finite array of shape {shape}")
        else:
            s = self.surrogate.initial_states(self.np_random, 1)[0]
        # numpy scalars, as the real env keeps its state (float64 after a reset): a spec's
        # one-state step may compute in the real env's arithmetic (see MountainCarSpec)
        self._state, self._t = list(s), 0
        return self.surrogate.observation(s[None])[0], {}

    def step(self, action: Any):
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        obs, nxt, reward, terminated, diverged = self._step_one(self._state, action)
        self._t += 1
        if diverged:
            self.n_diverged += 1
            return obs, 0.0, False, True, {"surrogate_diverged": True}
        self._state = nxt
        return obs, reward, terminated, self._t >= self._max_steps, {}
