"""SAC's update compiled by jax (issue 31, "and SAC if it fits"): ``gradient_steps`` gradient steps
in one ``jax.jit`` of a ``lax.scan``; ``rl.jax_sac_agent.JaxSAC`` puts it behind stable-baselines3's
interface (``agent=sac_jax``).

Why only the update: SAC takes one gradient step per env step (the package's recipe: 32 steps
collected, then 32 gradient steps on batches of 512), so its training is bound by the update, not
by the env. Measured on this 2-core machine, one core, the quick pack's sizes: SB3's
``SAC.train`` 7.8-8.7 ms per gradient step, this update 1.4-1.5 ms; collecting a step in Python
(this module's ``HostActor`` and the vector env) costs some 0.05 ms. A rollout compiled with the
surrogate's step, as the compiled PPO has it, would save a few percent here, and the same
collection serves the surrogate and the real env (the control) alike, a Dyna refit included.

What it does as SB3's ``SAC`` with ``MlpPolicy`` does (so that the two compare; tested against
SB3's own ``train`` from the same weights, batch and noise: ``tests/rl/test_jax_sac.py``):

* the actor: a ReLU MLP (``net_arch``) whose last features give the mean (a linear layer) and,
  without gSDE, the log-std (another linear layer, clipped to [-20, 2]); the action is
  tanh(mean + noise), its log-probability the Gaussian's minus sum log(1 - a^2 + 1e-6);
* gSDE (``use_sde``, SB3's ``StateDependentNoiseDistribution`` with ``full_std=True``,
  ``learn_features=True``, ``squash_output=True``): the mean clipped to +-``clip_mean``; a
  log-std per (feature, action), initialised to ``log_std_init``; noise = features @ E with E ~
  N(0, exp(log_std)^2) drawn at every gradient step (shared by the step's two samples) and at
  every collection (one per env copy); the Gaussian's std sqrt(features^2 @ exp(log_std)^2 + 1e-6)
  with the features' gradient kept; the log-probability of the squashed action taken from its
  inverse (atanh of the action clipped to +-(1 - float32 eps)), as SB3 takes it;
* ``n_critics`` Q MLPs on (observation, action), ReLU, and their targets, Polyak-averaged with
  ``tau`` at every ``target_update_interval``-th gradient step of a train call;
* one gradient step: the entropy coefficient's (``ent_coef="auto"``: log-alpha learned towards
  ``target_entropy``, -dim(A) by default), then the critics' on
  r + (1 - done) gamma (min target Q(s', a') - alpha log pi(a'|s')) with 0.5 x the sum of their
  MSEs, then the actor's on alpha log pi - min Q(s, a) with the just-updated critics; Adam (eps
  1e-8, as torch's) at a constant ``learning_rate`` for all three; no gradient clipping;
* float32 networks initialised as torch's ``nn.Linear`` (weights and biases uniform in
  +-1/sqrt(fan_in)), the targets copies of the critics.

The collection (``rl.jax_sac_agent.JaxSAC``) is SB3's ``collect_rollouts``: ``train_freq`` vector steps,
uniform random actions before ``learning_starts`` (unless ``use_sde_at_warmup``), transitions in a
replay buffer of ``buffer_size // n_envs`` rows per copy whose done flag drops timeouts
(``TimeLimit.truncated``: SB3's ``handle_timeout_termination``), ``gradient_steps`` gradient steps
after each collection once more than ``learning_starts`` steps are taken.

Hand-written, and why: sbx (SB3's jax port) has a SAC, but its gSDE is a held noise key (the same
Gaussian noise for every state until the next reset), not state-dependent; it ignores
``log_std_init`` and ``clip_mean``, so the package's MountainCar recipe (gSDE at log-std -3.67)
would not be the recipe; and it needs ``tfp-nightly``. The networks are plain (weight, bias)
pytrees run features-major with ``jax_nets.dense_layer`` (the product shapes XLA's fast CPU kernels
take); optax provides Adam.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any, NamedTuple

import numpy as np

from sdrl_bench import ConfigError
from sdrl_bench.rl import jax_nets

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0
"""SB3's clip of the actor's log-std head (no gSDE)."""
SQUASH_EPS = 1e-6
"""SB3's epsilon in log(1 - tanh(u)^2 + eps) and in gSDE's variance."""
ADAM_EPS = 1e-8
"""torch's Adam default, which SB3's SAC keeps."""
F32_EPS = float(np.finfo(np.float32).eps)
"""SB3's ``TanhBijector.inverse`` clips the action to +-(1 - this) before atanh."""


@dataclass(frozen=True)
class SACConfig:
    """SAC's hyperparameters, named as stable-baselines3 names them; defaults are SB3's SAC
    defaults (``n_envs``: the vector env's copies)."""

    n_envs: int = 1
    learning_rate: float = 3e-4
    buffer_size: int = 1_000_000
    learning_starts: int = 100
    batch_size: int = 256
    tau: float = 0.005
    gamma: float = 0.99
    train_freq: int = 1
    gradient_steps: int = 1
    ent_coef: float | str = "auto"
    target_update_interval: int = 1
    target_entropy: float | str = "auto"
    use_sde: bool = False
    use_sde_at_warmup: bool = False
    net_arch: tuple[int, ...] = (256, 256)
    """The actor's hidden layers (``policy_kwargs.net_arch``: a list, or a dict with ``pi``)."""
    qf_arch: tuple[int, ...] = (256, 256)
    """The critics' (the list again, or the dict's ``qf``)."""
    log_std_init: float = -3.0
    clip_mean: float = 2.0
    n_critics: int = 2

    def __post_init__(self) -> None:
        for k in ("n_envs", "buffer_size", "batch_size", "train_freq", "target_update_interval", "n_critics"):
            if int(getattr(self, k)) < 1:
                raise ConfigError(f"SACConfig.{k} must be >= 1, got {getattr(self, k)}")
        for k in ("learning_starts", "gradient_steps"):
            if int(getattr(self, k)) < 0:
                raise ConfigError(f"SACConfig.{k} must be >= 0 (gradient_steps=-1, as many as collected, is not "
                                  f"supported), got {getattr(self, k)}")
        if not self.net_arch or not self.qf_arch:
            raise ConfigError("SACConfig: net_arch needs at least one hidden layer")
        auto = isinstance(self.ent_coef, str)
        if auto and not (self.ent_coef == "auto" or self.ent_coef.startswith("auto_")):
            raise ConfigError(f"SACConfig.ent_coef: a number, 'auto' or 'auto_<init>', got {self.ent_coef!r}")
        if auto:
            try:
                init = self.alpha_init()
            except ValueError:
                raise ConfigError(f"SACConfig.ent_coef: 'auto_<init>' needs a number after 'auto_', "
                                  f"got {self.ent_coef!r}") from None
            if not init > 0:
                raise ConfigError(f"SACConfig.ent_coef: a learned coefficient starts above 0, got {self.ent_coef!r}")
        else:
            try:
                fixed = float(self.ent_coef)
            except (TypeError, ValueError):
                fixed = float("nan")
            if not fixed >= 0:
                raise ConfigError(f"SACConfig.ent_coef: a fixed coefficient is a number >= 0, got {self.ent_coef!r}")
        if isinstance(self.target_entropy, str) and self.target_entropy != "auto":
            raise ConfigError(f"SACConfig.target_entropy: a number or 'auto', got {self.target_entropy!r}")

    @property
    def learns_alpha(self) -> bool:
        """Whether the entropy coefficient is learned (``ent_coef`` 'auto' or 'auto_<init>')."""
        return isinstance(self.ent_coef, str)

    def alpha_init(self) -> float:
        """The entropy coefficient's value at the start (SB3: 1.0 for 'auto')."""
        if not self.learns_alpha:
            return float(self.ent_coef)
        return float(self.ent_coef[5:]) if self.ent_coef.startswith("auto_") else 1.0

    def entropy_target(self, n_act: int) -> float:
        return -float(n_act) if self.target_entropy == "auto" else float(self.target_entropy)

    @property
    def rows(self) -> int:
        """Replay rows per env copy (SB3: ``buffer_size // n_envs``, at least 1)."""
        return max(int(self.buffer_size) // int(self.n_envs), 1)

    @classmethod
    def from_kwargs(cls, kw: dict[str, Any], n_envs: int, who: str = "SAC") -> SACConfig:
        """The config of SB3-style SAC keyword arguments (``batch_size``, ``use_sde``,
        ``policy_kwargs={"log_std_init": ..., "net_arch": [...]}``, ...); what this SAC does not
        have is refused in one line naming ``who``."""
        kw = dict(kw)
        ignored = {"policy": "MlpPolicy", "device": None, "verbose": None, "sde_sample_freq": -1}
        policy_kwargs = dict(kw.pop("policy_kwargs", None) or {})
        own = {"net_arch", "qf_arch", "log_std_init", "clip_mean", "n_critics", "n_envs"}
        names = {f.name for f in fields(cls)} - own
        bad = [k for k, v in kw.items() if k not in names and not (k in ignored and ignored[k] in (None, v))]
        bad += [f"policy_kwargs.{k}" for k, v in policy_kwargs.items()
                if k not in {"net_arch", "log_std_init", "clip_mean", "n_critics"} and not (k == "use_expln" and not v)]
        if bad:
            raise ConfigError(f"SACConfig: {who} sets {sorted(bad)}, which the compiled SAC does not have (it has "
                              f"{sorted(names | {'policy_kwargs.' + k for k in ('net_arch', 'log_std_init', 'clip_mean', 'n_critics')})})")
        if "learning_rate" in kw and not isinstance(kw["learning_rate"], (int, float)):
            raise ConfigError(f"SACConfig: {who}: learning_rate must be a constant (no schedules), got {kw['learning_rate']!r}")
        if "train_freq" in kw and not isinstance(kw["train_freq"], int):
            raise ConfigError(f"SACConfig: {who}: train_freq must be a number of steps (no (n, 'episode')), got {kw['train_freq']!r}")
        extra: dict[str, Any] = {}
        arch = policy_kwargs.get("net_arch")
        if arch is not None:
            if isinstance(arch, dict):
                extra["net_arch"], extra["qf_arch"] = tuple(int(x) for x in arch["pi"]), tuple(int(x) for x in arch["qf"])
            else:
                extra["net_arch"] = extra["qf_arch"] = tuple(int(x) for x in arch)
        for k, kind in (("log_std_init", float), ("clip_mean", float), ("n_critics", int)):
            if k in policy_kwargs:
                extra[k] = kind(policy_kwargs[k])
        try:
            return cls(n_envs=int(n_envs), **extra, **{k: kw[k] for k in names if k in kw})
        except ConfigError as e:
            raise ConfigError(f"{who}: {e}") from None


# ---------------------------------------------------------------------- the networks
def _linear(rng: np.random.Generator, n_in: int, n_out: int) -> tuple[np.ndarray, np.ndarray]:
    """torch's ``nn.Linear`` initialisation: weight and bias uniform in +-1/sqrt(fan_in); the
    weight stored (n_in, n_out)."""
    bound = 1.0 / math.sqrt(n_in)
    return (rng.uniform(-bound, bound, (n_in, n_out)).astype(np.float32),
            rng.uniform(-bound, bound, n_out).astype(np.float32))


def _mlp_init(rng: np.random.Generator, sizes: list[int]) -> list:
    return [_linear(rng, a, b) for a, b in zip(sizes[:-1], sizes[1:], strict=True)]


class Nets(NamedTuple):
    """The learned parameters: ``actor`` {"hidden": [(w, b), ...], "mu": (w, b), "log_std": a
    (features, actions) array with gSDE or the head (w, b) without}, ``critics`` (one layer list
    per critic), their ``targets``, and ``log_alpha`` (the entropy coefficient's log; learned only
    with ``ent_coef='auto'``, and not read with a fixed one)."""

    actor: dict
    critics: list
    targets: list
    log_alpha: Any


def init_nets(seed: int, cfg: SACConfig, n_obs: int, n_act: int) -> Nets:
    """Fresh networks as SB3 builds them (module docstring), float32 numpy arrays drawn from
    ``seed``."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 47]))
    hidden = _mlp_init(rng, [n_obs, *cfg.net_arch])
    last = cfg.net_arch[-1]
    actor: dict[str, Any] = {"hidden": hidden, "mu": _linear(rng, last, n_act)}
    actor["log_std"] = (np.full((last, n_act), cfg.log_std_init, np.float32) if cfg.use_sde
                        else _linear(rng, last, n_act))
    critics = [_mlp_init(rng, [n_obs + n_act, *cfg.qf_arch, 1]) for _ in range(cfg.n_critics)]
    targets = [[(w.copy(), b.copy()) for w, b in c] for c in critics]
    alpha = cfg.alpha_init()  # 0 for a fixed ent_coef=0 (no entropy term): its log is -inf, never read
    return Nets(actor, critics, targets, np.float32(math.log(alpha) if alpha > 0 else -np.inf))


def _features(layers: list, x: Any) -> Any:
    """The last hidden layer's ReLU features, features-major (H, N), for samples-major ``x``."""
    import jax  # noqa: PLC0415  (imported by jax_nets.modules before any call)

    dense, h = jax_nets.dense_layer(), jax.lax.optimization_barrier(x.T)
    for w, b in layers:
        h = jax.nn.relu(dense(h, w, b))
    return h


def q_values(critics: list, obs: Any, actions: Any) -> Any:
    """Every critic's Q(obs, actions), (n_critics, N)."""
    import jax.numpy as jnp  # noqa: PLC0415

    x = jnp.concatenate([obs, actions], axis=1)
    return jnp.stack([jax_nets.dense_layer()(_features(c[:-1], x), *c[-1])[0] for c in critics])


def distribution(cfg: SACConfig, actor: dict, obs: Any) -> tuple[Any, Any, Any]:
    """(mean (N, A), std (N, A), features (H, N)) of the actor's Gaussian before the tanh."""
    import jax.numpy as jnp  # noqa: PLC0415

    h = _features(actor["hidden"], obs)
    mean = jax_nets.dense_layer()(h, *actor["mu"]).T
    if cfg.use_sde:
        if cfg.clip_mean > 0:
            mean = jnp.clip(mean, -cfg.clip_mean, cfg.clip_mean)
        variance = (h.T**2) @ (jnp.exp(actor["log_std"]) ** 2)
        return mean, jnp.sqrt(variance + SQUASH_EPS), h
    log_std = jnp.clip(jax_nets.dense_layer()(h, *actor["log_std"]).T, LOG_STD_MIN, LOG_STD_MAX)
    return mean, jnp.exp(log_std), h


def _normal_log_prob(x: Any, mean: Any, std: Any) -> Any:
    """torch's ``Normal.log_prob``, summed over the action's dimensions."""
    import jax.numpy as jnp  # noqa: PLC0415

    return jnp.sum(-((x - mean) ** 2) / (2 * std**2) - jnp.log(std) - math.log(math.sqrt(2 * math.pi)), axis=-1)


def sample(cfg: SACConfig, actor: dict, obs: Any, noise: Any) -> tuple[Any, Any]:
    """(squashed action (N, A) in (-1, 1), its log-probability (N,)) for ``noise``: gSDE, the
    step's standard-normal matrix (H, A) (the exploration matrix is it x exp(log_std), so its
    gradient reaches the log-std, as SB3's ``rsample`` does); without, standard normals (N, A)."""
    import jax.numpy as jnp  # noqa: PLC0415

    mean, std, h = distribution(cfg, actor, obs)
    if cfg.use_sde:
        gaussian = mean + h.T @ (noise * jnp.exp(actor["log_std"]))
        action = jnp.tanh(gaussian)
        inverse = jnp.arctanh(jnp.clip(action, -1.0 + F32_EPS, 1.0 - F32_EPS))
        logp = _normal_log_prob(inverse, mean, std) - jnp.sum(jnp.log(1.0 - jnp.tanh(inverse) ** 2 + SQUASH_EPS), axis=-1)
        return action, logp
    gaussian = mean + std * noise
    action = jnp.tanh(gaussian)
    return action, _normal_log_prob(gaussian, mean, std) - jnp.sum(jnp.log(1.0 - action**2 + SQUASH_EPS), axis=-1)


class Batch(NamedTuple):
    """Replay samples, float32: observations (..., N, n_obs), actions scaled to [-1, 1] (..., N,
    A), rewards (..., N), next observations, dones (..., N; 1 for a termination, 0 for a timeout)."""

    obs: Any
    actions: Any
    rewards: Any
    next_obs: Any
    dones: Any


class State(NamedTuple):
    """What a train call carries: the networks and the three optimisers' states."""

    nets: Nets
    actor_opt: Any
    critic_opt: Any
    alpha_opt: Any


def optimizer(cfg: SACConfig) -> Any:
    _, _, optax = jax_nets.modules()
    return optax.adam(cfg.learning_rate, eps=ADAM_EPS)


def init_state(cfg: SACConfig, nets: Nets) -> State:
    """The networks as jax float32 arrays with fresh Adam states."""
    jax, jnp, _ = jax_nets.modules()
    nets = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), nets)
    tx = optimizer(cfg)
    return State(nets, tx.init(nets.actor), tx.init(nets.critics), tx.init(nets.log_alpha))


def gradient_step(cfg: SACConfig, n_act: int, state: State, batch: Batch, noise: tuple[Any, Any],
                  update_target: Any) -> tuple[State, dict[str, Any]]:
    """One SAC gradient step, in SB3's order (module docstring). ``noise``: (for the batch's
    observations, for its next observations), ``sample``'s noise; with gSDE both are the step's
    one matrix. ``update_target``: whether this step Polyak-averages the targets (a bool array).
    Returns the new state and the step's losses and entropy coefficient."""
    jax, jnp, optax = jax_nets.modules()
    tx = optimizer(cfg)
    nets = state.nets
    sg = jax.lax.stop_gradient
    _, logp = sample(cfg, nets.actor, batch.obs, noise[0])
    stats: dict[str, Any] = {}
    alpha_opt, log_alpha = state.alpha_opt, nets.log_alpha
    # a fixed coefficient is SB3's constant itself, not exp(log(.)), so that 0 stays 0
    alpha = jnp.exp(sg(log_alpha)) if cfg.learns_alpha else jnp.float32(cfg.alpha_init())
    if cfg.learns_alpha:
        target_entropy = cfg.entropy_target(n_act)

        def alpha_loss(la):
            return -jnp.mean(la * sg(logp + target_entropy))

        loss_a, grad = jax.value_and_grad(alpha_loss)(log_alpha)
        upd, alpha_opt = tx.update(grad, alpha_opt, log_alpha)
        log_alpha = optax.apply_updates(log_alpha, upd)
        stats["ent_coef_loss"] = loss_a
    stats["ent_coef"] = alpha
    next_action, next_logp = sample(cfg, nets.actor, batch.next_obs, noise[1])
    next_q = jnp.min(q_values(nets.targets, batch.next_obs, next_action), axis=0) - alpha * next_logp
    target_q = sg(batch.rewards + (1.0 - batch.dones) * cfg.gamma * next_q)

    def critic_loss(critics):
        q = q_values(critics, batch.obs, batch.actions)
        return 0.5 * jnp.sum(jnp.mean((q - target_q) ** 2, axis=1))

    loss_q, grad = jax.value_and_grad(critic_loss)(nets.critics)
    upd, critic_opt = tx.update(grad, state.critic_opt, nets.critics)
    critics = optax.apply_updates(nets.critics, upd)

    def actor_loss(actor):
        action, lp = sample(cfg, actor, batch.obs, noise[0])
        return jnp.mean(alpha * lp - jnp.min(q_values(critics, batch.obs, action), axis=0))

    loss_pi, grad = jax.value_and_grad(actor_loss)(nets.actor)
    upd, actor_opt = tx.update(grad, state.actor_opt, nets.actor)
    actor = optax.apply_updates(nets.actor, upd)
    tau = jnp.where(update_target, jnp.float32(cfg.tau), jnp.float32(0.0))
    targets = jax.tree_util.tree_map(lambda t, p: t * (1.0 - tau) + p * tau, nets.targets, critics)
    stats.update(critic_loss=loss_q, actor_loss=loss_pi)
    return State(Nets(actor, critics, targets, log_alpha), actor_opt, critic_opt, alpha_opt), stats


def step_noise(cfg: SACConfig, key: Any, n_batch: int, n_act: int) -> tuple[Any, Any]:
    """One gradient step's noise from a jax key (``gradient_step``): gSDE's one standard-normal
    matrix (H, A) for both samples (SB3 draws it at the step's start), else two (N, A) draws."""
    import jax  # noqa: PLC0415
    import jax.numpy as jnp  # noqa: PLC0415

    if cfg.use_sde:
        m = jax.random.normal(key, (cfg.net_arch[-1], n_act), jnp.float32)
        return m, m
    draws = jax.random.normal(key, (2, n_batch, n_act), jnp.float32)
    return draws[0], draws[1]


def make_train(cfg: SACConfig, n_act: int) -> Callable:
    """``train(state, batches, key_data) -> (state, mean stats)``: ``cfg.gradient_steps`` gradient
    steps in one ``lax.scan``, on ``batches`` (a ``Batch`` of (gradient_steps, batch_size, ...)
    arrays sampled on the host), with noise from the key ``key_data`` (uint32 (2,)). Step i
    updates the targets when i % target_update_interval == 0 (SB3 counts within a train call)."""
    jax, jnp, _ = jax_nets.modules()
    steps = int(cfg.gradient_steps)

    def train(state, batches, key_data):
        keys = jax.random.split(jax.random.wrap_key_data(key_data), steps)
        update = jnp.arange(steps) % int(cfg.target_update_interval) == 0

        def body(st, xs):
            batch, key, upd = xs
            return gradient_step(cfg, n_act, st, batch, step_noise(cfg, key, cfg.batch_size, n_act), upd)

        state, stats = jax.lax.scan(body, state, (batches, keys, update))
        return state, {k: jnp.mean(v) for k, v in stats.items()}

    return train


# ---------------------------------------------------------------------- the host's side
class HostActor:
    """The actor's actions by numpy on the host, for collection and evaluation (one call per env
    step, where a compiled program's call would cost 50-90 us: ``jax_nets.HostPolicy``). Actions
    are scaled to [-1, 1] (the replay buffer's); ``unscale`` maps them to the env's bounds."""

    def __init__(self, cfg: SACConfig, actor: dict, low: np.ndarray, high: np.ndarray):
        self.cfg = cfg
        self.hidden = [(np.asarray(w), np.asarray(b)) for w, b in actor["hidden"]]
        self.mu = tuple(np.asarray(x) for x in actor["mu"])
        self.log_std = (np.asarray(actor["log_std"]) if cfg.use_sde
                        else tuple(np.asarray(x) for x in actor["log_std"]))
        self.low, self.high = low, high

    def _features(self, obs: np.ndarray) -> np.ndarray:
        h = np.asarray(obs, np.float32)
        for w, b in self.hidden:
            h = np.maximum(h @ w + b, 0.0)
        return h

    def _mean(self, h: np.ndarray) -> np.ndarray:
        mean = h @ self.mu[0] + self.mu[1]
        if self.cfg.use_sde and self.cfg.clip_mean > 0:
            mean = np.clip(mean, -self.cfg.clip_mean, self.cfg.clip_mean)
        return mean

    def deterministic(self, obs: np.ndarray) -> np.ndarray:
        """tanh(mean), (N, A) in [-1, 1]."""
        return np.tanh(self._mean(self._features(obs)))

    def exploration(self, rng: np.random.Generator, n: int) -> np.ndarray | None:
        """gSDE: one exploration matrix per env copy (n, H, A), entries N(0, exp(log_std)^2);
        None without gSDE."""
        if not self.cfg.use_sde:
            return None
        return (np.exp(self.log_std) * rng.standard_normal((n, *self.log_std.shape))).astype(np.float32)

    def sample(self, obs: np.ndarray, rng: np.random.Generator, explore: np.ndarray | None) -> np.ndarray:
        """A sampled action (N, A) in [-1, 1]: tanh(mean + features @ E_i) for copy i with gSDE,
        tanh(mean + std x N(0, 1)) without."""
        h = self._features(obs)
        mean = self._mean(h)
        if explore is not None:
            return np.tanh(mean + np.einsum("nh,nha->na", h, explore[: len(h)]))
        w, b = self.log_std
        std = np.exp(np.clip(h @ w + b, LOG_STD_MIN, LOG_STD_MAX))
        return np.tanh(mean + std * rng.standard_normal(mean.shape).astype(np.float32))

    def unscale(self, scaled: np.ndarray) -> np.ndarray:
        """[-1, 1] to the env's [low, high] (SB3's ``unscale_action``)."""
        return self.low + 0.5 * (scaled + 1.0) * (self.high - self.low)


@dataclass
class Replay:
    """SB3's ``ReplayBuffer`` (no memory optimisation): ``cfg.rows`` rows of ``n_envs`` transitions,
    a ring; ``sample`` draws a row index uniformly from the filled ones and an env copy uniformly,
    per sample, as SB3 does. The done flag is stored with timeouts dropped."""

    rows: int
    n_envs: int
    n_obs: int
    n_act: int
    pos: int = 0
    full: bool = False
    data: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        shapes = {"obs": (self.n_obs,), "actions": (self.n_act,), "rewards": (), "next_obs": (self.n_obs,), "dones": ()}
        self.data = {k: np.zeros((self.rows, self.n_envs, *s), np.float32) for k, s in shapes.items()}

    @property
    def size(self) -> int:
        return self.rows if self.full else self.pos

    def add(self, obs: np.ndarray, next_obs: np.ndarray, actions: np.ndarray, rewards: np.ndarray,
            dones: np.ndarray) -> None:
        for k, v in (("obs", obs), ("next_obs", next_obs), ("actions", actions), ("rewards", rewards), ("dones", dones)):
            self.data[k][self.pos] = np.asarray(v, np.float32).reshape(self.data[k].shape[1:])
        self.pos += 1
        if self.pos == self.rows:
            self.full, self.pos = True, 0

    def sample(self, rng: np.random.Generator, steps: int, batch: int) -> Batch:
        """(steps, batch, ...) samples for ``steps`` gradient steps."""
        rows = rng.integers(0, self.size, size=(steps, batch))
        envs = rng.integers(0, self.n_envs, size=(steps, batch))
        return Batch(*(self.data[k][rows, envs] for k in Batch._fields))
