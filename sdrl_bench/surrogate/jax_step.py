"""The surrogate's step as one pure JAX function (issue 31, second block), for tasks written for jax too.

``jax_step(model_env)`` returns ``step(states, actions, noise=None) -> (next_states, rewards,
terminated, diverged)``: ``ModelEnv.step`` (``surrogate.model_env``, its steps 1, 3, 4 and 5) as
one pure float64 jax.numpy function, jit-able, for the model and task the ModelEnv holds now
(build it again after ``ModelEnv.swap``). Nothing is drawn inside: the step noise ModelEnv draws
from its ``noise`` stream is an input.

Layout (N rows, batched; numpy or jax arrays in, jax arrays out):

* ``states`` (N, n_state), in the spec's ``state_names`` order (what ``ModelEnv.step`` takes);
* ``actions``: the raw actions (N, raw width), as ``ModelEnv.step`` takes them (discrete: the
  action indices, integers or integral floats); the task's functions see them as given;
* ``noise``: None (no step noise) or (N, n_targets), the already-scaled noise added to the
  model's prediction of the regressed states (``spec.target_names`` order), i.e. the transpose of
  what ``ModelEnv._add_noise`` adds to its rows. ``step_noise(model_env, actions)`` gives exactly
  what ModelEnv would add (drawn from its ``noise`` stream, advancing it as ``ModelEnv.step``
  does), or, for given standard-normal draws ``eps`` (N, n_targets), the noise ModelEnv makes of
  them (numpy draws: bit for bit; jax draws: a traceable einsum, equal to rounding);
* out: next states (N, n_state) float64, rewards (N,) float64, terminated (N,) bool, diverged
  (N,) bool. A diverged row keeps its state, gets reward 0 and terminated False.

The steps, each as ModelEnv does it: the model's inputs (the regressed states, then the actions
encoded by ``spec.action_encoding``: raw, clip, one_hot, index or values); the prediction
(``models.jax_eval.jax_predictor``) plus the noise; the divergence guard (a non-finite value, or
one beyond ``spec.divergence_limit()``, keeps the state; the rules below see the current state in
its place, as ModelEnv's placeholders); the spec's bounds (``EnvSpec.apply_bounds``: the box
clip, each ``circle_pairs`` pair projected back onto the unit circle, rounding to ``obs_dtype``);
clipping to the real env's observation space where ModelEnv clips (``ModelEnv._clip``); angles
wrapped to [-pi, pi); the task's reward and termination called on jax arrays: the spec's plain
functions (``env.spec.reward_fn`` / ``termination_fn``), or the ``task.reward_terminated`` of a task
an env class builds (``build_task``). Each must be written with ``envs.functional.array_namespace``
(checked when the step is built: one line naming the key or the function), as must the spec's
``apply_bounds`` and ``encode_actions`` when a class overrides them.

Rounding: ModelEnv evaluates the model with ``models.fast.batch_predictor`` and numpy's libm
(hypot, exp, cos); jax sums the model's terms in the one-state evaluator's order and has its own
transcendental functions, so the two agree to rounding (tested: <= 1e-12 on 10,000 states spanning
and beyond the data, diverging rows included); jit fuses a*b + c into FMAs (again to rounding).

Around the step, for a loop compiled with it (``rl.jax_ppo``): ``jax_observe(model_env)``, the
observations ``ModelEnv.observation`` emits (the spec's observation map in jax: each angle's cos and
sin, clipped to the real env's observation space, in its dtype); ``jax_reset(model_env)``, reset
states drawn from a jax PRNG key (the spec's ``initial_state_fn`` or the task's ``initial_states``,
or the ModelEnv's reset pool);
``has_step_noise(model_env)``, whether its step adds noise (a loop that feeds none must refuse it).

Not covered (refused when the step is built, one line naming each): the task's compiled kernels
(``task.step_batch``), exogenous states, regime dynamics, learned events, pessimism (build the
ModelEnv with ``penalty=False``), a sampling model's own draws (``noise=False`` steps its mean).
A task's one-state kernel (``task.step_one``) is no obstacle: ``ModelEnv.step`` composes the batched
step with numpy, which this mirrors. Models without term tables (``nn``, ``pe``):
``jax_predictor``'s error.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from sdrl_bench import ConfigError
from sdrl_bench.envs.base import EnvSpec
from sdrl_bench.envs.functional import array_namespace, one_line, resolve, wrap_angle
from sdrl_bench.models.jax_eval import jax_modules, jax_predictor

JaxStep = Callable[..., tuple[Any, Any, Any, Any]]


def unsupported(model_env: Any) -> list[str]:
    """What of ``model_env``'s step ``jax_step`` does not cover yet (empty: all of it)."""
    spec, task = model_env.spec, model_env.task
    out = []
    if task.step_batch is not None:
        out.append("compiled kernels (task.step_batch)")
    if spec.exogenous_names or task.exogenous is not None:
        out.append("exogenous states (env.spec.exogenous_names)")
    if task.regime_dynamics is not None:
        out.append("regime dynamics (task.regime_dynamics)")
    if model_env._learned:
        out.append(f"learned events ({', '.join(e.name for e, _ in model_env._learned)})")
    if model_env._members is not None:
        out.append("pessimism (task.uncertainty; ModelEnv(penalty=False) steps without)")
    if model_env._sample is not None:
        out.append("a sampling model's own draws (ModelEnv(noise=False) steps its mean)")
    return out


def _is_method(fn: Any, method: Callable) -> bool:
    """Whether ``fn`` is ``method`` bound to a spec (the task's plain-function wrappers)."""
    return getattr(fn, "__func__", None) is method


def _describe(fn: Any) -> str:
    """A task function's name for an error: ``Class.method`` for a bound method."""
    owner = getattr(fn, "__self__", None)
    name = getattr(fn, "__name__", None)
    if owner is not None and name:
        return f"{type(owner).__name__}.{name}"
    return getattr(fn, "__qualname__", None) or type(fn).__name__


def _traced(jax: Any, fn: Callable, args: tuple, who: str) -> Any:
    """``jax.eval_shape(fn, *args)``; a function written for numpy alone fails here, in one line
    (``who``: ``jax_step: <key> (<path>)``)."""
    try:
        return jax.eval_shape(fn, *args)
    except Exception as exc:  # a user's function may raise anything
        raise ConfigError(f"{who} does not run on jax arrays: {one_line(exc)}; write it with "
                          "envs.functional.array_namespace") from None


def _size(out: Any) -> int:
    return int(np.prod(getattr(out, "shape", (0,))))


def _check_traceable(jax: Any, fn: Callable, key: str, path: Any, n_state: int, action: Any) -> None:
    """``fn(states, actions, next_states)`` traced on abstract jax arrays of two rows: a function
    written for numpy alone fails here, in one line naming its key."""
    s = jax.ShapeDtypeStruct((2, n_state), np.float64)
    out = _traced(jax, fn, (s, action, s), f"jax_step: {key} ({path})")
    if _size(out) != 2:
        raise ConfigError(f"jax_step: {key} ({path}) returned shape {getattr(out, 'shape', None)} for 2 states; expected (2,)")


def _reward_terminated(spec: EnvSpec, task: Any, jax: Any, jnp: Any) -> Callable:
    """``(s, a, s') -> (rewards (N,), terminated (N,) bool)``, checked to run on jax arrays: the
    spec's plain functions (``env.spec.reward_fn``, ``termination_fn``; never terminated without
    one), as its task calls them, or the ``task.reward_terminated`` a spec class built."""
    n_state = len(spec.state_names)
    action = jax.ShapeDtypeStruct((2, spec.raw_action_width), np.int64 if spec.n_discrete_actions else np.float64)
    if not _is_method(task.reward_terminated, EnvSpec._reward_terminated):
        fn = task.reward_terminated
        s = jax.ShapeDtypeStruct((2, n_state), np.float64)
        who = f"jax_step: task.reward_terminated ({_describe(fn)})"
        out = _traced(jax, fn, (s, action, s), who)
        if not (isinstance(out, (tuple, list)) and len(out) == 2 and _size(out[0]) == _size(out[1]) == 2):
            raise ConfigError(f"{who} returned {out} for 2 states; expected (rewards (2,), terminated (2,))")

        def task_reward_terminated(states, actions, nxt):
            n = states.shape[0]
            rewards, terminated = fn(states, actions, nxt)
            return (jnp.asarray(rewards, dtype=jnp.float64).reshape(n), jnp.asarray(terminated, dtype=bool).reshape(n))

        return task_reward_terminated
    reward_fn = resolve(spec.reward_fn, "env.spec.reward_fn")
    term_fn = resolve(spec.termination_fn, "env.spec.termination_fn")
    _check_traceable(jax, reward_fn, "env.spec.reward_fn", spec.reward_fn, n_state, action)
    if term_fn is not None:
        _check_traceable(jax, term_fn, "env.spec.termination_fn", spec.termination_fn, n_state, action)

    def reward_terminated(states, actions, nxt):
        n = states.shape[0]
        rewards = jnp.asarray(reward_fn(states, actions, nxt), dtype=jnp.float64).reshape(n)
        terminated = (jnp.zeros(n, dtype=bool) if term_fn is None
                      else jnp.asarray(term_fn(states, actions, nxt), dtype=bool).reshape(n))
        return rewards, terminated

    return reward_terminated


def jax_step(model_env: Any) -> JaxStep:
    """``step(states, actions, noise=None) -> (next_states, rewards, terminated, diverged)``:
    ``model_env.step`` as a pure jax function (see the module docstring for the layout)."""
    missing = unsupported(model_env)
    spec = model_env.spec
    if missing:
        raise NotImplementedError(f"jax_step: env '{spec.name}': not covered yet: {'; '.join(missing)}")
    predict = jax_predictor(model_env.model)  # refuses a model without term tables
    jax, jnp = jax_modules("sdrl_bench.surrogate.jax_step")
    targets = np.asarray(spec.target_index, dtype=int)
    all_targets = np.array_equal(targets, np.arange(len(spec.state_names)))
    limit = np.asarray(model_env.limit, dtype=float)
    # clipping to the observation space, where ModelEnv clips (only columns with a finite bound)
    clip_cols = (np.flatnonzero(np.isfinite(model_env.obs_low) | np.isfinite(model_env.obs_high)) if model_env._clip
                 else np.array([], dtype=int))
    obs_low, obs_high = model_env.obs_low[clip_cols], model_env.obs_high[clip_cols]
    angles = None if model_env._angles is None else np.asarray(model_env._angles, dtype=int)
    reward_terminated = _reward_terminated(spec, model_env.task, jax, jnp)

    def step(states, actions, noise=None):
        states = jnp.asarray(states, dtype=jnp.float64)
        actions = jnp.asarray(actions)
        cur = states if all_targets else states[:, targets]
        rows = predict(jnp.concatenate([cur, spec.encode_actions(actions)], axis=1))  # (N, n_targets)
        if noise is not None:
            rows = rows + jnp.asarray(noise, dtype=jnp.float64)
        ok = jnp.all(jnp.abs(rows) <= limit, axis=1)  # False for NaN and inf
        pred = jnp.where(ok[:, None], rows, cur)  # placeholders: the rules see finite values
        bounded = spec.apply_bounds(states, pred)  # written once for numpy and jax
        nxt = bounded if all_targets else states.at[:, targets].set(bounded)
        if len(clip_cols):
            nxt = nxt.at[:, clip_cols].set(jnp.clip(nxt[:, clip_cols], obs_low, obs_high))
        if angles is not None:
            nxt = nxt.at[:, angles].set(wrap_angle(nxt[:, angles]))
        rewards, terminated = reward_terminated(states, actions, nxt)
        nxt = jnp.where(ok[:, None], nxt, states)
        return nxt, jnp.where(ok, rewards, 0.0), terminated & ok, ~ok

    return step


def step_noise(model_env: Any, actions: Any, eps: Any = None) -> Any:
    """(N, n_targets): the step noise ``model_env.step`` adds to the prediction for raw
    ``actions`` (``ModelEnv._add_noise``: the PSD square root of the residual covariance of each
    row's discrete action times standard-normal draws), in ``jax_step``'s ``noise`` layout.

    ``eps`` None: drawn from ``model_env.noise_rng`` exactly as ``ModelEnv.step`` draws them (the
    stream advances the same: a caller alternating ``step_noise`` and the jax step reproduces
    ModelEnv's steps); zeros, and no draw, when the ModelEnv adds no noise (``noise=False``, a
    model without ``noise_``, continuous actions). ``eps`` (N, n_targets) standard-normal draws:
    numpy gives ModelEnv's noise bit for bit; jax arrays (e.g. ``jax.random.normal`` inside a
    compiled loop) give it traceably, equal to rounding."""
    if model_env._sample is not None:
        raise NotImplementedError("step_noise: a sampling model draws its own steps (model.sample): not covered yet")
    chol, m = model_env._chol, len(model_env.spec.target_names)
    xp = np if eps is None else array_namespace(actions, eps)
    a = xp.asarray(actions)
    n = a.shape[0]
    if chol is None:
        return xp.zeros((n, m))
    if xp is not np:
        a = a.reshape(n, -1)[:, 0].astype(np.intp)
        return xp.einsum("nij,nj->ni", xp.asarray(chol)[a], xp.asarray(eps, dtype=xp.float64))
    if eps is not None:
        eps = np.asarray(eps, dtype=float)
        if eps.shape != (n, m):
            raise ValueError(f"step_noise: eps of shape {eps.shape}, expected ({n}, {m})")
    return model_env.noise_rows(a, eps).T  # ModelEnv's own noise (and draws, eps None)


def has_step_noise(model_env: Any) -> bool:
    """Whether ``model_env.step`` adds noise to the model's prediction (the residual covariance of
    a discrete action, or a sampling model's own draws): a compiled loop that steps ``jax_step``
    without its ``noise`` input would step the mean instead."""
    return model_env._chol is not None or model_env._sample is not None


def jax_observe(model_env: Any) -> Callable:
    """``observe(states (N, n_state)) -> observations (N, n_obs)``: ``ModelEnv.observation`` as a
    pure jax function: without an observation map the states themselves; with one, each angle's
    cos and sin and the other states (``EnvSpec.observe``), clipped to the real env's observation
    space; in the observation space's dtype either way."""
    spec = model_env.spec
    _, jnp = jax_modules("sdrl_bench.surrogate.jax_step")
    dtype = np.dtype(model_env.observation_space.dtype)
    if not spec.maps_observations:
        return lambda states: jnp.asarray(states).astype(dtype)
    low, high = model_env.obs_low, model_env.obs_high
    return lambda states: jnp.clip(spec.observe(jnp.asarray(states, dtype=jnp.float64)), low, high).astype(dtype)


def jax_reset(model_env: Any) -> Callable:
    """``reset(key, n) -> (n, n_state)`` float64 reset states from a jax PRNG key: uniformly from
    the ModelEnv's reset pool when it has one (given initial states, or the real env's first
    observations), else the spec's ``initial_state_fn`` (or the ``task.initial_states`` a spec
    class built) called on the key (written with ``envs.functional``'s draws; checked when built:
    one line naming the key or the function). The same distribution as
    ``ModelEnv.initial_states``, not the same draws."""
    jax, jnp = jax_modules("sdrl_bench.surrogate.jax_step")
    spec, task = model_env.spec, model_env.task
    pool = model_env._pool
    if pool is not None:
        pool = jnp.asarray(pool, dtype=jnp.float64)
        return lambda key, n: pool[jax.random.randint(key, (n,), 0, pool.shape[0])]
    if _is_method(task.initial_states, EnvSpec._checked_initial_states):
        fn = resolve(spec.initial_state_fn, "env.spec.initial_state_fn")
        who = f"env.spec.initial_state_fn ({spec.initial_state_fn})"
    else:
        fn = task.initial_states
        who = f"task.initial_states ({_describe(fn)})"
    n_state = len(spec.state_names)
    try:
        out = jax.eval_shape(lambda k: fn(k, 2), jax.random.key(0))
    except Exception as exc:  # a user's function may raise anything
        raise ConfigError(f"jax_reset: {who} does not draw from a jax key: {one_line(exc)}; write it with "
                          "envs.functional's uniform / standard_normal") from None
    if tuple(getattr(out, "shape", ())) != (2, n_state):
        raise ConfigError(f"jax_reset: {who} returned shape {getattr(out, 'shape', None)} for n=2; expected (2, {n_state})")
    return lambda key, n: jnp.asarray(fn(key, n), dtype=jnp.float64)
