"""Environment specs: what the project knows about a real Gymnasium environment.

``EnvSpec`` is the one required interface of an env, plain data checked at construction: it
names the state variables, says which of them a dynamics model regresses (``target_names``) and
which it takes as given inputs (``exogenous_names``, e.g. contact flags), encodes actions as
model inputs, applies the known state bounds the way the real environment applies them, and names
the fixed held-out test set. States vs observations: ``state_names`` are the coordinates the
model regresses and the task functions see (a dataset records them); ``observation_names`` the
real env's observation, which the agent sees; they differ only under an observation map
(``angles``: an angle observed as (cos, sin)).

Everything a surrogate needs besides the model is the env's **task** (``EnvSpec.task``, an
``envs.task.Task``): reward and termination, the reset distribution, exogenous states, events,
the pessimism of its uncertainty, optional kernels. The generic spec builds it from dotted paths
of plain functions and the YAML's ``events`` / ``uncertainty`` / ``crash_reward``; a spec class
with env knowledge (``envs/<env>/``) overrides ``build_task``. Optional data hooks with neutral
defaults: ``regimes`` / ``fit_rows`` (per-regime fits and scores), ``noise_floor``,
``task_fidelity``, ``heuristic_policy``, ``is_success``.

Envs are found by their config (``find_spec``: ``env/<name>.yaml`` of the config tree); generic
code imports this module, ``envs.task`` and ``envs.functional``, never an env's own package (an
import-linter contract and ``tests/test_env_agnostic.py`` keep it so).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from functools import cached_property
from typing import Any
from collections.abc import Callable, Sequence

import gymnasium as gym
import numpy as np

from sdrl_bench import ConfigError, seeds
from sdrl_bench.envs import functional
from sdrl_bench.envs.functional import resolve, spec_from_config
from sdrl_bench.envs.task import Task, parse_events, parse_priors, parse_uncertainty

Policy = Callable[[np.ndarray], Any]
StepOne = Callable[[list, Any], tuple[np.ndarray, list, float, bool, bool]]
"""One surrogate step of one env in plain Python: (state, raw action) -> (observation,
next state as floats, reward, terminated, diverged). See ``surrogate.model_env``."""


def _readonly(values: list[int]) -> np.ndarray:
    arr = np.array(values, dtype=int)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True)
class EnvSpec:
    """Generic spec for an environment with a Box observation space."""

    name: str
    """Short name used in run names, tags and file names (e.g. ``mountain_car``)."""
    gym_id: str
    """Gymnasium id passed to ``gymnasium.make``."""
    state_names: tuple[str, ...]
    """Names of the observation variables, in observation order."""
    action_names: tuple[str, ...] = ("u",)
    """Names of the encoded action features the model sees (one-hot names for discrete)."""
    gym_kwargs: dict = field(default_factory=dict)
    """Extra keyword arguments for ``gymnasium.make``."""
    exogenous_names: tuple[str, ...] = ()
    """State variables the model takes as inputs but does not regress."""
    state_low: tuple[float, ...] | None = None
    """Lower bounds the real env clips the state to (None: no clipping)."""
    state_high: tuple[float, ...] | None = None
    """Upper bounds the real env clips the state to."""
    max_episode_steps: int = 1000
    """Steps after which the real env truncates an episode."""
    solved_threshold: float | None = None
    """Mean return at which the task counts as solved."""
    obs_dtype: str = "float32"
    """dtype of the real env's observations."""
    n_discrete_actions: int = 0
    """0 for a continuous (Box) action space; else the number of discrete actions, one-hot
    encoded as model inputs named by ``action_names``."""
    action_labels: tuple[str, ...] = ()
    """Readable names of the discrete actions, for figures (default: ``action_names``)."""
    policy_map_slices: tuple = ()
    """2-D slices of the state space the policy maps show: ``(x name, (low, high), y name,
    (low, high))`` each. Empty: the first two regressed states over their bounds (or +-1)."""
    policy_map_hold: dict = field(default_factory=dict)
    """Values of the states off a slice's axes in the policy maps (others are 0)."""
    action_encoding: str = "auto"
    """How raw actions become model inputs. Discrete: ``one_hot`` (one input per action, named
    by ``action_names``; "auto"), ``index`` (one input, the action's index) or ``values`` (the
    action's physical values from ``action_values``: CartPole's push left / right as a force
    -1 / +1, which keeps the law sparse). Continuous: ``raw`` (as given; "auto") or ``clip``
    (clipped to the real env's action space, as most envs clip before acting)."""
    action_values: tuple = ()
    """For ``action_encoding: values``: one entry per discrete action, a number (or a list, one
    number per name in ``action_names``)."""
    observation_names: tuple[str, ...] = ()
    """Names of the real env's observation components when they differ from ``state_names``
    (an observation map such as ``angles``). Empty: the observation is the state."""
    angles: dict = field(default_factory=dict)
    """Angle-valued states the real env observes as a (cos, sin) pair: ``{th: [cos_th, sin_th]}``.
    The model regresses the angle (atan2 of the pair; the next angle unwrapped next to the
    current one, so th' = th + 0.05 thdot' stays exact across +-pi); the surrogate wraps it to
    [-pi, pi) and emits cos and sin, which stay on the circle."""
    circle_pairs: tuple = ()
    """Pairs of regressed states that lie on the unit circle, ``[[cos_th, sin_th]]``: an angle
    modelled by its cos and sin rather than mapped (``angles``). The surrogate projects each
    predicted pair back onto the circle every step (SINDy-RL's renormalisation); a pair at the
    origin is left as it is."""
    reward_fn: str | None = None
    """Dotted path of ``reward(states, actions, next_states) -> (N,)`` (batched, states in
    ``state_names`` order, raw actions (N, raw width)); makes the spec a task for a surrogate."""
    termination_fn: str | None = None
    """Dotted path of ``terminated(states, actions, next_states) -> (N,) bool`` (default: never)."""
    initial_state_fn: str | None = None
    """Dotted path of ``initial_states(rng, n) -> (n, n_state)`` (default: states observed after
    real resets)."""
    heuristic_fn: str | None = None
    """Dotted path of a controller ``policy(observation) -> action`` (for ``collector=heuristic``)."""
    exogenous_fn: str | None = None
    """Dotted path of ``exogenous(states, actions, next_states) -> (N, n_exogenous)``: the
    non-regressed states after a step (an event hook such as a contact flag)."""
    termination_causes_fn: str | None = None
    """Dotted path of ``causes(states, actions, next_states) -> {name: (N,) bool}``: why the
    surrogate's rules end each transition (tracked per cause in fidelity metrics)."""
    fit_regime: str | None = None
    """Fit the dynamics model on this regime's rows only (a name ``regimes`` gives, e.g. a
    lander's flight: the regime the model describes); None: all rows."""
    events: tuple = ()
    """The env's events (``envs.task.parse_events``: name, trigger, features, outcomes, prior):
    what the dynamics model does not describe, learned from each run's own transitions."""
    uncertainty: dict | None = None
    """The surrogate's pessimism where an ensemble's members disagree (``envs.task.Uncertainty``:
    ``{penalty, free, limit, scale}``); None: none."""
    crash_reward: float | None = None
    """The reward of a step the pessimism's limit ends (an env's crash value)."""
    priors: tuple = ()
    """What the env's surrogate takes from outside the run (``envs.task.parse_priors``): fitted
    constants with the real steps behind them, simulator measurements, simulator knowledge,
    knowledge. Every run that uses the env counts the fitted ones' real steps."""
    reset_seed_bits: int = 64
    """The widest reset seed the real env accepts. The harness's reset seeds are 64-bit
    (``seeds.reset_seed``); an env that takes 32 (dm_control through shimmy seeds a legacy
    ``RandomState``) gets each one hashed to 32 bits (``FoldResetSeed``)."""
    flatten_observation: bool = False
    """Wrap the real env in gymnasium's ``FlattenObservation``: a Dict observation (dm_control
    through shimmy: ``position``, ``velocity``) becomes one Box, its keys' arrays concatenated in
    the space's order; ``observation_names`` name the flattened entries."""
    own_data: bool = False
    """Learn from each fit's own transitions the constants the env can learn
    (``learned_constants``) and the pessimism's scale and free band (``surrogate.own_data``),
    in place of the priors that set them: a prior all of whose constants were learned no
    longer counts. False: the declared priors as they are."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "state_names", tuple(self.state_names))
        object.__setattr__(self, "action_names", tuple(self.action_names))
        object.__setattr__(self, "exogenous_names", tuple(self.exogenous_names))
        if len(set(self.state_names)) != len(self.state_names):
            raise ConfigError(f"env.spec.state_names: duplicate names in {self.state_names}")
        unknown = set(self.exogenous_names) - set(self.state_names)
        if unknown:
            raise ConfigError(f"env.spec.exogenous_names: {sorted(unknown)} are not state names")
        for key, unbounded in (("state_low", -np.inf), ("state_high", np.inf)):
            bound = getattr(self, key)
            if bound is not None:  # a null entry: that variable is unbounded
                bound = tuple(unbounded if b is None else float(b) for b in bound)
                object.__setattr__(self, key, bound)
                if len(bound) != len(self.state_names):
                    raise ConfigError(
                        f"env.spec.{key}: {len(bound)} values for {len(self.state_names)} states"
                    )
        if self.state_low is not None and self.state_high is not None:
            if any(lo >= hi for lo, hi in zip(self.state_low, self.state_high, strict=True)):
                raise ConfigError("env.spec.state_low must be below env.spec.state_high everywhere")
        self._check_actions()
        if self.max_episode_steps <= 0:
            raise ConfigError("env.spec.max_episode_steps must be positive")
        try:
            float_obs = np.issubdtype(np.dtype(self.obs_dtype), np.floating)
        except TypeError:
            float_obs = False
        if not float_obs:
            raise ConfigError(f"env.spec.obs_dtype: a float type (float32, float64) is required, got {self.obs_dtype!r}")
        if isinstance(self.reset_seed_bits, bool) or not isinstance(self.reset_seed_bits, int) \
                or not 16 <= self.reset_seed_bits <= 64:
            raise ConfigError(f"env.spec.reset_seed_bits: an integer in [16, 64] is required, got {self.reset_seed_bits!r}")
        object.__setattr__(self, "action_labels", tuple(self.action_labels))
        n_actions = self.n_discrete_actions or len(self.action_names)
        if self.action_labels and len(self.action_labels) != n_actions:
            raise ConfigError(f"env.spec.action_labels: {len(self.action_labels)} labels for {n_actions} actions")
        self._check_observation_map()
        self._check_circle_pairs()
        fns = {k: resolve(getattr(self, k), f"env.spec.{k}") for k in _TASK_FNS}
        object.__setattr__(self, "_fns", fns)
        object.__setattr__(self, "events", tuple(self.events or ()))
        object.__setattr__(self, "_events", parse_events(self.events, self))
        object.__setattr__(self, "priors", tuple(self.priors or ()))
        object.__setattr__(self, "declared_priors", parse_priors(self.priors))
        if self.crash_reward is not None and (isinstance(self.crash_reward, bool) or not np.isfinite(self.crash_reward)):
            raise ConfigError(f"env.spec.crash_reward: a finite number, got {self.crash_reward!r}")
        slices = tuple(_parse_slice(sl, i, self.state_names) for i, sl in enumerate(self.policy_map_slices))
        object.__setattr__(self, "policy_map_slices", slices)
        unknown = set(self.policy_map_hold) - set(self.state_names)
        if unknown:
            raise ConfigError(f"env.spec.policy_map_hold: {sorted(unknown)} are not state names")

    def _check_actions(self) -> None:
        enc, k, names = self.action_encoding, self.n_discrete_actions, self.action_names
        allowed = ("one_hot", "index", "values") if k else ("raw", "clip")
        if enc == "auto":
            enc = allowed[0]
            object.__setattr__(self, "action_encoding", enc)
        if enc not in allowed:
            kind = "discrete" if k else "continuous"
            raise ConfigError(f"env.spec.action_encoding: {enc!r} for {kind} actions; one of {list(allowed)}")
        if enc == "one_hot" and len(names) != k:
            raise ConfigError(f"env.spec.action_names: {len(names)} names for {k} one-hot encoded discrete actions "
                              "(or set env.spec.action_encoding: index / values)")
        if enc == "index" and len(names) != 1:
            raise ConfigError(f"env.spec.action_names: the index encoding is one input; got {len(names)} names")
        if enc == "values":
            try:
                table = np.array([np.atleast_1d(np.asarray(v, dtype=float)) for v in self.action_values], dtype=float)
            except (TypeError, ValueError):
                table = np.zeros((0, 0))
            if table.shape != (k, len(names)) or not np.all(np.isfinite(table)):
                raise ConfigError(f"env.spec.action_values: need {k} entries (one per discrete action) of "
                                  f"{len(names)} finite number(s) for {list(names)}, got {list(self.action_values)!r}")
            table.setflags(write=False)
            object.__setattr__(self, "_action_table", table)
        elif self.action_values:
            raise ConfigError(f"env.spec.action_values: only used with action_encoding: values (not {enc!r})")
        object.__setattr__(self, "action_values", tuple(self.action_values))

    def _check_observation_map(self) -> None:
        """Validate ``observation_names`` / ``angles``; store which state or angle each
        observation component comes from."""
        object.__setattr__(self, "observation_names", tuple(self.observation_names))
        angles = {str(a): tuple(pair) for a, pair in dict(self.angles).items()}
        object.__setattr__(self, "angles", angles)
        if not self.observation_names:
            if angles:
                raise ConfigError("env.spec.angles: name the real observation too (env.spec.observation_names)")
            return
        obs = self.observation_names
        if len(set(obs)) != len(obs):
            raise ConfigError(f"env.spec.observation_names: duplicate names in {list(obs)}")
        source: dict[str, tuple[str, str]] = {}
        for a, pair in angles.items():
            if a not in self.state_names:
                raise ConfigError(f"env.spec.angles: '{a}' is not a state name ({list(self.state_names)})")
            if len(pair) != 2 or any(p not in obs for p in pair):
                raise ConfigError(f"env.spec.angles.{a}: expected [cos name, sin name] from observation_names "
                                  f"{list(obs)}, got {list(pair)}")
            source[pair[0]], source[pair[1]] = ("cos", a), ("sin", a)
        for n in obs:
            if n not in source and n not in self.state_names:
                raise ConfigError(f"env.spec.observation_names: '{n}' is neither a state nor the cos / sin of an angle")
        missing = [n for n in self.state_names if n not in obs and n not in angles]
        if missing:
            raise ConfigError(f"env.spec.state_names: {missing} are neither observed nor angles (env.spec.angles)")
        object.__setattr__(self, "_obs_source", tuple(source.get(n, ("state", n)) for n in obs))

    def _check_circle_pairs(self) -> None:
        """Validate ``circle_pairs``: pairs of distinct regressed states, each in one pair; store
        their columns among the regressed states."""
        pairs = tuple(tuple(str(n) for n in p) if isinstance(p, (list, tuple)) else p for p in self.circle_pairs)
        object.__setattr__(self, "circle_pairs", pairs)
        seen: list[str] = []
        for i, pair in enumerate(pairs):
            if not isinstance(pair, tuple) or len(pair) != 2 or pair[0] == pair[1]:
                raise ConfigError(f"env.spec.circle_pairs[{i}]: expected [cos name, sin name], two distinct state names, "
                                  f"got {pair!r}")
            bad = [n for n in pair if n not in self.target_names]
            if bad:
                raise ConfigError(f"env.spec.circle_pairs[{i}]: {bad} are not regressed states ({list(self.target_names)})")
            if set(pair) & set(seen):
                raise ConfigError(f"env.spec.circle_pairs[{i}]: {sorted(set(pair) & set(seen))} already in another pair")
            seen.extend(pair)
        cols = np.array([[self.target_names.index(n) for n in pair] for pair in pairs], dtype=int).reshape(-1, 2)
        cols.setflags(write=False)
        object.__setattr__(self, "_circle_cols", cols)

    def __reduce__(self):
        """Pickled as its fields and rebuilt (checked again; the task's functions are rebuilt,
        not pickled: some are closures)."""
        return (_rebuild_spec, (type(self), {f.name: getattr(self, f.name) for f in fields(self) if f.init}))

    # ------------------------------------------------------------------ names and indices
    # Derived from frozen fields, so computed once (cached_property writes the instance dict,
    # which a frozen dataclass allows); the index arrays are read-only.
    @cached_property
    def target_names(self) -> tuple[str, ...]:
        """State variables the dynamics model regresses."""
        return tuple(n for n in self.state_names if n not in self.exogenous_names)

    @cached_property
    def target_index(self) -> np.ndarray:
        return _readonly([self.state_names.index(n) for n in self.target_names])

    @cached_property
    def exogenous_index(self) -> np.ndarray:
        return _readonly([self.state_names.index(n) for n in self.exogenous_names])

    @cached_property
    def control_names(self) -> tuple[str, ...]:
        """Model inputs besides the regressed states: exogenous states, then action features."""
        return self.exogenous_names + self.action_names

    @cached_property
    def input_names(self) -> tuple[str, ...]:
        return self.target_names + self.control_names

    # ------------------------------------------------------------------ the real env
    def check_registered(self) -> None:
        """The real env is registered with gymnasium (``gym_id`` ``my_module:MyEnv-v0`` imports
        ``my_module`` first, as ``gymnasium.make`` does); else one line naming the cause."""
        module, sep, env_id = self.gym_id.rpartition(":")
        if sep:
            functional.import_object(f"{module}:__name__", f"env.spec.gym_id ({self.gym_id!r})")
        try:
            gym.spec(env_id)
        except Exception as exc:  # gymnasium raises several error types for unknown ids
            cause = functional.one_line(exc).split(" Did you mean", 1)[0]  # its guess is of another env
            fix = (f"module '{module}' imported, but it registers no {env_id!r}: check the id its gymnasium.register "
                   "call gives" if sep else "call gymnasium.register in your module and name it "
                   "'my_module:MyEnv-v0' so that it is imported first")
            raise ConfigError(f"env.spec.gym_id: {env_id!r} is not registered with gymnasium ({cause}); {fix}") from None

    def make_env(self, **kwargs: Any) -> gym.Env:
        env = gym.make(self.gym_id, **{**self.gym_kwargs, **kwargs})
        if self.reset_seed_bits < 64:
            env = FoldResetSeed(env, self.reset_seed_bits)
        return gym.wrappers.FlattenObservation(env) if self.flatten_observation else env

    @property
    def raw_action_width(self) -> int:
        """Columns of a raw action in a dataset (1 for a discrete action index)."""
        return 1 if self.n_discrete_actions else len(self.action_names)

    def encode_actions(self, actions: np.ndarray) -> np.ndarray:
        """Raw actions (N, raw width) -> model action features (N, len(action_names)), by
        ``action_encoding``."""
        xp = functional.array_namespace(actions)  # numpy, or jax.numpy in a compiled step
        actions = xp.asarray(actions, dtype=float).reshape(-1, self.raw_action_width)
        enc = self.action_encoding
        if enc == "raw":
            return actions
        if enc == "clip":
            low, high = action_bounds(self)
            return xp.clip(actions, low, high)
        index = actions[:, 0].astype(int)
        if enc == "one_hot":
            return xp.eye(self.n_discrete_actions)[index]
        if enc == "index":
            return actions[:, :1] + 0.0  # a copy
        return xp.asarray(self._action_table)[index]

    # ------------------------------------------------------------------ observations <-> states
    @property
    def obs_names(self) -> tuple[str, ...]:
        """Names of the real env's observation components (``state_names`` without a map)."""
        return self.observation_names or self.state_names

    @property
    def maps_observations(self) -> bool:
        """Whether observations differ from states (an observation map is declared)."""
        return bool(self.observation_names)

    def observe(self, states: np.ndarray) -> np.ndarray:
        """States (N, n_state) -> the real env's observations (N, n_obs): each angle's cos and
        sin, the other states as they are. The identity (the same array) without a map."""
        if not self.maps_observations:
            return states
        xp = functional.array_namespace(states)  # numpy, or jax.numpy in a compiled step
        states = xp.asarray(states, dtype=float)
        cols = []
        for kind, name in self._obs_source:
            col = states[..., self.state_names.index(name)]
            cols.append(xp.cos(col) if kind == "cos" else xp.sin(col) if kind == "sin" else col)
        return xp.stack(cols, axis=-1)

    def coordinates(self, observations: np.ndarray, reference: np.ndarray | None = None) -> np.ndarray:
        """Real observations (N, n_obs) -> states (N, n_state): angles by atan2 in [-pi, pi],
        or, given the ``reference`` states (the step's current states), unwrapped to lie
        within pi of them (a step's angle change stays continuous). Identity without a map."""
        if not self.maps_observations:
            return observations
        obs = np.asarray(observations, dtype=float)
        out = np.empty(obs.shape[:-1] + (len(self.state_names),))
        for i, n in enumerate(self.state_names):
            if n in self.angles:
                c, s = (self.obs_names.index(p) for p in self.angles[n])
                out[..., i] = np.arctan2(obs[..., s], obs[..., c])
                if reference is not None:
                    ref = np.asarray(reference, dtype=float)[..., i]
                    out[..., i] = ref + wrap_angle(out[..., i] - ref)
            else:
                out[..., i] = obs[..., self.obs_names.index(n)]
        return out

    @cached_property
    def angle_index(self) -> np.ndarray:
        """Columns of the angle-valued states (in ``state_names``)."""
        return _readonly([self.state_names.index(a) for a in self.angles])

    def random_action(self, rng: np.random.Generator, env: gym.Env) -> Any:
        space = env.action_space
        if isinstance(space, gym.spaces.Discrete):
            return int(rng.integers(space.n))
        return rng.uniform(space.low, space.high).astype(space.dtype)

    def heuristic_policy(self, env: gym.Env) -> Policy:
        if self._fns["heuristic_fn"] is not None:
            return self._fns["heuristic_fn"]
        raise ConfigError(f"collector: env '{self.name}' has no heuristic policy (env.spec.heuristic_fn); "
                          "use collector=random")

    # ------------------------------------------------------------------ model <-> state
    def model_inputs(self, states: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(regressed states, controls) for a dynamics model from full states and raw actions."""
        states = np.asarray(states, dtype=float)
        controls = [states[:, self.exogenous_index], self.encode_actions(actions)]
        return states[:, self.target_index], np.concatenate(controls, axis=1)

    def at_bound(self, next_states: np.ndarray) -> np.ndarray:
        """Rows whose next state lies on a known bound (a non-smooth event no library fits)."""
        next_states = np.asarray(next_states, dtype=float)
        mask = np.zeros(len(next_states), dtype=bool)
        if self.state_low is not None:
            mask |= np.any(next_states <= np.asarray(self.state_low), axis=1)
        if self.state_high is not None:
            mask |= np.any(next_states >= np.asarray(self.state_high), axis=1)
        return mask

    def apply_bounds(self, states: np.ndarray, predicted_targets: np.ndarray) -> np.ndarray:
        """Predicted regressed states -> regressed states as the real env would bound them.

        Generic behaviour: clip each regressed variable to its box bounds, then round to the
        real env's observation dtype.
        """
        xp = functional.array_namespace(predicted_targets)  # numpy, or jax.numpy in a compiled step
        out = xp.asarray(predicted_targets, dtype=float)
        idx = self.target_index
        if self.state_low is not None or self.state_high is not None:
            low = -np.inf if self.state_low is None else np.asarray(self.state_low)[idx]
            high = np.inf if self.state_high is None else np.asarray(self.state_high)[idx]
            out = xp.clip(out, low, high)
        if len(self._circle_cols):  # back onto the unit circle (a pair at the origin stays)
            cols = [out[:, j] for j in range(out.shape[1])]
            for c, si in self._circle_cols:
                r = xp.hypot(cols[c], cols[si])
                r = xp.where(r > 0, r, 1.0)
                cols[c], cols[si] = cols[c] / r, cols[si] / r
            out = xp.stack(cols, axis=1)
        return self.round_obs(out)

    def target_bounds(self) -> dict[str, tuple[float, float]]:
        """{regressed state: (low, high)} of the regressed states the env bounds (one side may be
        infinite): a model that composes next values (primed terms) applies them in between."""
        low = self.state_low or (-np.inf,) * len(self.state_names)
        high = self.state_high or (np.inf,) * len(self.state_names)
        return {n: (float(low[i]), float(high[i])) for n, i in zip(self.target_names, self.target_index, strict=True)
                if np.isfinite(low[i]) or np.isfinite(high[i])}

    def round_obs(self, values: np.ndarray) -> np.ndarray:
        """Round to the real env's observation dtype (as float64 values)."""
        return functional.round_through(values, self.obs_dtype)

    def divergence_limit(self) -> np.ndarray:
        """Per regressed variable: a magnitude beyond which a predicted state counts as diverged."""
        if self.state_low is not None and self.state_high is not None:
            span = np.asarray(self.state_high) - np.asarray(self.state_low)
            limit = (np.maximum(np.abs(self.state_low), np.abs(self.state_high)) + 10 * span)[self.target_index]
            return np.where(np.isfinite(limit), limit, 1e3)  # 1e3 for unbounded variables
        return np.full(len(self.target_names), 1e3)

    # ------------------------------------------------------------------ the task (surrogate envs)
    @cached_property
    def task(self) -> Task | None:
        """The env's task for a surrogate (``envs.task.Task``: reward, termination, resets,
        exogenous states, events, pessimism, kernels), built once and checked then; None when the
        spec defines no reward (a surrogate then cannot be built: fits and real-env RL still can)."""
        return self.build_task()

    def build_task(self) -> Task | None:
        """The generic task from the dotted paths of the YAML (``reward_fn``, ``termination_fn``,
        ``initial_state_fn``, ``exogenous_fn``, ``termination_causes_fn``), ``events``,
        ``uncertainty`` and ``crash_reward``. A spec class with its own task overrides this."""
        fns = self._fns
        if fns["reward_fn"] is None:
            return None
        if self.exogenous_names and fns["exogenous_fn"] is None:
            raise ConfigError(f"env.spec.exogenous_fn: '{self.name}' does not say how to derive "
                              f"{list(self.exogenous_names)} in a surrogate")
        return Task(reward_terminated=self._reward_terminated, initial_states=self._checked_initial_states
                    if fns["initial_state_fn"] is not None else None,
                    exogenous=self._exogenous if fns["exogenous_fn"] is not None else None,
                    termination_causes=fns["termination_causes_fn"], crash_reward=self.crash_reward,
                    uncertainty=parse_uncertainty(self.uncertainty, None), events=self._events)

    def _reward_terminated(self, states, actions, next_states) -> tuple[np.ndarray, np.ndarray]:
        n = len(states)
        reward = np.asarray(self._fns["reward_fn"](states, actions, next_states), dtype=float).reshape(n)
        term_fn = self._fns["termination_fn"]
        terminated = (np.zeros(n, dtype=bool) if term_fn is None
                      else np.asarray(term_fn(states, actions, next_states), dtype=bool).reshape(n))
        return reward, terminated

    def _exogenous(self, states, actions, next_states) -> np.ndarray:
        out = np.asarray(self._fns["exogenous_fn"](states, actions, next_states), dtype=float)
        return out.reshape(len(states), len(self.exogenous_names))

    def _checked_initial_states(self, rng: np.random.Generator, n: int) -> np.ndarray:
        out = np.asarray(self._fns["initial_state_fn"](rng, n), dtype=float)
        if out.shape != (n, len(self.state_names)) or not np.all(np.isfinite(out)):
            raise ConfigError(f"env.spec.initial_state_fn: returned shape {out.shape} (or non-finite values) "
                              f"for n={n}; need finite ({n}, {len(self.state_names)}) states")
        return out

    def check_task(self, run_seed: int = 0) -> None:
        """Call the task's functions once on two real reset states (resets only: no env step)
        with random actions, and check what they return: a function that raises, takes the wrong
        arguments or returns the wrong shape is one line naming its key, before any real step."""
        task = self.task
        if task is None:
            return
        env = self.make_env()
        try:
            obs = [env.reset(seed=seeds.reset_seed(run_seed, "reset_pool", i))[0] for i in range(CHECK_RESETS)]
            env.action_space.seed(seeds.int_seed(run_seed, "reset_pool"))
            acts = np.array([np.atleast_1d(np.asarray(env.action_space.sample(), dtype=float)) for _ in range(2)])
        finally:
            env.close()
        s = np.asarray(self.coordinates(np.asarray(obs, dtype=float)), dtype=float)
        fns = self._fns
        n = len(s)

        def call(key: str, fn, shape, *args):
            try:
                out = np.asarray(fn(*args))
            except Exception as exc:  # a user's function may raise anything
                raise ConfigError(f"{key}: {functional.one_line(exc)} (called on two real reset states)") from None
            if shape is not None and out.shape != shape:
                raise ConfigError(f"{key}: returned shape {out.shape} for {n} states; expected {shape}")
            return out

        names = {"reward": "env.spec.reward_fn", "term": "env.spec.termination_fn", "exo": "env.spec.exogenous_fn"}
        if fns["reward_fn"] is not None:  # the YAML's functions, each under its own key
            call(names["reward"], fns["reward_fn"], (n,), s, acts, s)
            if fns["termination_fn"] is not None:
                call(names["term"], fns["termination_fn"], (n,), s, acts, s)
        else:
            r = call("env task: reward_terminated", task.reward_terminated, None, s, acts, s)
            if r.shape != (2, n):
                raise ConfigError(f"env task: reward_terminated returned shape {r.shape}; expected (reward, terminated) of {n}")
        if task.initial_states is not None:
            call("env.spec.initial_state_fn", task.initial_states, (n, len(self.state_names)), np.random.default_rng(0), n)
        if task.exogenous is not None:
            call(names["exo"], task.exogenous, (n, len(self.exogenous_names)), s, acts, s)
        for i, e in enumerate(task.events):
            key = f"env.spec.events[{i}]"
            call(f"{key}.trigger", e.trigger, (n,), s, acts, s)
            call(f"{key}.features", e.features, (n, len(e.feature_names)), s)
            if e.prior is not None:
                call(f"{key}.prior", e.prior, (n,), s)

    @property
    def defines_task(self) -> bool:
        """Whether a surrogate can be built for this env (it has a task)."""
        return self.task is not None

    def is_success(self, episode_return: float, terminated: bool) -> bool:
        """Whether a finished episode counts as a success. Default: its return reaches
        ``solved_threshold`` (specs whose task has a goal state override this)."""
        return self.solved_threshold is not None and episode_return >= self.solved_threshold

    def map_slices(self) -> tuple[tuple[str, tuple[float, float], str, tuple[float, float]], ...]:
        """The policy maps' slices: ``policy_map_slices``, else the first two regressed states
        over their bounds (+-1 where unbounded); one state alone gives no 2-D map."""
        if self.policy_map_slices:
            return self.policy_map_slices
        names = self.target_names[:2]
        if len(names) < 2:
            raise ConfigError(f"env.spec.policy_map_slices: '{self.name}' has fewer than two regressed states; name the slices")
        lows = self.state_low or (-np.inf,) * len(self.state_names)
        highs = self.state_high or (np.inf,) * len(self.state_names)
        ranges = []
        for n in names:  # unbounded: +-pi for an angle, else +-1
            wide = np.pi if n in self.angles else 1.0
            lo, hi = lows[self.state_names.index(n)], highs[self.state_names.index(n)]
            ranges.append((lo if np.isfinite(lo) else -wide, hi if np.isfinite(hi) else wide))
        return ((names[0], ranges[0], names[1], ranges[1]),)

    def discrete_action_labels(self) -> tuple[str, ...]:
        if self.action_labels or self.action_encoding == "one_hot":
            return self.action_labels or self.action_names
        if self.action_encoding == "values":
            return tuple(", ".join(f"{n}={v:g}" for n, v in zip(self.action_names, row, strict=True))
                         for row in self._action_table)
        return tuple(str(i) for i in range(self.n_discrete_actions))

    # ------------------------------------------------------------------ held-out test set
    def test_set_recipe(self) -> TestSetRecipe:
        """The fixed, named held-out test set every model of this env is scored on."""
        return TestSetRecipe(name=f"{self.name}-heldout-v1", seed=10_000, episodes=(("random", 1.0),) * 6)

    # ------------------------------------------------------------------ data and fidelity hooks (neutral defaults)
    def regimes(self, episode: np.ndarray, states: np.ndarray, rewards: np.ndarray,
                next_states: np.ndarray) -> dict[str, np.ndarray]:
        """Named row masks of transitions (N,) by physical regime (e.g. a lander's flight and
        contact), for fitting a model on the regime it describes and scoring per regime.
        Default: none (one regime: all rows)."""
        return {}

    def fit_rows(self, episode: np.ndarray, states: np.ndarray, rewards: np.ndarray,
                 next_states: np.ndarray) -> np.ndarray | None:
        """The rows a dynamics model is fitted on (a mask): those of ``fit_regime``; None: all."""
        if self.fit_regime is None:
            return None
        masks = self.regimes(episode, states, rewards, next_states)
        if self.fit_regime not in masks:
            raise ConfigError(f"env.spec.fit_regime: {self.fit_regime!r} is not one of {sorted(masks) or 'no regimes'}")
        return masks[self.fit_regime]

    def noise_floor(self, test_name: str) -> dict[str, Sequence[float]] | None:
        """{regime ("all" and those of ``regimes``): per regressed state, the replay noise floor
        (variance) of one-step prediction on the named test set}, or None when unknown
        (``fidelity.replay_noise_floor`` measures it)."""
        return None

    def learned_constants(self, data: Any) -> tuple[dict[str, Any], dict[str, float]]:
        """(field replacements, {prior key: learned value}) from a run's own transitions
        (``data``), for ``own_data``: the env's constants its data identify (LunarLander: the
        contact rules). A prior key is what a declared prior ``sets`` (``rules.floor``); a
        constant the data do not identify is left out (its prior keeps counting). Default: none."""
        return {}, {}

    def task_fidelity(self, test: Any) -> dict[str, float]:
        """Extra task-fidelity metrics of the surrogate's rules on real episodes (``test``: a
        ``data.Transitions`` of whole episodes); default: none."""
        return {}


def _rebuild_spec(cls: type, values: dict) -> EnvSpec:
    return cls(**values)


def _parse_slice(value: Any, i: int, state_names: tuple[str, ...]) -> tuple:
    key = f"env.spec.policy_map_slices[{i}]"
    try:
        xn, (x0, x1), yn, (y0, y1) = value
        out = (str(xn), (float(x0), float(x1)), str(yn), (float(y0), float(y1)))
    except (TypeError, ValueError):
        raise ConfigError(f"{key}: expected [x name, [low, high], y name, [low, high]], got {value!r}") from None
    for n in (out[0], out[2]):
        if n not in state_names:
            raise ConfigError(f"{key}: '{n}' is not a state name ({list(state_names)})")
    return out


_TASK_FNS = ("reward_fn", "termination_fn", "initial_state_fn", "heuristic_fn", "exogenous_fn", "termination_causes_fn")


wrap_angle = functional.wrap_angle
"""Angles wrapped to [-pi, pi) (numpy or jax arrays)."""


_ACTION_BOUNDS: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}


def action_bounds(spec: EnvSpec) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) of the real env's Box action space, cached per env and process."""
    key = (spec.gym_id, repr(sorted(spec.gym_kwargs.items())))
    if key not in _ACTION_BOUNDS:
        env = spec.make_env()
        try:
            space = env.action_space
        finally:
            env.close()
        if not isinstance(space, gym.spaces.Box):
            raise ConfigError(f"env.spec.action_encoding: clip needs a Box action space; {spec.gym_id} has {space}")
        _ACTION_BOUNDS[key] = (space.low.astype(float), space.high.astype(float))
    return _ACTION_BOUNDS[key]


def find_spec(name: str, config_dirs: Sequence[str] = ()) -> EnvSpec:
    """The spec of ``env/<name>.yaml`` in ``config_dirs``, ``$SDRL_BENCH_CONFIG_DIR`` or the
    package's configs (``envs.functional.spec_from_config``): envs are found by their config,
    never by importing an env's module here."""
    from_config = spec_from_config(name, config_dirs)
    if from_config is None:
        raise ConfigError(f"spec: unknown env {name!r}: no env/{name}.yaml in "
                          f"{[str(d) for d in functional.config_dirs(config_dirs)]} (config_dir= or "
                          f"${functional.CONFIG_DIR_VAR})")
    if not isinstance(from_config, EnvSpec):
        raise ConfigError(f"spec '{name}': its _target_ builds a {type(from_config).__name__}, not an EnvSpec")
    return from_config


class FoldResetSeed(gym.Wrapper):
    """Hands the real env each reset seed hashed to ``bits`` bits (``numpy.random.SeedSequence``
    of the seed), for envs that take no wider seed. Distinct seeds stay distinct with
    probability about 1 - n^2 / 2^(bits + 1) over n resets (32 bits, 10,000 resets: 99%)."""

    def __init__(self, env: gym.Env, bits: int):
        super().__init__(env)
        self.bits = int(bits)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            seed = int(np.random.SeedSequence(int(seed)).generate_state(1, np.uint64)[0] >> (64 - self.bits))
        return self.env.reset(seed=seed, options=options)


@dataclass(frozen=True)
class TestSetRecipe:
    """A deterministic recipe for a held-out test set.

    Episode ``i`` is played with policy ``episodes[i][0]`` ("heuristic" or "random") under
    eps-greedy exploration ``episodes[i][1]``, reset with seed ``seed + i`` (never a seed the
    training collectors use by default), for at most ``max_steps`` steps.
    """

    name: str
    seed: int
    episodes: tuple[tuple[str, float], ...]
    max_steps: int | None = None


CHECK_RESETS = 2
"""Real resets ``EnvSpec.check_task`` takes (no step)."""
POOL_RESETS = 200
"""Real resets behind a surrogate's default reset pool (``observed_initial_states``; no step)."""
_INITIAL_POOLS: dict[tuple, np.ndarray] = {}


def observed_initial_states(spec: EnvSpec, run_seed: int = 0, n: int = POOL_RESETS) -> np.ndarray:
    """Observations right after ``n`` resets of the real env (as states), reset seeds of the
    run's ``reset_pool`` stream (``seeds``: no other run or purpose uses them), cached per env,
    run seed and process. Resets only: no env step is taken."""
    key = (spec.gym_id, repr(sorted(spec.gym_kwargs.items())), int(run_seed), n)
    if key not in _INITIAL_POOLS:
        env = spec.make_env()
        try:
            pool = np.array([env.reset(seed=seeds.reset_seed(run_seed, "reset_pool", i))[0] for i in range(n)], dtype=float)
            pool = np.array(spec.coordinates(pool), dtype=float)  # states (a copy only with a map)
        finally:
            env.close()
        pool.setflags(write=False)
        _INITIAL_POOLS[key] = pool
    return _INITIAL_POOLS[key]
