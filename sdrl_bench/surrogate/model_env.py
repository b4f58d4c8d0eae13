"""The model-based env core: a fitted dynamics model + the env's injected task, one step function.

``ModelEnv`` (after mbrl-lib's ``ModelEnv``, batched) binds a model to an env spec's task
(``envs.task.Task``) once: validation, spaces, compiled evaluators, kernels, its random streams.
Its ``step`` is *the* surrogate step; the single env (``surrogate.env``), the vector env
(``surrogate.vec``), evaluation inside a surrogate and Dyna all step through it, so noise,
pessimism, learned events and kernels are the same everywhere and survive a model swap
(``swap``). A step of N states:

1. model inputs from (s, a) -> the model's prediction of the regressed variables, plus its step
   noise (``model.noise_``: a covariance per one-hot action; drawn from the ``noise`` stream);
2. the task's ``regime_dynamics`` (outside the model's regime, e.g. a lander on its legs);
3. **divergence guard**: a non-finite prediction, or one beyond ``spec.divergence_limit()``,
   ends the episode as *truncated* (the model failed, the task did not end), reward 0, the
   state kept;
4. the spec's bounds (``apply_bounds``, which also rounds to the real env's float32), the
   task's exogenous variables, clipping to the real env's observation space, angles wrapped;
5. the task's reward and termination;
6. **pessimism** (``task.uncertainty``, MOPO): in the model's regime (``task.model_regime``),
   reward minus penalty x the ensemble's disagreement beyond a free band; beyond the limit the
   episode ends with the task's ``crash_reward``;
7. **learned events** (``surrogate.events``): on rows where a declared event triggers and the
   task did not end the episode, the event's outcome is drawn from the model learned from the
   run's own real transitions (``events`` stream); an outcome that ends the episode sets its
   reward. Counted per outcome (``event_counts``).

Steps 3-5 may run in the task's kernels (``task.step_batch``: one compiled loop; ``task.step_one``:
plain Python for one state, which a single env uses, e.g. to replay a real env bit for bit); the
generic steps 1, 2, 6 and 7 wrap them identically. The one-state path agrees with the batched one
to rounding (the tests check both with noise, pessimism and events on).

Random streams (``seed``): ``init`` (resets), ``noise`` and ``events``, derived from the seed
through ``seeds`` (purpose ``surrogate``). The reset pool (when the task has no reset
distribution: the real env's first observations) is drawn once, from the run seed the env is
built with.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from sdrl_bench import ConfigError, seeds
from sdrl_bench.envs.base import EnvSpec, find_spec, observed_initial_states, wrap_angle
from sdrl_bench.models.base import load_model
from sdrl_bench.models.fast import batch_predictor, scalar_predictor

_SPACES: dict[tuple, tuple[gym.Space, gym.Space]] = {}
STREAMS = ("init", "noise", "events")


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


def check_model(model: Any, spec: EnvSpec, source: str = "model") -> Any:
    """The model (loaded from a path), checked against the spec's regressed states and inputs."""
    if isinstance(model, (str, Path)):
        source, model = f"model file {model}", load_model(model)
    if not callable(getattr(model, "predict", None)) or not hasattr(model, "state_names_"):
        raise ConfigError(f"{source}: {type(model).__name__} is not a fitted dynamics model")
    for what, got, want in (("regresses states", model.state_names_, spec.target_names),
                            ("takes inputs", model.control_names_, spec.control_names)):
        if list(got) != list(want):
            raise ConfigError(f"{source} {what} {list(got)} ({len(got)}), but env.spec "
                              f"'{spec.name}' needs {list(want)} ({len(want)})")
    return model


NO_MEMBERS = "none: the model has no members"
"""The pessimism of a model without a spread estimate (one MLP), as runs and surrogates state it."""


def member_predictors(model: Any) -> list:
    """One batched predictor (``models.fast.batch_predictor``) per ensemble member of a
    structured model (``members_``: coefficient matrices over its ``terms_``); [] without."""
    members = getattr(model, "members_", None) or []
    shim = [type("Member", (), {"terms_": model.terms_, "coef_": np.asarray(c), "state_names_": model.state_names_,
                                "control_names_": model.control_names_,
                                "stages_": getattr(model, "stages_", None)})() for c in members]
    return [batch_predictor(mb) for mb in shim]


def member_spread(model: Any):
    """``spread(z) -> (K, n_outputs, N)``: every ensemble member's prediction at model inputs z
    (n_inputs, N), for any model kind with members: a structured model's ``members_`` (SINDy's
    bootstrap refits) or ``predict_members`` (an NN ensemble); None for a single model (no spread
    estimate: no pessimism)."""
    if len(getattr(model, "members_", None) or []) > 1:
        preds = member_predictors(model)
        return lambda z: np.stack([p(z) for p in preds])
    if callable(getattr(model, "predict_members", None)) and getattr(model, "ensemble_size", 1) > 1:
        n = len(model.state_names_)
        return lambda z: np.asarray(model.predict_members(z[:n].T, z[n:].T)).transpose(0, 2, 1)
    return None


def surrogate_settings(model: Any, spec: EnvSpec) -> dict[str, str]:
    """How a surrogate of ``model`` on ``spec`` steps, in words (stated in every fit run): its
    step noise and its pessimism, or why it has none."""
    noise = getattr(model, "noise_", None) or {}
    unc = spec.task.uncertainty if spec.task is not None else None
    spread = member_spread(model)
    k = (len(getattr(model, "members_", None) or []) or len(getattr(model, "elites_", ()))
         or getattr(model, "ensemble_size", 1))
    learned = callable(getattr(model, "sample", None))
    return {"surrogate.noise": ("learned variance: a random elite's Gaussian each step" if learned else
                                "residual covariance per " + ", ".join(sorted(noise)) if noise else "none"),
            "surrogate.pessimism": ("off (the env declares none)" if unc is None or not unc.active else
                                    f"ensemble disagreement ({k} members)" if spread is not None else
                                    NO_MEMBERS)}


class ModelEnv:
    """A fitted dynamics model bound to an env's task (see the module docstring).

    Parameters
    ----------
    model : a fitted model (``predict(x, u)``, ``state_names_``, ``control_names_``) or the path
        of a saved one.
    spec : an ``EnvSpec`` with a task, or an env name (``envs.base.find_spec``).
    initial_states : optional (K, n_state) states to reset from (uniformly); default: the task's
        reset distribution, else the real env's first observations (the run's reset pool).
    fused : use the task's batched kernel when it has one; False composes the numpy functions
        (same results; for comparisons).
    noise : add the model's step noise; False: deterministic.
    penalty : apply the task's pessimism to an ensemble's disagreement; False: the task's reward.
    events : {event name: a learned ``surrogate.events.EventModel``} (None or missing: the
        task's own rules alone decide that event).
    seed : the run seed: the reset pool and the random streams (None: fresh entropy, pool of run 0).
    config_dir : a config directory holding ``env/<spec>.yaml``, for a spec given by name.
    """

    def __init__(self, model: Any, spec: EnvSpec | str, initial_states: np.ndarray | None = None, *,
                 fused: bool = True, noise: bool = True, penalty: bool = True, events: dict | None = None,
                 seed: int | None = None, config_dir: str | None = None):
        self.spec = spec = resolve_spec(spec, config_dir)
        if spec.task is None:
            raise ConfigError(f"env.spec.reward_fn: '{spec.name}' ({type(spec).__name__}) defines no reward (no task); a surrogate "
                              "needs env.spec.reward_fn (and termination_fn) or an EnvSpec subclass with build_task()")
        self.task = spec.task
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
        self._limit_col = self.limit[:, None]
        self._initial = None
        if initial_states is not None:
            init = np.asarray(initial_states, dtype=float)
            if init.ndim != 2 or init.shape[1] != len(spec.state_names) or not len(init) or not np.all(np.isfinite(init)):
                raise ConfigError(f"initial_states: need a finite (K, {len(spec.state_names)}) array, got shape {init.shape}")
            self._initial = init
        self._pool = self._initial
        self.real_resets = 0
        """Real resets behind the reset pool (the real env's first observations; no step)."""
        if self._pool is None and self.task.initial_states is None:
            self._pool = observed_initial_states(spec, 0 if seed is None else seed)
            self.real_resets = len(self._pool)
        self._flags = (bool(fused), bool(noise), bool(penalty))
        index = np.concatenate([spec.target_index, spec.exogenous_index])
        self._n_state_inputs = len(index)
        # slice(None) when the states are the model's first inputs, in order (no copy needed)
        self._input_index = slice(None) if np.array_equal(index, np.arange(len(index))) else index
        self._one_hot = spec.action_encoding == "one_hot"
        self._action_ids = np.arange(spec.n_discrete_actions)[:, None]
        self._targets, self._exogenous = _as_slice(spec.target_index), _as_slice(spec.exogenous_index)
        self._angles = spec.angle_index if len(spec.angle_index) else None
        self.event_counts: dict[str, dict[str, int]] = {e.name: {o: 0 for o in e.outcome_names} for e in self.task.events}
        """Learned-event outcomes drawn so far, per event and outcome (all rows, all episodes)."""
        self.last_events: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        """The last step's drawn events: {event: (rows, outcome indices)}."""
        self.seed(seed)
        self.swap(model, events)

    # ------------------------------------------------------------------ set-up
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

    def seed(self, seed: int | None) -> None:
        """Seed the random streams (same seed and actions, same trajectories; None: fresh
        entropy). Resets draw from ``numpy.random.default_rng(seed)``, the generator a gymnasium
        env resets with: a task whose reset distribution is the real env's (MountainCar) then
        starts where the real env reset with the same seed starts. Step noise and event draws
        have streams of their own (``seeds``, purpose ``surrogate``)."""
        self._seed = seed
        self._rngs = {"init": np.random.default_rng(seed)}
        for k, name in enumerate(STREAMS[1:], start=1):
            self._rngs[name] = np.random.default_rng() if seed is None else seeds.generator(seed, "surrogate", k)

    @property
    def init_rng(self) -> np.random.Generator:
        return self._rngs["init"]

    @property
    def noise_rng(self) -> np.random.Generator:
        return self._rngs["noise"]

    def swap(self, model: Any, events: dict | None = None, seed: int | None = None, spec: EnvSpec | None = None) -> None:
        """Step on with ``model`` (and learned event models): the flags, pool and counters stay;
        the compiled evaluators and kernels are rebuilt (episode memory such as a sleep counter
        starts again); ``seed`` reseeds the streams; ``spec``: the same env with constants
        learned from the refit's data (``surrogate.own_data``). Dyna swaps its refits in here."""
        if spec is not None and spec is not self.spec:
            if spec.name != self.spec.name or spec.state_names != self.spec.state_names:
                raise ConfigError(f"swap: spec '{spec.name}' is not the surrogate's env '{self.spec.name}'")
            self.spec, self.task = spec, spec.task
        spec, task = self.spec, self.task
        self.model = model = check_model(model, spec)
        fused, noise, penalty = self._flags
        if seed is not None:
            self.seed(seed)
        self.events = dict(events or {})
        unknown = set(self.events) - {e.name for e in task.events}
        if unknown:
            raise ConfigError(f"events: {sorted(unknown)} are not events of env '{spec.name}'")
        self._learned = [(e, self.events[e.name]) for e in task.events if self.events.get(e.name) is not None]
        self._setup_noise(noise)
        self._setup_members(penalty)
        self._predict_rows = batch_predictor(model)
        sampler = getattr(model, "sample", None) if noise else None
        self._sample = None
        if callable(sampler):  # a model that draws its own steps (a probabilistic ensemble): its noise
            n_s = len(model.state_names_)
            self._sample = lambda z: np.asarray(sampler(z[:n_s].T, z[n_s:].T, self.noise_rng)).T
        # the one-state kernel evaluates a deterministic predictor: a sampling model steps by the batched path
        kernel = (task.step_one(self.predictor, self.obs_low, self.obs_high)
                  if task.step_one is not None and self._sample is None else None)
        self._step_one_kernel = kernel
        # the kernel itself when nothing wraps it: a single env's step is then one call
        self.step_one = kernel if kernel is not None and not (self._members is not None or self._learned) else self._step_one
        self._step_batch = (task.step_batch(self.limit, self.obs_low, self.obs_high, rng=lambda: self.init_rng)
                            if fused and task.step_batch is not None else None)
        self.state_order = "F" if self._step_batch is None else "C"
        """Memory layout of the states ``step`` returns (and steps fastest): a fused kernel reads
        states row by row ("C"); the numpy composition works column by column ("F")."""

    def _setup_noise(self, noise: bool) -> None:
        """The step noise: ``model.noise_`` {one-hot action column: covariance of the fit's
        residuals} as a PSD square root per discrete action."""
        spec, model = self.spec, self.model
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

    def _setup_members(self, penalty: bool) -> None:
        """The ensemble's members (``member_spread``: any model kind) when the task's pessimism
        is active; ``self.pessimism`` says which (a model without members gets none)."""
        model, unc = self.model, self.task.uncertainty
        self._members = None
        spread = member_spread(model) if penalty and unc is not None and unc.active else None
        if spread is not None:
            self._scale = np.asarray(unc.scale, dtype=float)[:, None]
            self._members = spread
        self.pessimism = ("off" if not (penalty and unc is not None and unc.active) else
                          "ensemble disagreement" if spread is not None else NO_MEMBERS)
        """How the reward is made pessimistic: by the members' disagreement, or not (and why)."""

    def __reduce__(self):  # compiled functions are rebuilt, not pickled
        # (``step_one``: the task's kernel, or ``_step_one`` around it; set by ``swap``)
        fused, noise, penalty = self._flags
        return (_rebuild, (self.model, self.spec, self._initial, fused, noise, penalty, self.events, self._seed))

    # ------------------------------------------------------------------ pieces
    def observation(self, states: np.ndarray) -> np.ndarray:
        """States (N, n_state) -> the observations the agent sees (the real env's dtype)."""
        dtype = self.observation_space.dtype
        if not self.spec.maps_observations:
            return states.astype(dtype, order="C")
        return np.clip(self.spec.observe(states), self.obs_low, self.obs_high).astype(dtype)

    def initial_states(self, n: int, rng: np.random.Generator | None = None) -> np.ndarray:
        """n reset states from the ``init`` stream (or ``rng``)."""
        rng = self.init_rng if rng is None else rng
        if self._pool is not None:
            return self._pool[rng.integers(len(self._pool), size=n)]
        return self.task.initial_states(rng, n)

    def predictor(self, fixed: dict[int, float] | None = None):
        """The model's fast one-state evaluator (``models.fast.scalar_predictor``), with the step
        noise of a discrete action held fixed added from the ``noise`` stream."""
        predict = scalar_predictor(self.model, fixed)
        chol = self._noise_for_fixed(fixed)
        if chol is None:
            return predict
        m = chol.shape[0]

        def noisy(z):
            out = predict(z)
            d = chol @ self.noise_rng.standard_normal((1, m))[0]
            return [v + float(e) for v, e in zip(out, d, strict=True)]

        return noisy

    def _noise_for_fixed(self, fixed: dict[int, float] | None) -> np.ndarray | None:
        if self._chol is None or not fixed:
            return None
        first = len(self.spec.input_names) - self.spec.n_discrete_actions
        hot = [i - first for i, v in fixed.items() if i >= first and v == 1.0]
        # an action without noise still draws (zeros): every path consumes the stream alike
        return self._chol[hot[0]] if len(hot) == 1 else None

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

    def model_inputs(self, states: np.ndarray, actions: np.ndarray) -> np.ndarray:
        """The model's inputs as rows z (n_inputs, N): states, then encoded actions."""
        spec, n_s = self.spec, self._n_state_inputs
        z = np.empty((n_s + len(spec.action_names), len(states)))
        z[:n_s] = states.T[self._input_index]
        if self._one_hot:
            np.equal(np.asarray(actions).reshape(len(states), -1)[:, 0], self._action_ids, out=z[n_s:], casting="unsafe")
        else:
            z[n_s:] = spec.encode_actions(actions).T
        return z

    def disagreement(self, z: np.ndarray) -> np.ndarray:
        """(N,) the ensemble's disagreement at model inputs z (n_inputs, N): the largest over
        regressed states of the members' standard deviation, in units of the task's scale."""
        return (self._members(z).std(axis=0) / self._scale).max(axis=0)

    def _add_noise(self, rows: np.ndarray, actions: np.ndarray) -> np.ndarray:
        return rows + self.noise_rows(actions)

    def noise_rows(self, actions: np.ndarray, eps: np.ndarray | None = None) -> np.ndarray:
        """The step noise (n_targets, N) for raw discrete ``actions``: the square root of each
        row's action's residual covariance times standard-normal draws ``eps`` (N, n_targets),
        drawn from the ``noise`` stream when not given."""
        a = np.asarray(actions).reshape(len(actions), -1)[:, 0].astype(np.intp)
        if eps is None:
            eps = self.noise_rng.standard_normal((len(a), self._chol.shape[1]))
        return np.einsum("nij,nj->in", self._chol[a], eps)

    # ------------------------------------------------------------------ the step
    def step(self, states: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, ...]:
        """One batched step: (next states, rewards, terminated, diverged), all (N, ...).

        Diverged rows keep their state, get reward 0 and terminated False (see module doc).
        The next states are laid out in ``state_order``.
        """
        task, states = self.task, np.asarray(states, dtype=float)
        with np.errstate(all="ignore"):
            z = self.model_inputs(states, actions)
            if self._sample is not None:  # the model's own draw (its learned variance), seeded
                rows = self._sample(z)
            else:
                rows = self._predict_rows(z)
                if self._chol is not None:  # the step noise (e.g. engine dispersion), seeded
                    rows = self._add_noise(rows, actions)
            if task.regime_dynamics is not None:
                rows = task.regime_dynamics(states, actions, rows)
            if self._step_batch is not None:  # the task's kernel does steps 3-5
                nxt, rewards, terminated, diverged = self._step_batch(states, actions, rows)
            else:
                nxt, rewards, terminated, diverged = self._compose(states, actions, rows)
        return self._post(states, actions, z, nxt, rewards, terminated, diverged)

    def _compose(self, states, actions, rows):
        """Steps 3-5 with numpy (no kernel)."""
        spec, task = self.spec, self.task
        ok = (np.abs(rows) <= self._limit_col).all(axis=0)  # False for NaN and inf
        bad = None if ok.all() else np.flatnonzero(~ok)
        pred = rows.T  # (N, m), Fortran order
        if bad is not None:  # placeholders (the current state) so that the rules see finite values
            pred = np.array(pred, order="F")
            pred[bad] = states[bad][:, spec.target_index]
        nxt = np.array(states, order="F")  # columns contiguous: cheap per-variable work
        nxt[:, self._targets] = spec.apply_bounds(states, pred)
        if spec.exogenous_names:
            nxt[:, self._exogenous] = task.exogenous(states, actions, nxt)
        if self._clip:  # only the columns that leave the space (np.clip on all is slow)
            outside = (nxt.min(axis=0) < self.obs_low) | (nxt.max(axis=0) > self.obs_high)
            for j in np.flatnonzero(outside):
                np.clip(nxt[:, j], self.obs_low[j], self.obs_high[j], out=nxt[:, j])
        if self._angles is not None:
            nxt[:, self._angles] = wrap_angle(nxt[:, self._angles])
        rewards, terminated = task.reward_terminated(states, actions, nxt)
        rewards = np.asarray(rewards, dtype=float)
        terminated = np.asarray(terminated, dtype=bool)
        if bad is not None:
            rewards, terminated = rewards.copy(), terminated.copy()
            nxt[bad] = states[bad]
            rewards[bad], terminated[bad] = 0.0, False
        return nxt, rewards, terminated, ~ok

    def _post(self, states, actions, z, nxt, rewards, terminated, diverged):
        """Steps 6 and 7 (pessimism, learned events), shared by both paths."""
        if self._members is not None:
            rewards, terminated = self._pessimism(states, z, rewards, terminated, diverged)
        if self._learned:
            rewards, terminated = self._draw_events(states, actions, nxt, rewards, terminated, diverged)
        return nxt, rewards, terminated, diverged

    def _pessimism(self, states, z, rewards, terminated, diverged):
        unc, task = self.task.uncertainty, self.task
        u = self.disagreement(z)
        live = ~diverged & ~terminated
        if task.model_regime is not None:
            live &= np.asarray(task.model_regime(states), dtype=bool)
        rewards = np.where(live, rewards - unc.penalty * np.maximum(u - unc.free, 0.0), rewards)
        over = live & (u > unc.limit)
        if over.any():
            rewards = np.where(over, float(task.crash_reward), rewards)
            terminated = terminated | over
        return rewards, terminated

    def _draw_events(self, states, actions, nxt, rewards, terminated, diverged):
        self.last_events = {}
        for event, model in self._learned:
            rows = np.asarray(event.trigger(states, actions, nxt), dtype=bool) & ~terminated & ~diverged
            idx = np.flatnonzero(rows)
            if not len(idx):
                continue
            pre = states[idx]
            if event.prior is not None and event.learn_on == "open":  # the prior's decided rows stay the task's
                keep = np.asarray(event.prior(pre)) == 0
                idx, pre = idx[keep], pre[keep]
                if not len(idx):
                    continue
            out = model.draw(event.features(pre), self._rngs["events"])
            self.last_events[event.name] = (idx, out)
            rewards, terminated = np.array(rewards, dtype=float), np.array(terminated, dtype=bool)
            for k, outcome in enumerate(event.outcomes):
                hit = idx[out == k]
                self.event_counts[event.name][outcome.name] += len(hit)
                if outcome.ends and len(hit):
                    terminated[hit] = True
                    if outcome.reward is not None:
                        rewards[hit] = outcome.reward
        return rewards, terminated

    def _step_one(self, state: list, action: Any) -> tuple[np.ndarray, list, float, bool, bool]:
        """``step_one(state, action)``: one state -> (observation, next state as a list, reward,
        terminated, diverged). The task's one-state kernel when it has one (plain Python: no
        numpy per step), else ``step`` with N = 1; pessimism and events as in ``step``."""
        kernel = self._step_one_kernel
        if kernel is None:
            s = np.asarray([state], dtype=float)
            nxt, r, term, div = self.step(s, self.raw_actions(action, 1))
            return self.observation(nxt[:1])[0], nxt[0].tolist(), float(r[0]), bool(term[0]), bool(div[0])
        obs, nxt, r, term, div = kernel(state, action)
        if div or term or not (self._members is not None or self._learned):
            return obs, nxt, r, term, div
        s, a = np.asarray([state], dtype=float), self.raw_actions(action, 1)
        z = self.model_inputs(s, a) if self._members is not None else None
        _, rew, ter, _ = self._post(s, a, z, np.asarray([nxt], dtype=float), np.array([r]), np.array([False]),
                                    np.array([False]))
        return obs, nxt, float(rew[0]), bool(ter[0]), div


def _rebuild(model, spec, initial, fused, noise, penalty, events, seed) -> ModelEnv:
    return ModelEnv(model, spec, initial, fused=fused, noise=noise, penalty=penalty, events=events, seed=seed)
