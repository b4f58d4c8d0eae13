"""PPO compiled together with the surrogate's step (issue 31, third block): rollout and update in
one ``jax.jit`` of ``lax.scan`` loops, written after the PureJaxRL pattern.

``train(model_env, cfg, total_steps, seed) -> (params, stats)`` trains a Gaussian policy in the
surrogate ``model_env`` (a ``surrogate.model_env.ModelEnv``) without leaving XLA: each iteration
collects ``n_steps`` steps of ``n_envs`` copies (``surrogate.jax_step``: the ModelEnv's step as a
float64 jax function) and runs ``n_epochs`` epochs of minibatch updates on them; the iterations
are one ``lax.scan``. ``policy_fn(params)`` is the trained policy's deterministic action (its mean,
clipped to the action space) for numpy observations, to judge it in the real env;
``evaluate_surrogate`` plays deterministic episodes in the surrogate, compiled.

What it does as stable-baselines3's ``PPO`` with ``MlpPolicy`` does (so that the two compare):

* the policy: a diagonal Gaussian whose mean comes from a [64, 64] tanh MLP and whose log-std is
  one free parameter per action dimension (initialised to ``log_std_init``), or with gSDE
  (``use_sde``) one per (last hidden feature, action) and the noise mean + latent @ E, one
  exploration matrix E per env copy drawn at each rollout's start (SB3's ``full_std=True``,
  ``sde_sample_freq=-1``, features without gradient); the value from a separate [64, 64]
  tanh MLP; orthogonal weights (gain sqrt 2 in the hidden layers, 0.01 for the mean, 1 for the
  value), zero biases; float32, as SB3's torch networks (the surrogate steps in float64);
* rollouts: the sampled action is stored (and scored) unclipped; the env steps it clipped to the
  action space; an episode ends at termination, at ``spec.max_episode_steps`` or when the model
  diverges (``ModelEnv``'s guard, a truncation) and restarts at once from the task's reset
  distribution (``surrogate.jax_step.jax_reset``); a truncated episode's last reward gets
  gamma x V(final observation) added (SB3's timeout bootstrap, which the surrogate vector env
  triggers for the step limit and divergence alike);
* the update: GAE(lambda) over the rollout, ``n_epochs`` passes over a fresh permutation in
  minibatches of ``batch_size``, advantages normalised per minibatch (unbiased std + 1e-8), the
  clipped surrogate objective (``clip_range``), the value loss as plain MSE (no value clipping),
  the entropy bonus, the gradient's global norm clipped to ``max_grad_norm``, Adam (eps 1e-5, as
  SB3 sets it) at a constant ``learning_rate``.

* reward normalisation (``normalize_reward``, which the package's ``ppo_fast`` recipe turns on):
  SB3's ``VecNormalize(norm_obs=False, norm_reward=True)`` inside the loop (``RewardNorm``).

Not done here: observation normalisation (the package never uses it); learning-rate schedules,
``target_kl``, value clipping, ``sde_sample_freq`` > 0 and other ``policy_kwargs`` than
``log_std_init`` (refused by ``PPOConfig.from_agent`` when a recipe sets them). Random streams are
jax's, so a run is not the SB3 run with the same seed. ``rl.jax_agent.JaxPPO`` puts this PPO
behind SB3's interface (``agent=ppo_jax``), in the surrogate and, as the control, in real envs.

Hand-written, and why: the networks and the policy's distributions (``rl.jax_nets``) are a few
lines of jax.numpy over a plain pytree of (weight, bias) pairs (why not flax: there). optax
provides the optimiser (Adam, gradient-norm clipping); the PPO loop itself is what no installed
library offers over the harness's surrogate step (rejax and PureJaxRL expect their own env API).

Covered: the surrogates ``jax_step.jax_stepper`` covers (Pendulum, MountainCar, CartPole, the
swing-up, LunarLander on flat ground or terrain), with their step noise, pessimism, learned events and per-row
memory, the noise and event draws made from jax keys inside the compiled program (the same
distributions as ``ModelEnv``'s, other draws; a rollout makes all its steps' draws before its
loop, ``rollout_draws``). Box actions get the Gaussian above; discrete actions a categorical policy over the actor's logits
(SB3's ``CategoricalDistribution``). jax and optax are the optional ``jax`` extra (``pip install
'sdrl-bench[jax]'``), imported on first use.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any, NamedTuple

import numpy as np

from sdrl_bench import ConfigError
from sdrl_bench.rl.jax_nets import (HostPolicy, action_noise, deterministic_action, exploration_matrices,
                                     init_net, log_prob_entropy, modules, sample_action, value)
from sdrl_bench.surrogate.jax_step import jax_observe, jax_reset, jax_stepper, noise_of, reset_aux

ADAM_EPS = 1e-5
"""SB3's ``ActorCriticPolicy`` sets Adam's eps to 1e-5."""
COMPILER_OPTIONS = {"xla_backend_optimization_level": 2}
"""XLA options for the programs this module's training compiles (``make_train``, and
``rl.jax_agent.JaxPPO``'s init, rollout and update): LLVM at O2 instead of XLA's default O3. A
rollout is some 150 small kernels per step over 64-128 rows, and O3's larger code ran slower.
Measured on this 2-core host, one core, 2026-11-27 (``benchmarks/xla_opt_level.py``: each program
compiled at each level, interleaved medians): LunarLander's terrain rollout (64 x 128) 15.35 ->
13.02 ms, and its cold compile 7.7 -> 3.7 s (the code 2.2 -> 1.6 MB); MountainCar's rollout and
both updates unchanged (O3 / O2: 1.67 / 1.66, 10.69 / 10.65, 22.22 / 22.31 ms). O1 gave the same
times, O0 ran four times slower. Fast-math stays off, but LLVM may fuse a multiply and an add differently at
another level: those four programs' outputs were the same bit for bit, and a Pendulum rollout
of 8 rows differed in the last bit of some float32 values (tested to rounding)."""


MAX_ROLLOUT = 2**24
"""The most samples one update shuffles (``shuffles`` keeps at least 40 random bits per index)."""


@dataclass(frozen=True)
class PPOConfig:
    """PPO's hyperparameters, named as stable-baselines3 names them; defaults are SB3's PPO
    defaults (``n_envs``: the vector env's copies)."""

    n_envs: int = 1
    n_steps: int = 2048
    batch_size: int = 64
    n_epochs: int = 10
    gamma: float = 0.99
    gae_lambda: float = 0.95
    learning_rate: float = 3e-4
    ent_coef: float = 0.0
    vf_coef: float = 0.5
    clip_range: float = 0.2
    max_grad_norm: float = 0.5
    use_sde: bool = False
    """gSDE (generalized state-dependent exploration), as SB3's PPO does it with ``sde_sample_freq=-1``:
    one exploration matrix per env copy, drawn at each rollout's start (see ``sample_action``)."""
    log_std_init: float = 0.0
    """The initial log-std (SB3's ``policy_kwargs.log_std_init``)."""
    normalize_reward: bool = False
    """Rewards scaled by a running std of the discounted return, as SB3's ``VecNormalize(norm_obs=False,
    norm_reward=True)`` does it (``RewardNorm``)."""
    clip_reward: float = 10.0
    """VecNormalize's clip of the scaled reward."""

    def __post_init__(self) -> None:
        for k in ("n_envs", "n_steps", "batch_size", "n_epochs"):
            if int(getattr(self, k)) < 1:
                raise ConfigError(f"PPOConfig.{k} must be >= 1, got {getattr(self, k)}")
        if (self.n_envs * self.n_steps) % self.batch_size:
            raise ConfigError(f"PPOConfig: batch_size {self.batch_size} must divide n_envs x n_steps = "
                              f"{self.n_envs * self.n_steps} (compiled minibatches have one shape)")
        if self.n_envs * self.n_steps > MAX_ROLLOUT:
            raise ConfigError(f"PPOConfig: n_envs x n_steps = {self.n_envs * self.n_steps:,} is over the "
                              f"{MAX_ROLLOUT:,} samples one update can shuffle (shuffles)")

    @property
    def rollout_size(self) -> int:
        """Transitions per iteration (n_envs x n_steps)."""
        return self.n_envs * self.n_steps

    @classmethod
    def from_agent(cls, agent: Any) -> PPOConfig:
        """The config of a package recipe (``rl.agents.AgentConfig`` of SB3's PPO, e.g.
        ``agent=ppo_fast``): its ``n_envs`` and the algorithm's bound hyperparameters. Settings
        this PPO does not have are refused in one line; ``normalize_reward`` is not applied
        (see the module docstring)."""
        algo = agent.algo
        if getattr(getattr(algo, "func", None), "__name__", None) not in ("PPO", "JaxPPO"):
            raise ConfigError(f"PPOConfig.from_agent: agent '{agent.name}' is not PPO (SB3's or rl.jax_agent.JaxPPO)")
        return cls.from_kwargs(dict(getattr(algo, "keywords", {})), int(agent.n_envs), bool(agent.normalize_reward),
                               f"agent '{agent.name}'")

    @classmethod
    def from_kwargs(cls, kw: dict[str, Any], n_envs: int, normalize_reward: bool = False, who: str = "PPO") -> PPOConfig:
        """The config of SB3-style PPO keyword arguments (``n_steps``, ``use_sde``,
        ``policy_kwargs={"log_std_init": ...}``, ...); what this PPO does not have is refused in
        one line naming ``who``."""
        kw = dict(kw)
        # accepted, not PPO's math: SB3's plumbing, and where JaxPPO steps a surrogate (rl.jax_agent)
        ignored = {"policy": "MlpPolicy", "device": None, "verbose": None, "sde_sample_freq": -1, "compiled_rollout": None}
        policy_kwargs = dict(kw.pop("policy_kwargs", None) or {})
        names = {f.name for f in fields(cls)} - {"n_envs", "log_std_init", "normalize_reward", "clip_reward"}
        bad = [k for k, v in kw.items() if k not in names and not (k in ignored and ignored[k] in (None, v))]
        bad += [f"policy_kwargs.{k}" for k in policy_kwargs if k != "log_std_init"]
        if bad:
            raise ConfigError(f"PPOConfig: {who} sets {sorted(bad)}, which the compiled PPO does not have (it has "
                              f"{sorted(names | {'policy_kwargs.log_std_init', 'sde_sample_freq=-1'})})")
        for k in ("learning_rate", "clip_range"):
            if k in kw and not isinstance(kw[k], (int, float)):
                raise ConfigError(f"PPOConfig: {who}: {k} must be a constant (no schedules), got {kw[k]!r}")
        extra = {"log_std_init": float(policy_kwargs["log_std_init"])} if "log_std_init" in policy_kwargs else {}
        return cls(n_envs=int(n_envs), normalize_reward=normalize_reward, **extra, **{k: kw[k] for k in names if k in kw})


class RewardNorm(NamedTuple):
    """SB3's ``VecNormalize`` reward scaling, as a pytree: per copy the discounted return so far;
    its running mean, variance and count (``RunningMeanStd``, updated with each step's batch of
    returns, count starting at 1e-4). A reward is divided by sqrt(var + 1e-8) and clipped."""

    returns: Any
    mean: Any
    var: Any
    count: Any

    @staticmethod
    def init(n: int) -> RewardNorm:
        import jax.numpy as jnp  # noqa: PLC0415

        return RewardNorm(jnp.zeros(n, jnp.float64), jnp.float64(0.0), jnp.float64(1.0), jnp.float64(1e-4))

    def step(self, reward: Any, done: Any, gamma: float, clip: float) -> tuple[RewardNorm, Any]:
        """(the state after this step's rewards, the scaled float32 rewards): the statistics
        are updated first, then the reward scaled, then finished episodes' returns reset, in
        VecNormalize's order."""
        import jax.numpy as jnp  # noqa: PLC0415

        returns = self.returns * gamma + reward
        b_mean, b_var, b_count = jnp.mean(returns), jnp.var(returns), returns.shape[0]
        delta = b_mean - self.mean
        tot = self.count + b_count
        mean = self.mean + delta * b_count / tot
        var = (self.var * self.count + b_var * b_count + delta**2 * self.count * b_count / tot) / tot
        scaled = jnp.clip(reward / jnp.sqrt(var + 1e-8), -clip, clip).astype(jnp.float32)
        return RewardNorm(jnp.where(done, 0.0, returns), mean, var, tot), scaled


# ---------------------------------------------------------------------- the surrogate, compiled
class EnvState(NamedTuple):
    """The vector env's state inside the loop."""

    states: Any
    """(n_envs, n_state) float64 surrogate states."""
    t: Any
    """(n_envs,) int32 steps into each episode."""
    ep_return: Any
    """(n_envs,) float64 return of each episode so far (the task's rewards)."""
    norm: Any = None
    """``RewardNorm`` when the config normalizes rewards, else None."""
    aux: Any = None
    """(n_envs,) the task's per-row memory (``surrogate.jax_step.JaxStepper``; None: fresh)."""


class Transition(NamedTuple):
    """One step of the rollout, (n_steps, n_envs, ...) once scanned. The first six are what the
    update reads; the rest record the env's step (for tests and statistics)."""

    obs: Any
    action: Any
    """The sampled action, unclipped (float32), as SB3 stores it."""
    log_prob: Any
    value: Any
    reward: Any
    """The learner's reward (float32): the task's (scaled, ``cfg.normalize_reward``), plus gamma x
    V(final observation) on a truncation."""
    done: Any
    state: Any
    """The state stepped from (float64)."""
    env_action: Any
    """The action stepped (clipped to the action space, float64)."""
    next_state: Any
    """The step's next state, before any reset."""
    task_reward: Any
    terminated: Any
    diverged: Any
    t: Any
    """Steps into the episode after this step."""
    episode_return: Any
    """The return of the episode this step ended (0 where none ended)."""


class Surrogate(NamedTuple):
    """The surrogate's pieces as jax functions, with its sizes and bounds."""

    step: Callable
    """``step(states, actions, aux, key, params) -> (next states, rewards, terminated, diverged,
    aux)``: ``jax_stepper``'s step with its step noise and learned-event draws drawn from ``key``
    and the model's numbers ``params`` (``JaxStepper.params``)."""
    observe: Callable
    reset: Callable
    """``reset(key, n, params=None)``: n fresh states (from ``params["pool"]`` when given, else the
    surrogate's own reset pool or draw)."""
    n_obs: int
    n_act: int
    """Action dimensions (Box) or the number of discrete actions."""
    action_low: np.ndarray | None
    action_high: np.ndarray | None
    """The Box's bounds (None for discrete actions)."""
    max_steps: int
    discrete: bool = False
    init_aux: Callable | None = None
    """``init_aux(n, key=None)``: the task's memory of n fresh episodes (drawn from ``key`` where
    it is random: ``aux_key``)."""
    params: Any = None
    """The ModelEnv's model as numbers (``JaxStepper.params``): an argument of the compiled rollout."""
    key: tuple = ()
    """``JaxStepper.key``: surrogates of equal keys (and spec) share a compiled rollout."""
    draw: Callable | None = None
    """``draw(key, n)``: the random inputs ``step`` draws from ``key`` for n rows, drawn apart."""
    step_drawn: Callable | None = None
    """``step_drawn(states, actions, aux, drawn, params)``: ``step`` on ``draw``'s inputs, so
    ``step(s, a, aux, key, p) == step_drawn(s, a, aux, draw(key, len(s)), p)``."""


def surrogate(model_env: Any) -> Surrogate:
    """``model_env`` as the compiled loop steps it: ``surrogate.jax_step.jax_stepper``'s step,
    with the ModelEnv's step noise (``step_noise`` of standard-normal draws: the same
    distribution as ModelEnv's, not its draws), one uniform per row and learned event, and a
    probabilistic ensemble's own draws (its elite and its Gaussian's normals) drawn from the
    step's key; refuses (in one line) what ``jax_stepper`` does not cover."""
    jax, jnp, _ = modules()
    spec = model_env.spec
    stepper = jax_stepper(model_env)
    noisy = stepper.params["chol"] is not None
    m, k = len(spec.target_names), stepper.n_event_draws

    def draw(key, n):
        """The step's random inputs for ``n`` rows, drawn from ``key``: (standard normals for the
        step noise, uniforms for the learned events, a probabilistic ensemble's draws), None
        where the model has none."""
        k_noise, k_event = jax.random.split(key)
        normals = jax.random.normal(k_noise, (n, m), jnp.float64) if noisy else None
        event_u = jax.random.uniform(k_event, (n, k), jnp.float64) if k else None
        draws = None
        if stepper.sampling:  # folded in, not split off: the other models' streams stay what they were
            k_pick, k_eps = jax.random.split(jax.random.fold_in(key, 2))
            draws = (jax.random.uniform(k_pick, (n,), jnp.float64), jax.random.normal(k_eps, (n, m), jnp.float64))
        return normals, event_u, draws

    def step_drawn(states, actions, aux, drawn, params):
        normals, event_u, draws = drawn
        noise = noise_of(params["chol"], actions, normals) if noisy else None
        return stepper.step(states, actions, aux, noise, event_u, params, draws)

    def step(states, actions, aux, key, params):
        return step_drawn(states, actions, aux, draw(key, states.shape[0]), params)

    # the reset pool (a seed's real first observations) is a number of the model like its
    # coefficients: an argument, so that one compiled rollout serves every seed's surrogate
    pool = None if model_env._pool is None else np.asarray(model_env._pool, dtype=np.float64)
    params = {**stepper.params, "pool": pool}
    key = (stepper.key, None if pool is None else pool.shape)
    draw_reset = jax_reset(model_env)

    def reset(key, n, params=None):
        return draw_reset(key, n, None if params is None else params["pool"])

    space = model_env.action_space
    pieces = (step, jax_observe(model_env), reset, len(spec.obs_names))
    if spec.n_discrete_actions:
        return Surrogate(*pieces, int(spec.n_discrete_actions), None, None, int(spec.max_episode_steps), True,
                         stepper.init_aux, params, key, draw, step_drawn)
    return Surrogate(*pieces, spec.raw_action_width, np.asarray(space.low, np.float32),
                     np.asarray(space.high, np.float32), int(spec.max_episode_steps), False, stepper.init_aux,
                     params, key, draw, step_drawn)


def aux_key(key: Any) -> Any:
    """The key a fresh episode's task memory is drawn from (a terrain), derived from the key its
    states are drawn from. Folded in rather than split off, so that the states' keys, and every
    run of a task whose memory is not drawn, stay what they were (and the unused fold compiles
    away)."""
    jax, _, _ = modules()
    return jax.random.fold_in(key, 1)


def init_env(sur: Surrogate, key: Any, n_envs: int, cfg: PPOConfig | None = None,
             params: Any = None) -> tuple[EnvState, Any]:
    """Fresh episodes in every copy: (env state, float32 observations); ``params``: the surrogate
    model's numbers (``sur.params``), whose reset pool it draws from (None: the surrogate's own).
    Called eagerly it runs op by op, each op a program of its own (LunarLander's terrain: about
    0.2 s of lowering and cache reads in a fresh process, measured); ``rl.jax_agent`` jits it."""
    _, jnp, _ = modules()
    states = sur.reset(key, n_envs, params)
    norm = RewardNorm.init(n_envs) if cfg is not None and cfg.normalize_reward else None
    env = EnvState(states, jnp.zeros(n_envs, jnp.int32), jnp.zeros(n_envs, jnp.float64), norm,
                   sur.init_aux(n_envs, aux_key(key)))
    return env, sur.observe(states).astype(jnp.float32)


def rollout_draws(sur: Surrogate, cfg: PPOConfig, net: dict, explore: Any, params: Any, key: Any) -> tuple:
    """Every step's random inputs for a rollout, ``cfg.n_steps`` along the first axis: (its
    actions' noise (``action_noise``; None with gSDE's ``explore``), its fresh episodes' states,
    their float32 observations and task memory, the model's draws (``Surrogate.draw``)). Step i
    splits the i-th of ``cfg.n_steps`` keys from ``key`` three ways (action, reset, model), as a
    step drawing on its own would. Why before the loop, in batched calls: a threefry call on the
    CPU is a loop of its own (XLA's rolled rounds), five of them a step in LunarLander's
    rollout; drawn once for all steps their cost is shared: a rollout of LunarLander's terrain
    pack took 23.1 ms with the draws in the loop, 19.2 ms with them here (median of 30, one
    core, this 2-core machine); MountainCar's fast pack, 2.51 against 2.26 ms. The costs: every
    step's fresh episodes are held at once, arrays of the trajectory's own shape (n_steps,
    n_envs, ...), where a step drew and dropped its own; and the program lowers more slowly
    (LunarLander's terrain rollout 0.13 -> 0.17 s, every compile, cached or not), which a short
    run's fewer rollouts do not win back (docs/compiled.md)."""
    jax, jnp, _ = modules()
    n = cfg.n_envs
    keys = jax.vmap(lambda k: jax.random.split(k, 3))(jax.random.split(key, cfg.n_steps))
    k_act, k_reset, k_step = keys[:, 0], keys[:, 1], keys[:, 2]
    act_noise = None if explore is not None else jax.vmap(lambda k: action_noise(net, k, n))(k_act)
    fresh = jax.vmap(lambda k: sur.reset(k, n, params))(k_reset)
    fresh_aux = jax.vmap(lambda k: sur.init_aux(n, aux_key(k)))(k_reset)
    return (act_noise, fresh, jax.vmap(sur.observe)(fresh).astype(jnp.float32), fresh_aux,
            jax.vmap(lambda k: sur.draw(k, n))(k_step))


def make_rollout(sur: Surrogate, cfg: PPOConfig) -> Callable:
    """``rollout(net, env, obs, key, params=None) -> (env, obs, transitions, last value)``:
    ``cfg.n_steps`` steps of the ``cfg.n_envs`` copies (pure; jit it, or call it inside a compiled
    loop). ``params``: the surrogate model's numbers (default ``sur.params``); compiled with them
    as an argument, the rollout steps any surrogate of the same ``key`` without compiling again."""
    jax, jnp, _ = modules()
    low, high = (None, None) if sur.discrete else (jnp.asarray(sur.action_low), jnp.asarray(sur.action_high))
    n, gamma = cfg.n_envs, cfg.gamma

    def one_step(net, explore, params, carry, x):
        env, obs = carry
        act_noise, fresh, fresh_obs, fresh_aux, drawn = x
        action, logp, _ = sample_action(net, obs, None, explore, act_noise)
        v = value(net, obs)
        env_action = action[:, None] if sur.discrete else jnp.clip(action, low, high).astype(jnp.float64)
        nxt, reward, terminated, diverged, aux = sur.step_drawn(env.states, env_action, env.aux, drawn, params)
        t = env.t + 1
        truncated = (t >= sur.max_steps) | diverged
        done = terminated | truncated
        final_obs = sur.observe(nxt).astype(jnp.float32)
        timeout = truncated & ~terminated
        boot = jax.lax.cond(jnp.any(timeout), lambda: value(net, final_obs), lambda: jnp.zeros(n, jnp.float32))
        norm, scaled = (None, reward.astype(jnp.float32)) if env.norm is None else \
            env.norm.step(reward, done, gamma, cfg.clip_reward)
        learn_reward = scaled + gamma * jnp.where(timeout, boot, 0.0)
        ep_return = env.ep_return + reward
        states = jnp.where(done[:, None], fresh, nxt)
        new_obs = jnp.where(done[:, None], fresh_obs, final_obs)
        new_env = EnvState(states, jnp.where(done, 0, t), jnp.where(done, 0.0, ep_return), norm,
                           reset_aux(done, fresh_aux, aux))
        tr = Transition(obs, action, logp, v, learn_reward, done, env.states, env_action, nxt, reward, terminated,
                        diverged, t, jnp.where(done, ep_return, 0.0))
        return (new_env, new_obs), tr

    def rollout(net, env, obs, key, params=None):
        params = sur.params if params is None else params
        if env.aux is None:  # a state built without the task's memory: fresh episodes
            env = env._replace(aux=sur.init_aux(n, aux_key(key)))
        k_explore, k_steps = jax.random.split(key)
        explore = exploration_matrices(net, k_explore, n)  # gSDE: drawn once per rollout (sde_sample_freq=-1)
        (env, obs), traj = jax.lax.scan(lambda c, x: one_step(net, explore, params, c, x), (env, obs),
                                        rollout_draws(sur, cfg, net, explore, params, k_steps))
        return env, obs, traj, value(net, obs)

    return rollout


def gae(cfg: PPOConfig, values: Any, rewards: Any, dones: Any, last_value: Any) -> tuple[Any, Any]:
    """(advantages, returns), (n_steps, n_envs): GAE(lambda) as SB3's rollout buffer computes it
    (a step's successor counts unless the step ended its episode)."""
    jax, jnp, _ = modules()

    def back(carry, x):
        adv, next_value = carry
        v, r, d = x
        live = 1.0 - d.astype(jnp.float32)
        delta = r + cfg.gamma * next_value * live - v
        adv = delta + cfg.gamma * cfg.gae_lambda * live * adv
        return (adv, v), adv

    _, adv = jax.lax.scan(back, (jnp.zeros_like(last_value), last_value), (values, rewards, dones), reverse=True)
    return adv, adv + values


def optimizer(cfg: PPOConfig) -> Any:
    """The gradient's global norm clipped, then Adam (eps 1e-5), as SB3's PPO steps; on the
    parameters flattened into one vector (``optax.flatten``: the same elementwise Adam in a few
    large ops instead of a few per array; measured 12.5 -> 11.6 ms per fast-pack update)."""
    _, _, optax = modules()
    return optax.flatten(optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm),
                                     optax.adam(cfg.learning_rate, eps=ADAM_EPS)))


def shuffles(key: Any, n_epochs: int, n: int) -> Any:
    """(n_epochs, n) int32: an independent random permutation of range(n) per epoch, as SB3 draws
    one per epoch. Written by hand because ``jax.random.permutation`` sorts (key, index) pairs in
    rounds, and XLA's CPU sort of a pair is slow: 1.2 ms per permutation of 4,096 samples, against
    12 ms for the whole fast-pack update it served (measured, this 2-core machine). Here each
    index goes into the low bits of a random uint64, and all epochs are sorted at once in one
    plain integer sort (0.53 ms for four). The order is that of the random high bits (64 - b of
    them, b = the bits of n - 1): a uniform permutation unless two draws share all of them
    (chance under n^2 / 2^(65 - b), 1.6e-8 at n = 8,192), where the lower index goes first."""
    jax, jnp, _ = modules()
    if not 1 <= n <= MAX_ROLLOUT:
        raise ValueError(f"shuffles: n must be in [1, {MAX_ROLLOUT:,}], got {n:,}")
    b = max(1, (n - 1).bit_length())
    packed = jax.random.bits(key, (n_epochs, n), jnp.uint64) >> b << b | jnp.arange(n, dtype=jnp.uint64)
    return (jnp.sort(packed, axis=1) & ((1 << b) - 1)).astype(jnp.int32)


def make_update(cfg: PPOConfig, shuffled_outside: bool = False) -> Callable:
    """``update(net, opt_state, batch, key) -> (net, opt_state, stats)``: ``cfg.n_epochs`` passes
    over ``batch`` (obs, action, log_prob, advantage, return; first axis the samples) in shuffled
    minibatches of ``cfg.batch_size``, one Adam step each, each epoch's permutation drawn from
    ``key`` (``shuffles``). ``shuffled_outside``: ``update(net, opt_state, batch, perms)`` takes
    the epochs' permutations as an input instead, (n_epochs, n) int32, one permutation of range(n)
    a row (``rl.jax_agent`` draws them on the host, where numpy shuffles 4 x 4,096 indices in
    0.15 ms against the 0.53 ms of ``shuffles``' sort; measured on this 2-core machine)."""
    jax, jnp, optax = modules()
    tx = optimizer(cfg)
    c = cfg.clip_range

    def loss_fn(net, b):
        obs, act, old_logp, adv, ret = b
        logp, ent_rows = log_prob_entropy(net, obs, act)
        adv = (adv - adv.mean()) / (jnp.std(adv, ddof=1) + 1e-8)
        log_ratio = logp - old_logp
        ratio = jnp.exp(log_ratio)
        pg_loss = -jnp.mean(jnp.minimum(adv * ratio, adv * jnp.clip(ratio, 1.0 - c, 1.0 + c)))
        value_loss = jnp.mean((ret - value(net, obs)) ** 2)
        ent = jnp.mean(ent_rows)
        loss = pg_loss - cfg.ent_coef * ent + cfg.vf_coef * value_loss
        return loss, {"pg_loss": pg_loss, "value_loss": value_loss, "entropy": ent,
                      "approx_kl": jnp.mean((ratio - 1.0) - log_ratio), "clip_fraction": jnp.mean(jnp.abs(ratio - 1.0) > c)}

    grad_fn = jax.value_and_grad(loss_fn, has_aux=True)

    def minibatch(carry, b):
        net, opt = carry
        (_, aux), grads = grad_fn(net, b)
        updates, opt = tx.update(grads, opt, net)
        return (optax.apply_updates(net, updates), opt), aux

    def epoch(carry, perm, batch):
        n = batch[0].shape[0]
        mbs = jax.tree_util.tree_map(lambda x: x[perm].reshape(n // cfg.batch_size, cfg.batch_size, *x.shape[1:]), batch)
        return jax.lax.scan(minibatch, carry, mbs)

    def update_on(net, opt_state, batch, perms):
        (net, opt_state), aux = jax.lax.scan(lambda c_, p: epoch(c_, p, batch), (net, opt_state), perms)
        return net, opt_state, jax.tree_util.tree_map(jnp.mean, aux)

    def update(net, opt_state, batch, key):
        return update_on(net, opt_state, batch, shuffles(key, cfg.n_epochs, batch[0].shape[0]))

    return update_on if shuffled_outside else update


def make_batch(cfg: PPOConfig, traj: Transition, last_value: Any) -> tuple:
    """The update's batch from a rollout: (obs, action, log_prob, advantage, return), flattened."""
    adv, ret = gae(cfg, traj.value, traj.reward, traj.done, last_value)
    flat = lambda x: x.reshape(-1, *x.shape[2:])  # noqa: E731
    return tuple(flat(x) for x in (traj.obs, traj.action, traj.log_prob, adv, ret))


def n_iterations(cfg: PPOConfig, total_steps: int) -> int:
    """Iterations (rollout + update) to reach ``total_steps`` env steps: SB3's ``learn`` also
    collects whole rollouts until it has at least that many."""
    return max(1, math.ceil(int(total_steps) / cfg.rollout_size))


def make_train(model_env: Any, cfg: PPOConfig, total_steps: int) -> Callable:
    """``train_fn(key) -> (net, stats)``, jitted: initialise, then ``n_iterations`` of rollout and
    update in one ``lax.scan``. Calling it again with another key reuses the compiled program
    (what ``benchmarks/compiled_ppo.py`` times as the second call). ``stats``: per iteration,
    the rollout's episodes ended, their summed return, diverged steps, mean task reward, and the
    update's mean losses, entropy, approximate KL and clip fraction."""
    jax, jnp, _ = modules()
    sur = surrogate(model_env)
    rollout, update, tx = make_rollout(sur, cfg), make_update(cfg), optimizer(cfg)
    iters = n_iterations(cfg, total_steps)

    def iteration(carry, key):
        net, opt, env, obs = carry
        k_roll, k_upd = jax.random.split(key)
        env, obs, traj, last_value = rollout(net, env, obs, k_roll)
        net, opt, stats = update(net, opt, make_batch(cfg, traj, last_value), k_upd)
        stats.update(episodes=jnp.sum(traj.done), episode_return_sum=jnp.sum(traj.episode_return),
                     diverged=jnp.sum(traj.diverged), reward_mean=jnp.mean(traj.task_reward))
        return (net, opt, env, obs), stats

    def train_fn(key):
        k_net, k_env, k_loop = jax.random.split(key, 3)
        net = init_net(k_net, sur.n_obs, sur.n_act, cfg, sur.discrete)
        env, obs = init_env(sur, k_env, cfg.n_envs, cfg)
        (net, _, _, _), stats = jax.lax.scan(iteration, (net, tx.init(net), env, obs), jax.random.split(k_loop, iters))
        return net, stats

    return jax.jit(train_fn, compiler_options=COMPILER_OPTIONS)


def as_params(net: Any, model_env: Any) -> dict[str, Any]:
    """``train``'s params: the trained networks (``net``) and the action space's bounds (None
    for discrete actions)."""
    space = model_env.action_space
    if not hasattr(space, "low"):
        return {"net": net, "action_low": None, "action_high": None}
    return {"net": net, "action_low": np.asarray(space.low, np.float32), "action_high": np.asarray(space.high, np.float32)}


def train(model_env: Any, cfg: PPOConfig, total_steps: int, seed: int = 0) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Train in the surrogate for at least ``total_steps`` env steps (whole iterations of
    ``cfg.rollout_size``). Returns (params, stats): params for ``policy_fn`` /
    ``evaluate_surrogate``; stats as numpy arrays per iteration (``make_train``), plus ``steps``
    (env steps after each iteration) and ``episode_return_mean`` (NaN where no episode ended)."""
    jax, _, _ = modules()
    net, stats = make_train(model_env, cfg, total_steps)(jax.random.key(int(seed)))
    out = {k: np.asarray(v) for k, v in stats.items()}
    out["steps"] = cfg.rollout_size * np.arange(1, len(out["episodes"]) + 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        out["episode_return_mean"] = np.where(out["episodes"] > 0, out["episode_return_sum"] / out["episodes"], np.nan)
    return as_params(net, model_env), out


class JaxPolicy:
    """The trained policy's deterministic action: the Gaussian's mean, clipped to the action
    space, or the most probable discrete action. ``policy(obs)`` for one observation (n_obs,) or
    a batch (N, n_obs) (numpy in, numpy out); ``predict(obs, deterministic=True)`` as SB3's, so
    ``rl.agents.evaluate_real`` plays it in the real env. Computed on the host (``HostPolicy``)."""

    def __init__(self, params: dict[str, Any]):
        self.params = params
        self._act = HostPolicy(params["net"], params["action_low"], params["action_high"])

    def __call__(self, obs: Any) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float32)
        single = obs.ndim == 1
        out = self._act(obs[None] if single else obs)
        return out[0] if single else out

    def predict(self, obs: Any, state: Any = None, episode_start: Any = None, deterministic: bool = True):
        if not deterministic:
            raise NotImplementedError("JaxPolicy.predict: only the deterministic (mean) action")
        return self(obs), None


def policy_fn(params: dict[str, Any]) -> JaxPolicy:
    """``params`` (from ``train``) as a callable ``obs (numpy) -> action (numpy)``: the mean action,
    clipped to the action space (see ``JaxPolicy``)."""
    return JaxPolicy(params)


def surrogate_evaluator(model_env: Any, n_episodes: int, low: Any = None, high: Any = None) -> Callable:
    """``run(net, key) -> returns (n_episodes,)``, jitted once: ``n_episodes`` deterministic episodes
    (the mean action clipped to [low, high], or the most probable index) in the surrogate, side by
    side, each from a reset drawn with ``key``, up to ``spec.max_episode_steps`` steps or its end
    (termination, divergence). Built once and called with each new ``net``, it compiles once (a
    study that evaluates after every rollout)."""
    jax, jnp, _ = modules()
    sur = surrogate(model_env)

    def run(net, key):
        def body(carry, k):
            states, aux, ret, live = carry
            a = deterministic_action(net, sur.observe(states).astype(jnp.float32), low, high)
            a = a[:, None] if sur.discrete else a.astype(jnp.float64)
            nxt, r, term, div, aux = sur.step(states, a, aux, k, sur.params)
            return (nxt, aux, ret + jnp.where(live, r, 0.0), live & ~term & ~div), None

        k_reset, k_steps = jax.random.split(key)
        init = (sur.reset(k_reset, n_episodes), sur.init_aux(n_episodes, aux_key(k_reset)), jnp.zeros(n_episodes),
                jnp.ones(n_episodes, bool))
        (_, _, ret, _), _ = jax.lax.scan(body, init, jax.random.split(k_steps, sur.max_steps))
        return ret

    return jax.jit(run)


def evaluate_surrogate(model_env: Any, params: dict[str, Any], n_episodes: int, seed: int = 0) -> np.ndarray:
    """Returns of ``n_episodes`` deterministic episodes (the mean action, clipped) in the surrogate,
    side by side, compiled: each from a reset drawn with jax key ``seed`` (``surrogate_evaluator``)."""
    jax, _, _ = modules()
    run = surrogate_evaluator(model_env, n_episodes, params["action_low"], params["action_high"])
    return np.asarray(run(params["net"], jax.random.key(int(seed))))
