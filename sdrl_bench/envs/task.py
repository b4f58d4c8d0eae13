"""What a surrogate needs besides a dynamics model: the env's task, injected, never looked up.

A surrogate env is (dynamics model) + (task), in the style of mbrl-lib's ``ModelEnv``, which
takes its reward and termination as functions. Here the task is one frozen ``Task`` built once
per env spec (``EnvSpec.task``) and checked then: every optional capability is a field that is
either a callable of the documented signature or None, so generic code asks ``task.exogenous is
None`` instead of testing an env's name, a state index or which methods a class overrode.

Signatures (batched: states and next states (N, n_state) in ``state_names`` order, raw actions
(N, raw width)); each is a small ``Protocol`` below:

* ``reward_terminated(s, a, s') -> (reward (N,), terminated (N,) bool)``: required;
* ``initial_states(rng, n) -> (n, n_state)``: the reset distribution (None: states observed
  after real resets, ``surrogate.model_env``);
* ``exogenous(s, a, s') -> (N, n_exogenous)``: the non-regressed states after a step (required
  when the env declares exogenous states);
* ``regime_dynamics(s, a, predicted (n_target, N)) -> (n_target, N)``: the next regressed values
  outside the model's regime (a lander on its legs); None: the model everywhere;
* ``model_regime(s) -> (N,) bool``: rows whose step the model predicts, where its uncertainty
  penalty applies; None: every row;
* ``step_one`` / ``step_batch``: compiled or plain-Python kernels of the step after the
  prediction (``surrogate.model_env`` documents their contract); None: the numpy composition;
* ``array_step``: the same step as ``step_batch`` (and ``regime_dynamics``) written once for
  numpy and jax arrays, with its per-row memory passed in and out (``ArrayStep``), for a jax step
  (``surrogate.jax_step``); None: no such form (a jax step refuses ``step_batch`` then);
* ``termination_causes(s, a, s') -> {cause: (N,) bool}`` and ``observed_causes(rewards,
  terminated) -> {cause: (N,) bool}``: why the surrogate's rules and the real env ended a
  transition (fidelity metrics per cause);
* ``uncertainty``: the MOPO-style pessimism (``Uncertainty``); ``crash_reward``: the reward of a
  step the pessimism ends; ``events``: the declared events (``Event``).

Events are data (``Event``, declared in the env's YAML ``events:`` list, see ``parse_events``):
a trigger (a state condition), the outcomes with how each ends or continues the episode, how a
real event's outcome is observed, the features an event model may use, and optionally a prior
(the outcome a hand-set rule gives). Generic code (``surrogate.events``) learns the outcome model
from the run's own transitions, scores it and steps it.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Any, Protocol

import numpy as np

from sdrl_bench import ConfigError
from sdrl_bench.envs.functional import resolve


class RewardTerminated(Protocol):
    def __call__(self, states: np.ndarray, actions: np.ndarray, next_states: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]: ...


class InitialStates(Protocol):
    def __call__(self, rng: np.random.Generator, n: int) -> np.ndarray: ...


class Transition(Protocol):
    """A function of a batch of transitions (s, a, s') -> (N, ...) values (exogenous states,
    an event's trigger)."""

    def __call__(self, states: np.ndarray, actions: np.ndarray, next_states: np.ndarray) -> np.ndarray: ...


class RegimeDynamics(Protocol):
    def __call__(self, states: np.ndarray, actions: np.ndarray, predicted: np.ndarray) -> np.ndarray: ...


class StateMask(Protocol):
    """A function of states (N, n_state) -> (N,) values (a regime mask, an event's prior outcome)."""

    def __call__(self, states: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class Uncertainty:
    """The surrogate's pessimism where its model's members disagree (MOPO, Yu et al. 2020):
    reward minus ``penalty`` x (disagreement - ``free``)+, and beyond ``limit`` the step ends the
    episode with the task's ``crash_reward``. Disagreement is the largest over regressed states
    of the members' standard deviation in units of ``scale`` (one per regressed state)."""

    scale: tuple[float, ...]
    penalty: float = 0.0
    free: float = 0.0
    limit: float = math.inf

    def __post_init__(self) -> None:
        object.__setattr__(self, "scale", tuple(float(s) for s in self.scale))
        if not self.scale or not all(math.isfinite(s) and s > 0 for s in self.scale):
            raise ConfigError(f"env.spec.uncertainty.scale: positive finite numbers are required, got {self.scale!r}")
        for key in ("penalty", "free"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"env.spec.uncertainty.{key}: a finite number >= 0 is required, got {v!r}")
        if isinstance(self.limit, bool) or not isinstance(self.limit, (int, float)) or not self.limit > 0:
            raise ConfigError(f"env.spec.uncertainty.limit: a number > 0 (or .inf) is required, got {self.limit!r}")

    @property
    def active(self) -> bool:
        return self.penalty > 0 or math.isfinite(self.limit)


@dataclass(frozen=True)
class Outcome:
    """One outcome of an event."""

    name: str
    ends: bool = False
    """Whether the outcome ends the episode (terminated)."""
    reward: float | None = None
    """The step's reward when the event ends this way (None: the task's own reward)."""
    within: int | None = None
    """How a real event is seen to end this way: its episode terminates within this many steps
    of the trigger row (None: this outcome is not observed by termination; see ``Event``)."""
    observed_reward: float | None = None
    """... and, when given, with this reward on the terminating step."""


@dataclass(frozen=True)
class Event:
    """An event of an env's dynamics that a regression model does not describe (a touchdown, an
    impact): where it happens, what can follow, and what tells its outcome apart.

    ``outcomes[0]`` is the default: what a real event counts as when no other outcome is
    observed within its window, and what the surrogate does when neither a prior nor a learned
    model says otherwise. A real event whose episode stops (truncated, or the data end) before
    an outcome could be seen is left out of the event data.
    """

    name: str
    trigger: Transition
    """(s, a, s') -> (N,) bool: the event happens on this step."""
    features: Callable[[np.ndarray], np.ndarray]
    """Pre-event states (N, n_state) -> (N, F) features of the outcome model."""
    feature_names: tuple[str, ...]
    outcomes: tuple[Outcome, ...]
    prior: StateMask | None = None
    """Pre-event states -> the outcome index a hand-set rule gives (a prior; the env's own kernels
    may already apply it). None: no prior."""
    learn_on: str = "open"
    """Which real events train the outcome model: ``open`` (those the prior leaves at the
    default outcome) or ``all``."""
    once_per_episode: bool = True
    """Only each real episode's first trigger counts as an event in the data (later ones follow
    from the first: bounces)."""
    min_events: int = 8
    """Real events (of ``learn_on``) needed, with at least two outcomes seen, before a model is fitted."""

    @property
    def outcome_names(self) -> tuple[str, ...]:
        return tuple(o.name for o in self.outcomes)

    @property
    def window(self) -> int:
        """Steps after the trigger over which an outcome is observed (the largest ``within``)."""
        return max((o.within for o in self.outcomes if o.within is not None), default=1)


@dataclass(frozen=True)
class ArrayStep:
    """A task's kernels as array functions (``envs.functional.array_namespace``: numpy or jax),
    for a step compiled by jax (``surrogate.jax_step``). Predictions are (N, n_target) here (the
    jax step's layout); the per-row memory a compiled kernel keeps between calls (``step_batch``:
    a counter per row) is ``aux`` (N,) or a tuple of such per-row arrays, passed in and out, fresh
    per episode (``init_aux``)."""

    step: Callable[..., Callable]
    """``step(limit, obs_low, obs_high) -> f(s, a, predicted, aux) -> (s', reward (N,),
    terminated (N,) bool, diverged (N,) bool, aux)``: ``step_batch``'s step for predictions with
    ``regime_dynamics`` applied (a diverged row keeps its state and memory, reward 0)."""
    init_aux: Callable[..., Any]
    """``init_aux(n, key=None)``: the memory of n fresh episodes; ``key`` (a numpy Generator or a
    jax PRNG key) where that memory is drawn at random (e.g. a terrain per episode)."""
    regime_dynamics: Callable[..., Any] | None = None
    """``(s, a, predicted (N, n_target)) -> (N, n_target)``: ``Task.regime_dynamics``; None: the model everywhere."""

    def __post_init__(self) -> None:
        for key in ("step", "init_aux", "regime_dynamics"):
            fn = getattr(self, key)
            if not callable(fn) and not (fn is None and key == "regime_dynamics"):
                raise ConfigError(f"env task: array_step.{key} must be a function, got {type(fn).__name__}")


@dataclass(frozen=True)
class Task:
    """An env's task for a surrogate (see the module docstring); checked at construction."""

    reward_terminated: RewardTerminated
    initial_states: InitialStates | None = None
    exogenous: Transition | None = None
    regime_dynamics: RegimeDynamics | None = None
    model_regime: StateMask | None = None
    step_one: Callable[..., Any] | None = None
    """``step_one(predictor, obs_low, obs_high) -> one-state step or None`` (see ``surrogate.model_env``)."""
    step_batch: Callable[..., Any] | None = None
    """``step_batch(limit, obs_low, obs_high, rng) -> batched step or None``."""
    array_step: ArrayStep | None = None
    """``step_batch`` and ``regime_dynamics`` for numpy and jax arrays (``ArrayStep``), or None."""
    termination_causes: Transition | None = None
    observed_causes: Callable[[np.ndarray, np.ndarray], dict] | None = None
    crash_reward: float | None = None
    uncertainty: Uncertainty | None = None
    events: tuple[Event, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        for key in ("reward_terminated", "initial_states", "exogenous", "regime_dynamics", "model_regime",
                    "step_one", "step_batch", "termination_causes", "observed_causes"):
            fn = getattr(self, key)
            if fn is not None and not callable(fn):
                raise ConfigError(f"env task: {key} must be a function, got {type(fn).__name__}")
        if self.reward_terminated is None:
            raise ConfigError("env task: reward_terminated is required")
        if self.array_step is not None and not isinstance(self.array_step, ArrayStep):
            raise ConfigError(f"env task: array_step must be an ArrayStep, got {type(self.array_step).__name__}")
        if self.uncertainty is not None and math.isfinite(self.uncertainty.limit) and self.crash_reward is None:
            raise ConfigError("env.spec.crash_reward: required with a finite env.spec.uncertainty.limit "
                              "(the reward of a step the limit ends)")
        names = [e.name for e in self.events]
        if len(set(names)) != len(names):
            raise ConfigError(f"env.spec.events: duplicate event names {names}")


# ---------------------------------------------------------------------- from YAML
def bind_spec(fn: Callable | None, spec: Any) -> Callable | None:
    """``fn`` with ``spec=spec`` bound when it takes a ``spec`` keyword (a task function that
    reads the env's constants: LunarLander's touchdown prior reads its rules)."""
    if fn is None:
        return None
    try:
        params = inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return fn
    return partial(fn, spec=spec) if "spec" in params else fn


_EVENT_KEYS = {"name", "trigger", "features", "feature_names", "outcomes", "prior", "learn_on", "once_per_episode",
               "min_events"}
_OUTCOME_KEYS = {"name", "ends", "reward", "within", "observed_reward"}


def _number(value: Any, key: str, allow_none: bool = True) -> float | None:
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{key}: a finite number is required, got {value!r}")
    return float(value)


def _outcome(node: Any, key: str) -> Outcome:
    if not isinstance(node, dict) or not isinstance(node.get("name"), str):
        raise ConfigError(f"{key}: an outcome is a mapping with a name (and ends, reward, within, observed_reward)")
    unknown = sorted(set(node) - _OUTCOME_KEYS)
    if unknown:
        raise ConfigError(f"{key}.{unknown[0]}: unknown key; known: {', '.join(sorted(_OUTCOME_KEYS))}")
    ends = node.get("ends", False)
    if not isinstance(ends, bool):
        raise ConfigError(f"{key}.ends: true or false, got {ends!r}")
    within = node.get("within")
    if within is not None and (isinstance(within, bool) or not isinstance(within, int) or within < 1):
        raise ConfigError(f"{key}.within: a positive integer (steps) or null, got {within!r}")
    if node.get("observed_reward") is not None and within is None:
        raise ConfigError(f"{key}.observed_reward: needs within (the steps after the trigger it is looked for)")
    return Outcome(node["name"], ends, _number(node.get("reward"), f"{key}.reward"), within,
                   _number(node.get("observed_reward"), f"{key}.observed_reward"))


def _feature_fn(node: Any, state_names: Sequence[str], key: str) -> tuple[Callable, tuple[str, ...] | None]:
    """``features:`` as a list of state names (their pre-event values) or a dotted path."""
    if isinstance(node, (list, tuple)):
        missing = [n for n in node if n not in state_names]
        if missing or not node:
            raise ConfigError(f"{key}: {missing or 'empty'} are not state names ({list(state_names)})")
        cols = [list(state_names).index(n) for n in node]
        return (lambda states: np.asarray(states, dtype=float)[:, cols]), tuple(str(n) for n in node)
    return resolve(node, key), None


def parse_events(nodes: Any, spec: Any) -> tuple[Event, ...]:
    """The ``events:`` list of an env's spec config as ``Event``s (dotted paths resolved, each
    error one line naming the key)::

        events:
          - name: impact
            trigger: my_envs.task.impact          # (s, a, s') -> bool: the step hits the floor
            features: [v]                         # state names, or a dotted path (states) -> (N, F)
            outcomes:
              - {name: bounce}                    # the default: the episode goes on
              - {name: break, ends: true, reward: -10.0, within: 1, observed_reward: -10.0}
            prior: null                           # optional: (states) -> outcome index
    """
    if nodes is None:
        return ()
    if not isinstance(nodes, (list, tuple)):
        raise ConfigError(f"env.spec.events: a list of events, got {type(nodes).__name__}")
    return tuple(node if isinstance(node, Event) else _event(node, spec, f"env.spec.events[{i}]")
                 for i, node in enumerate(nodes))


def _check_mapping(node: Any, key: str, what: str, known: set[str], required: Sequence[str]) -> None:
    """One line naming ``key`` for a node that is not a mapping, has an unknown key or lacks a
    required one (None or empty)."""
    if not isinstance(node, dict):
        raise ConfigError(f"{key}: {what} is a mapping ({', '.join(required)}, ...)")
    unknown = sorted(set(node) - known)
    if unknown:
        raise ConfigError(f"{key}.{unknown[0]}: unknown key; known: {', '.join(sorted(known))}")
    for req in required:
        value = node.get(req)
        if value is None or (hasattr(value, "__len__") and len(value) == 0):
            raise ConfigError(f"{key}.{req}: required")


def _event(node: Any, spec: Any, key: str) -> Event:
    _check_mapping(node, key, "an event", _EVENT_KEYS, ("name", "trigger", "features", "outcomes"))
    features, names = _feature_fn(node["features"], spec.state_names, f"{key}.features")
    names = names or tuple(str(n) for n in node.get("feature_names") or ())
    if not names:
        raise ConfigError(f"{key}.feature_names: name the columns of a features function")
    outcomes = node["outcomes"]
    if not isinstance(outcomes, (list, tuple)) or len(outcomes) < 2:
        raise ConfigError(f"{key}.outcomes: at least two outcomes (the first is the default)")
    parsed = tuple(_outcome(o, f"{key}.outcomes[{j}]") for j, o in enumerate(outcomes))
    if len({o.name for o in parsed}) != len(parsed):
        raise ConfigError(f"{key}.outcomes: duplicate outcome names")
    if not any(o.within is not None for o in parsed[1:]):
        raise ConfigError(f"{key}.outcomes: no outcome but the default says how it is observed (within:)")
    learn_on = node.get("learn_on", "open")
    if learn_on not in ("open", "all"):
        raise ConfigError(f"{key}.learn_on: 'open' or 'all', got {learn_on!r}")
    once = node.get("once_per_episode", True)
    if not isinstance(once, bool):
        raise ConfigError(f"{key}.once_per_episode: true or false, got {once!r}")
    min_events = node.get("min_events", 8)
    if isinstance(min_events, bool) or not isinstance(min_events, int) or min_events < 2:
        raise ConfigError(f"{key}.min_events: an integer >= 2, got {min_events!r}")
    return Event(name=str(node["name"]), trigger=bind_spec(resolve(node["trigger"], f"{key}.trigger"), spec),
                 features=bind_spec(features, spec), feature_names=names, outcomes=parsed,
                 prior=bind_spec(resolve(node.get("prior"), f"{key}.prior"), spec), learn_on=learn_on,
                 once_per_episode=once, min_events=min_events)


def parse_uncertainty(node: Any, scale: Sequence[float] | None) -> Uncertainty | None:
    """``uncertainty: {penalty, free, limit, scale}`` (``scale`` from the config, else the env's
    own default, e.g. its replay noise floor's standard deviation); None without a node."""
    if node is None or isinstance(node, Uncertainty):
        return node
    if not isinstance(node, dict):
        raise ConfigError(f"env.spec.uncertainty: a mapping (penalty, free, limit, scale), got {node!r}")
    unknown = sorted(set(node) - {"penalty", "free", "limit", "scale"})
    if unknown:
        raise ConfigError(f"env.spec.uncertainty.{unknown[0]}: unknown key; known: free, limit, penalty, scale")
    values = {k: node[k] for k in ("penalty", "free", "limit") if k in node}
    chosen = node.get("scale", scale)
    if chosen is None:
        raise ConfigError("env.spec.uncertainty.scale: required (one standard deviation per regressed state)")
    return Uncertainty(scale=tuple(chosen), **values)


# ---------------------------------------------------------------------- priors
PRIOR_KINDS = ("fitted", "simulator", "simulator_knowledge", "knowledge")
"""What a prior is: ``fitted`` on real data (its real steps count in every run that uses it);
``simulator``: measured with what only a resettable simulator gives (replays from a saved state;
a user with a physical system could not collect it); ``simulator_knowledge``: constants read off a
simulator's source that a physical system would not reveal (Box2D's sleep thresholds);
``knowledge``: what a user of the real system knows without running it (its documented
interface, units, dt, bounds, the reward's definition)."""


@dataclass(frozen=True)
class Prior:
    """A declared prior of an env's surrogate: what it sets, where it comes from, what it cost."""

    name: str
    kind: str
    sets: tuple[str, ...]
    """The constants or config keys it sets (``rules.touchdown_speed``, ``uncertainty.scale``, ...)."""
    source: str
    """Where it comes from: a study and its command, or a document (the env's source, its docs)."""
    real_steps: int = 0
    """Real env steps it was fitted on (``fitted``)."""
    simulator_steps: int = 0
    """Steps replayed from saved simulator states (``simulator``)."""
    expert: str | None = None
    """The trained agent it needed, as ``<env>-<algo>-n<budget>`` (its training counts once per run)."""
    file: str | None = None
    """A data file the prior is, when named: it must exist."""

    @property
    def expert_steps(self) -> int:
        return expert_budget(self.expert)


def expert_budget(expert: str | None) -> int:
    """The training steps of an expert named ``<env>-<algo>-n<budget>`` (0 for None)."""
    if not expert:
        return 0
    tail = expert.rsplit("-n", 1)[-1]
    return int(tail) if tail.isdigit() else 0


_PRIOR_KEYS = {"name", "kind", "sets", "source", "real_steps", "simulator_steps", "expert", "file"}


def parse_priors(nodes: Any) -> tuple[Prior, ...]:
    """The ``priors:`` list of an env's spec config (each error one line naming the key)."""
    from pathlib import Path

    if nodes is None:
        return ()
    if not isinstance(nodes, (list, tuple)):
        raise ConfigError(f"env.spec.priors: a list of priors, got {type(nodes).__name__}")
    out = []
    for i, node in enumerate(nodes):
        key = f"env.spec.priors[{i}]"
        if isinstance(node, Prior):
            out.append(node)
            continue
        _check_mapping(node, key, "a prior", _PRIOR_KEYS, ("name", "kind", "sets", "source"))
        if node["kind"] not in PRIOR_KINDS:
            raise ConfigError(f"{key}.kind: one of {', '.join(PRIOR_KINDS)}, got {node['kind']!r}")
        for k in ("real_steps", "simulator_steps"):
            v = node.get(k, 0)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ConfigError(f"{key}.{k}: an integer >= 0, got {v!r}")
        if node["kind"] == "fitted" and not node.get("real_steps"):
            raise ConfigError(f"{key}.real_steps: a fitted prior names the real steps it was fitted on")
        if node.get("file") is not None and not Path(node["file"]).is_file():
            raise ConfigError(f"{key}.file: no such file: {node['file']}")
        sets = node["sets"] if isinstance(node["sets"], (list, tuple)) else [node["sets"]]
        out.append(Prior(str(node["name"]), node["kind"], tuple(str(s) for s in sets), str(node["source"]),
                         int(node.get("real_steps", 0)), int(node.get("simulator_steps", 0)), node.get("expert"),
                         node.get("file")))
    names = [p.name for p in out]
    if len(set(names)) != len(names):
        raise ConfigError(f"env.spec.priors: duplicate names {names}")
    return tuple(out)
