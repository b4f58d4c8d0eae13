"""The surrogate's step as one pure JAX function (issue 31, second block), for tasks written for jax too.

``jax_stepper(model_env)`` returns a ``JaxStepper(step, init_aux, n_event_draws)`` whose
``step(states, actions, aux, noise=None, event_u=None) -> (next_states, rewards, terminated,
diverged, aux)`` is ``ModelEnv.step`` (``surrogate.model_env``, its steps 1 to 7) as one pure
float64 jax.numpy function, jit-able, for the model, task and learned events the ModelEnv holds
now (build it again after ``ModelEnv.swap``). Nothing is drawn and nothing is remembered inside:
the step noise, the events' uniforms and the task's per-row memory are inputs.
``jax_step(model_env)`` is the same without memory or events, ``step(states, actions,
noise=None) -> (next_states, rewards, terminated, diverged)`` (refused, pointing here, for a
task with memory or learned events).

Layout (N rows, batched; numpy or jax arrays in, jax arrays out):

* ``states`` (N, n_state), in the spec's ``state_names`` order (what ``ModelEnv.step`` takes);
* ``actions``: the raw actions (N, raw width), as ``ModelEnv.step`` takes them (discrete: the
  action indices, integers or integral floats); the task's functions see them as given;
* ``aux`` (N,) int64: the task's per-row memory (``task.array_step``: e.g. a sleep counter that
  the compiled kernel keeps per row between calls); ``init_aux(n)`` is that of n fresh episodes
  (zeros; zeros throughout for a task without memory). Pass the returned ``aux`` to the next
  step and reset the rows whose episode ends: ``reset_aux(done, init_aux(n), aux)``. ModelEnv's
  kernel does this itself (a row whose state is not the one it returned last counts from 0). A
  task whose fresh memory is drawn (e.g. a random terrain per episode) has a tuple
  of per-row arrays as ``aux`` and draws it from a jax key, ``init_aux(n, key)``;
* ``noise``: None (no step noise) or (N, n_targets), the already-scaled noise added to the
  model's prediction of the regressed states (``spec.target_names`` order), i.e. the transpose of
  what ``ModelEnv._add_noise`` adds to its rows. ``step_noise(model_env, actions)`` gives exactly
  what ModelEnv would add (drawn from its ``noise`` stream, advancing it as ``ModelEnv.step``
  does), or, for given standard-normal draws ``eps`` (N, n_targets), the noise ModelEnv makes of
  them (numpy draws: bit for bit; jax draws: a traceable einsum, equal to rounding);
* ``event_u``: None (the learned events are not drawn: the task's rules alone) or (N,
  ``n_event_draws``) uniforms in [0, 1), one per row and learned event, in the task's event
  order; ModelEnv draws one from its ``events`` stream per row an event triggers on;
* out: next states (N, n_state) float64, rewards (N,) float64, terminated (N,) bool, diverged
  (N,) bool, aux (N,) int64. A diverged row keeps its state and memory, gets reward 0 and
  terminated False.

The steps, each as ModelEnv does it: the model's inputs (the regressed states, the exogenous
states, then the actions encoded by ``spec.action_encoding``: raw, clip, one_hot, index or
values); the prediction (``models.jax_eval.jax_model``: a sparse model's ``linear_predictor``, its
coefficients an argument; an NN model's network, ``models.jax_nn``, its weights an argument) plus
the noise, or a probabilistic ensemble's own draw (``sample_draws``: a uniform per row picks the
elite, standard normals scale its variance); the task's regime
dynamics (``task.array_step.regime_dynamics``). Then, with the task's kernels (``task.step_batch``,
ModelEnv's fused path), their array form ``task.array_step.step`` (the divergence guard and all
the task's rules, memory in and out); else ModelEnv's composition: the divergence guard (a
non-finite value, or one beyond ``spec.divergence_limit()``, keeps the state; the rules below see
the current state in its place, as ModelEnv's placeholders); the spec's bounds
(``EnvSpec.apply_bounds``: the box clip, each ``circle_pairs`` pair projected back onto the unit
circle, rounding to ``obs_dtype``); clipping to the real env's observation space where ModelEnv
clips (``ModelEnv._clip``); angles wrapped to [-pi, pi); the task's reward and termination called
on jax arrays: the spec's plain functions (``env.spec.reward_fn`` / ``termination_fn``), or the
``task.reward_terminated`` of a task an env class builds (``build_task``). Then the pessimism
(``ModelEnv._pessimism``: the members' standard deviation, ddof 0, over the members' jax
predictions, a sparse model's ``members_`` or an NN ensemble's members, in units of the task's
scale, largest over states; penalty, free band, limit and
crash reward; in ``task.model_regime``) and the learned events (``ModelEnv._draw_events``: on rows
the trigger fires, not ended, open to the prior when the event learns on those, an outcome drawn
by ``surrogate.events.draw_outcomes`` from the model's probabilities, ``outcome_probabilities``;
an outcome that ends sets terminated and its reward). Every task function the step calls must be
written with ``envs.functional.array_namespace`` (checked when the step is built: one line naming
the key or the function), as must the spec's ``apply_bounds`` and ``encode_actions`` when a class
overrides them.

Rounding: ModelEnv evaluates the model with ``models.fast.batch_predictor`` and numpy's libm
(hypot, exp, cos); jax sums the model's terms in the one-state evaluator's order and has its own
transcendental functions, so the two agree to rounding (tested: <= 1e-12 on 10,000 states spanning
and beyond the data, diverging rows included); jit fuses a*b + c into FMAs (again to rounding).
Comparisons on rounded values (a threshold hit to the last bit) could then go either way.

Around the step, for a loop compiled with it (``rl.jax_ppo``): ``jax_observe(model_env)``, the
observations ``ModelEnv.observation`` emits (the spec's observation map in jax: each angle's cos and
sin, clipped to the real env's observation space, in its dtype); ``jax_reset(model_env)``, reset
states drawn from a jax PRNG key (the spec's ``initial_state_fn`` or the task's ``initial_states``,
or the ModelEnv's reset pool).

Not covered (``unsupported``; refused when the step is built, one line naming each): models
with neither term tables nor a network, a sampling model that is not an NN ensemble
(``noise=False`` steps its mean), compiled kernels without an array form (``task.array_step`` None),
exogenous states or regime dynamics outside one, pessimism from a sparse model without
``members_``, learned events
whose model is not a standard scaler + logistic regression. A task's one-state kernel
(``task.step_one``) is no obstacle: it is the batched step for one state.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

from sdrl_bench import ConfigError
from sdrl_bench.envs.base import EnvSpec
from sdrl_bench.envs.functional import array_namespace, one_line, resolve, wrap_angle
from sdrl_bench.models.jax_eval import JaxModel, is_network, jax_model, jax_modules
from sdrl_bench.surrogate.events import draw_outcomes, logistic_numbers, outcome_probabilities

JaxStep = Callable[..., tuple[Any, Any, Any, Any]]


def unsupported(model_env: Any) -> list[str]:
    """What of ``model_env``'s step ``jax_stepper`` does not cover (empty: all of it)."""
    spec, task, model = model_env.spec, model_env.task, model_env.model
    out = []
    network = is_network(model)
    if not network and (getattr(model, "terms_", None) is None or getattr(model, "coef_", None) is None):
        kind = getattr(model, "kind", None) or type(model).__name__
        out.append(f"a model without term tables or a network ({kind}; models.jax_eval.jax_model evaluates "
                   "the sparse and the NN models)")
    array = task.array_step
    lacking = [(what, key) for what, key, used, given in (
        ("compiled kernels", "task.step_batch", model_env._step_batch is not None, array is not None),
        ("regime dynamics", "task.regime_dynamics", task.regime_dynamics is not None,
         array is not None and array.regime_dynamics is not None)) if used and not given]
    if lacking:
        out.append(f"{' and '.join(w for w, _ in lacking)} without an array form "
                   f"({', '.join(k for _, k in lacking)}; no task.array_step)")
    if model_env._step_batch is None and (spec.exogenous_names or task.exogenous is not None):
        out.append("exogenous states outside the task's kernels (env.spec.exogenous_names)")
    if model_env._members is not None and not network and len(getattr(model, "members_", None) or []) < 2:
        out.append("pessimism from a model without members_ (ModelEnv(penalty=False) steps without)")
    bad = [e.name for e, m in model_env._learned if logistic_numbers(m) is None]
    if bad:
        out.append(f"learned events whose model is not a scaler + logistic regression ({', '.join(bad)})")
    if model_env._sample is not None and not (network and callable(getattr(model, "sample", None))):
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


class JaxStepper(NamedTuple):
    """``model_env``'s step as a pure jax function with its per-row memory and event draws as
    inputs (see the module docstring)."""

    step: Callable[..., tuple[Any, Any, Any, Any, Any]]
    """``step(states, actions, aux, noise=None, event_u=None, params=None, sample_draws=None) ->
    (next_states, rewards, terminated, diverged, aux)``; ``params`` None: this stepper's own;
    ``sample_draws`` (a model that draws its own steps, ``sampling``): (u (N,) uniform in [0, 1),
    eps (N, n_targets) standard normal), None: the model's mean step."""
    init_aux: Callable[..., Any]
    """``init_aux(n, key=None)``: the memory of n fresh episodes, (n,) int64 (zeros for a task
    without), or a tuple of per-row arrays for a task whose memory is drawn (e.g. a counter and
    a random terrain per episode, drawn from the jax ``key``)."""
    n_event_draws: int
    """Columns of ``event_u``: one uniform per row and learned event."""
    params: dict[str, Any] | None = None
    """The numbers of the ModelEnv's model, as arrays (``JaxModel.params``): a sparse model's
    ``coef`` (its coefficients) and ``members`` (its ensemble members', stacked; None without
    pessimism), an NN model's weights, biases and normalisation; then ``chol`` (the step
    noise's square roots per discrete action; None without noise), ``events`` (per learned event
    its scaler's mean and scale and its logistic coefficients and intercept). Passed to ``step``
    as an argument of a compiled program, a refit of the same structure (equal ``key``) steps
    through the program compiled for the first."""
    key: tuple = ()
    """The structure the compiled step depends on besides ``params`` (the term table and which
    terms are used, the members' count, noise, the events' classes); with the same ModelEnv spec,
    steppers of equal keys are interchangeable given their ``params``."""
    sampling: bool = False
    """Whether the model draws its own steps (a probabilistic ensemble with the ModelEnv's noise
    on): ``step`` then takes ``sample_draws``."""


def _composed(model_env: Any, jax: Any, jnp: Any) -> Callable:
    """``f(states, actions, rows, aux) -> (next_states, rewards, terminated, diverged, aux)``:
    ModelEnv's numpy composition (``ModelEnv._compose``) after the prediction; no memory."""
    spec = model_env.spec
    targets = np.asarray(spec.target_index, dtype=int)
    all_targets = np.array_equal(targets, np.arange(len(spec.state_names)))
    limit = np.asarray(model_env.limit, dtype=float)
    # clipping to the observation space, where ModelEnv clips (only columns with a finite bound)
    clip_cols = (np.flatnonzero(np.isfinite(model_env.obs_low) | np.isfinite(model_env.obs_high)) if model_env._clip
                 else np.array([], dtype=int))
    obs_low, obs_high = model_env.obs_low[clip_cols], model_env.obs_high[clip_cols]
    angles = None if model_env._angles is None else np.asarray(model_env._angles, dtype=int)
    reward_terminated = _reward_terminated(spec, model_env.task, jax, jnp)

    def composed(states, actions, rows, aux):
        cur = states if all_targets else states[:, targets]
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
        return nxt, jnp.where(ok, rewards, 0.0), terminated & ok, ~ok, aux

    return composed


def _as_jax(aux: Any, jnp: Any) -> Any:
    """The task's memory as jax arrays: one int64 array (a counter per row), or a tuple of
    per-row arrays, each of its own dtype."""
    return tuple(jnp.asarray(a) for a in aux) if isinstance(aux, tuple) else jnp.asarray(aux, dtype=jnp.int64)


def reset_aux(done: Any, fresh: Any, aux: Any) -> Any:
    """``aux`` with the rows where ``done`` (N,) replaced by ``fresh``'s, for an array or a tuple
    of per-row arrays (e.g. a sleep count (N,) and a terrain (N, 11))."""
    _, jnp = jax_modules("sdrl_bench.surrogate.jax_step")

    def one(f, a):
        return jnp.where(jnp.reshape(done, (-1,) + (1,) * (jnp.ndim(a) - 1)), f, a)

    return tuple(one(f, a) for f, a in zip(fresh, aux, strict=True)) if isinstance(aux, tuple) else one(fresh, aux)


def _kernel(model_env: Any, jnp: Any) -> Callable:
    """The task's kernels in their array form (``task.array_step``) for the ModelEnv's
    divergence limit and observation bounds, outputs as jax arrays of fixed dtypes."""
    fn = model_env.task.array_step.step(model_env.limit, model_env.obs_low, model_env.obs_high)

    def kernel(states, actions, rows, aux):
        nxt, rewards, terminated, diverged, aux = fn(states, actions, rows, aux)
        return (jnp.asarray(nxt, dtype=jnp.float64), jnp.asarray(rewards, dtype=jnp.float64),
                jnp.asarray(terminated, dtype=bool), jnp.asarray(diverged, dtype=bool), _as_jax(aux, jnp))

    return kernel


def _state_fn(jax: Any, fn: Callable, key: str, n_state: int, width: int | None = None) -> None:
    """``fn(states)`` traced on two abstract rows: (2,) values (``width`` None) or (2, width)."""
    who = f"jax_step: {key} ({_describe(fn)})"
    out = _traced(jax, fn, (jax.ShapeDtypeStruct((2, n_state), np.float64),), who)
    want = (2,) if width is None else (2, width)
    if tuple(getattr(out, "shape", ())) != want:
        raise ConfigError(f"{who} returned shape {getattr(out, 'shape', None)} for 2 states; expected {want}")


def _pessimism(model_env: Any, jm: JaxModel, jax: Any, jnp: Any) -> Callable | None:
    """``f(states, z, rewards, terminated, diverged, params) -> (rewards, terminated)``:
    ``ModelEnv._pessimism`` with the members' predictions ``jm.members`` (``jax_model``: a sparse
    model's members' coefficients, an NN ensemble's members) at the model's numbers ``params``;
    None without pessimism."""
    if model_env._members is None:
        return None
    task = model_env.task
    unc = task.uncertainty
    scale = np.asarray(unc.scale, dtype=float)
    regime = task.model_regime
    if regime is not None:
        _state_fn(jax, regime, "task.model_regime", len(model_env.spec.state_names))
    penalty, free, limit = float(unc.penalty), float(unc.free), float(unc.limit)
    crash = float(task.crash_reward) if task.crash_reward is not None else 0.0

    def pessimism(states, z, rewards, terminated, diverged, params):
        spread = jm.members(z, params)  # (K, N, n_states)
        u = (spread.std(axis=0) / scale).max(axis=1)  # (N,), as disagreement()
        live = ~diverged & ~terminated
        if regime is not None:
            live = live & jnp.asarray(regime(states), dtype=bool).reshape(-1)
        rewards = jnp.where(live, rewards - penalty * jnp.maximum(u - free, 0.0), rewards)
        if np.isfinite(limit):
            over = live & (u > limit)
            rewards, terminated = jnp.where(over, crash, rewards), terminated | over
        return rewards, terminated

    return pessimism


def _event_draws(model_env: Any, jax: Any, jnp: Any) -> list[tuple[Callable, tuple]]:
    """Per learned event, (``f(states, actions, nxt, rewards, terminated, diverged, u, numbers)
    -> (rewards, terminated)``, its logistic numbers): ``ModelEnv._draw_events`` for uniforms
    ``u`` (N,) and the model's (mean, scale, coef, intercept) ``numbers``, the event's functions
    traced (each checked on jax arrays: one line naming it)."""
    spec = model_env.spec
    n_state = len(spec.state_names)
    s = jax.ShapeDtypeStruct((2, n_state), np.float64)
    action = jax.ShapeDtypeStruct((2, spec.raw_action_width), np.int64 if spec.n_discrete_actions else np.float64)
    draws = []
    for event, em in model_env._learned:
        numbers = logistic_numbers(em)
        key = f"env.spec.events ({event.name})"
        out = _traced(jax, event.trigger, (s, action, s), f"jax_step: {key}.trigger ({_describe(event.trigger)})")
        if _size(out) != 2:
            raise ConfigError(f"jax_step: {key}.trigger returned shape {getattr(out, 'shape', None)} for 2 states")
        _state_fn(jax, event.features, f"{key}.features", n_state, numbers[2].shape[1])
        prior = event.prior if event.prior is not None and event.learn_on == "open" else None
        if prior is not None:  # the prior's decided rows stay the task's
            _state_fn(jax, prior, f"{key}.prior", n_state)
        n_out = len(event.outcomes)
        ends = jnp.asarray([o.ends for o in event.outcomes])
        sets = ends & jnp.asarray([o.reward is not None for o in event.outcomes])
        value = jnp.asarray([o.reward if o.reward is not None else 0.0 for o in event.outcomes], dtype=jnp.float64)

        def draw(states, actions, nxt, rewards, terminated, diverged, u, numbers, event=event, classes=numbers[4],
                 prior=prior, n_out=n_out, ends=ends, sets=sets, value=value):
            rows = jnp.asarray(event.trigger(states, actions, nxt), dtype=bool).reshape(-1) & ~terminated & ~diverged
            if prior is not None:
                rows = rows & (jnp.asarray(prior(states)).reshape(-1) == 0)
            k = draw_outcomes(outcome_probabilities((*numbers, classes), event.features(states), n_out), u)
            rewards = jnp.where(rows & sets[k], value[k], rewards)
            return rewards, terminated | (rows & ends[k])

        draws.append((draw, numbers))
    return draws


def jax_stepper(model_env: Any) -> JaxStepper:
    """``model_env.step`` as a pure jax function with its memory and draws as inputs: a
    ``JaxStepper`` (see the module docstring); refuses what it does not cover in one line."""
    missing = unsupported(model_env)
    spec, task = model_env.spec, model_env.task
    if missing:
        raise NotImplementedError(f"jax_step: env '{spec.name}': not covered yet: {'; '.join(missing)}")
    model = model_env.model
    jax, jnp = jax_modules("sdrl_bench.surrogate.jax_step")
    jm = jax_model(model, members=model_env._members is not None)  # the model's numbers as arguments
    sampling = model_env._sample is not None
    inputs = np.concatenate([spec.target_index, spec.exogenous_index]).astype(int)  # ModelEnv.model_inputs
    kernel = model_env._step_batch is not None
    after = _kernel(model_env, jnp) if kernel else _composed(model_env, jax, jnp)
    regime = task.array_step.regime_dynamics if task.regime_dynamics is not None else None
    fresh = task.array_step.init_aux if kernel else (lambda n, key=None: np.zeros(n, dtype=np.int64))
    pessimism = _pessimism(model_env, jm, jax, jnp)
    draws = _event_draws(model_env, jax, jnp)
    own = {**jm.params, "chol": None if model_env._chol is None else np.asarray(model_env._chol, dtype=float),
           "events": [tuple(np.asarray(x, dtype=float) for x in numbers[:4]) for _, numbers in draws]}
    key = (jm.key, sampling, None if own["chol"] is None else own["chol"].shape,
           tuple((tuple(numbers[4].tolist()), numbers[2].shape) for _, numbers in draws))

    def step(states, actions, aux, noise=None, event_u=None, params=None, sample_draws=None):
        params = own if params is None else params
        states = jnp.asarray(states, dtype=jnp.float64)
        actions = jnp.asarray(actions)
        z = jnp.concatenate([states[:, inputs], spec.encode_actions(actions)], axis=1)
        if sampling and sample_draws is not None:  # the model's own draw (ModelEnv._sample), its draws given
            rows = jm.sample(z, params, *sample_draws)
        else:
            rows = jm.predict(z, params)  # (N, n_targets)
        if noise is not None:
            rows = rows + jnp.asarray(noise, dtype=jnp.float64)
        if regime is not None:
            rows = jnp.asarray(regime(states, actions, rows), dtype=jnp.float64)
        nxt, rewards, terminated, diverged, aux = after(states, actions, rows, _as_jax(aux, jnp))
        if pessimism is not None:
            rewards, terminated = pessimism(states, z, rewards, terminated, diverged, params)
        if draws and event_u is not None:
            u = jnp.asarray(event_u, dtype=jnp.float64).reshape(states.shape[0], len(draws))
            for j, (draw, _) in enumerate(draws):
                rewards, terminated = draw(states, actions, nxt, rewards, terminated, diverged, u[:, j], params["events"][j])
        return nxt, rewards, terminated, diverged, aux

    return JaxStepper(step, lambda n, key=None: _as_jax(fresh(n, key), jnp), len(draws), own, key, sampling)


def noise_of(chol: Any, actions: Any, eps: Any) -> Any:
    """(N, n_targets): the step noise of a ``JaxStepper``'s ``params["chol"]`` for discrete
    ``actions`` and standard-normal ``eps`` (N, n_targets), as ``step_noise`` makes it (traceable,
    ``chol`` an argument)."""
    xp = array_namespace(actions, eps, chol)
    a = xp.asarray(actions).reshape(xp.shape(actions)[0], -1)[:, 0].astype(np.intp)
    return xp.einsum("nij,nj->ni", xp.asarray(chol)[a], xp.asarray(eps, dtype=xp.float64))


def jax_step(model_env: Any) -> JaxStep:
    """``step(states, actions, noise=None) -> (next_states, rewards, terminated, diverged)``:
    ``model_env.step`` as a pure jax function, for a step without per-row memory or learned
    events (else ``jax_stepper``; see the module docstring)."""
    stepper = jax_stepper(model_env)
    if model_env._step_batch is not None or stepper.n_event_draws:
        raise NotImplementedError(f"jax_step: env '{model_env.spec.name}': its step keeps per-row memory "
                                  "(task.array_step) or draws learned events: use jax_stepper")
    _, jnp = jax_modules("sdrl_bench.surrogate.jax_step")

    def step(states, actions, noise=None):
        nxt, rewards, terminated, diverged, _ = stepper.step(states, actions, jnp.zeros(jnp.shape(states)[0], jnp.int64),
                                                             noise)
        return nxt, rewards, terminated, diverged

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
        return noise_of(chol, a, eps)
    if eps is not None:
        eps = np.asarray(eps, dtype=float)
        if eps.shape != (n, m):
            raise ValueError(f"step_noise: eps of shape {eps.shape}, expected ({n}, {m})")
    return model_env.noise_rows(a, eps).T  # ModelEnv's own noise (and draws, eps None)


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
    """``reset(key, n, pool=None) -> (n, n_state)`` float64 reset states from a jax PRNG key:
    uniformly from the ModelEnv's reset pool when it has one (given initial states, or the real
    env's first observations; ``pool``: rows of the same width in its place, e.g. the pool as an
    argument of a compiled program, so that one program serves other seeds' pools), else the
    spec's ``initial_state_fn`` (or the ``task.initial_states`` a spec class built) called on
    the key (written with ``envs.functional``'s draws; checked when built: one line naming the
    key or the function). The same distribution as ``ModelEnv.initial_states``, not the same
    draws."""
    jax, jnp = jax_modules("sdrl_bench.surrogate.jax_step")
    spec, task = model_env.spec, model_env.task
    pool = model_env._pool
    if pool is not None:
        own = jnp.asarray(pool, dtype=jnp.float64)

        def from_pool(key, n, pool=None):
            rows = own if pool is None else jnp.asarray(pool, dtype=jnp.float64)
            return rows[jax.random.randint(key, (n,), 0, rows.shape[0])]

        return from_pool
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
    return lambda key, n, pool=None: jnp.asarray(fn(key, n), dtype=jnp.float64)
