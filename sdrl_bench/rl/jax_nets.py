"""The compiled agents' networks, as pure functions of a pytree of (weight, bias) pairs: SB3's
``MlpPolicy`` actor and critic for the compiled PPO (``rl.jax_ppo``): their layers, SB3's
orthogonal initialisation, the Gaussian (plain or gSDE) and categorical policies' sampling,
log-probabilities and entropies, the deterministic action, on the host too (``HostPolicy``);
and the dense layer with its hand-written gradient that the compiled SAC (``rl.jax_sac``) builds
its networks from as well. ``modules()`` imports jax (float64 on) and optax, the optional
``[jax]`` extra, on first use.

Hand-written, and why: the two MLPs are a few lines of jax.numpy over a plain pytree of
(weight, bias) pairs, not flax modules; flax would add a dependency for two tanh matmul chains
and a second parameter format beside SB3's. The layers are float32, as SB3's torch networks.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from sdrl_bench import ConfigError

if TYPE_CHECKING:
    from sdrl_bench.rl.jax_ppo import PPOConfig

HIDDEN = (64, 64)
"""SB3's default ``net_arch`` for PPO's MlpPolicy: separate actor and critic MLPs."""
INSTALL_HINT = "pip install 'sdrl-bench[jax]' (jax, optax)"


def modules(who: str = "sdrl_bench.rl.jax_nets") -> tuple[Any, Any, Any]:
    """jax (float64 on), jax.numpy and optax, imported on first use (an optional extra);
    ``who`` names what needs them in the install hint."""
    from sdrl_bench.models.jax_eval import jax_modules  # noqa: PLC0415

    jax, jnp = jax_modules(who)
    try:
        import optax  # noqa: PLC0415
    except ImportError as exc:
        raise ImportError(f"{who} needs optax, an optional extra: {INSTALL_HINT}") from exc
    return jax, jnp, optax


def mlp_layers(n_obs: int, n_act: int) -> dict[str, list[tuple[int, int]]]:
    """(inputs, outputs) of each linear layer of the actor and the critic."""
    sizes = (n_obs, *HIDDEN)
    hidden = list(zip(sizes[:-1], sizes[1:], strict=True))
    return {"actor": [*hidden, (HIDDEN[-1], n_act)], "critic": [*hidden, (HIDDEN[-1], 1)]}


def init_net(key: Any, n_obs: int, n_act: int, cfg: PPOConfig | None = None, discrete: bool = False) -> dict[str, Any]:
    """The actor, critic and log-std, initialised as SB3's MlpPolicy (``ortho_init``): orthogonal
    weights with gain sqrt(2) in hidden layers, 0.01 for the action mean (or the logits), 1 for
    the value; zero biases; log-std ``cfg.log_std_init`` (one per action, or with gSDE one per
    (latent feature, action), SB3's ``full_std``). float32. ``discrete``: a categorical policy
    over ``n_act`` actions (the actor's outputs are its logits; no log-std)."""
    from sdrl_bench.rl.jax_ppo import PPOConfig  # noqa: PLC0415  (jax_ppo imports this module)

    jax, jnp, _ = modules()
    cfg = cfg or PPOConfig()
    use_sde, log_std_init = cfg.use_sde, cfg.log_std_init
    net: dict[str, Any] = {}
    layers = mlp_layers(n_obs, n_act)
    keys = iter(jax.random.split(key, sum(len(v) for v in layers.values())))
    for name, last_gain in (("actor", 0.01), ("critic", 1.0)):
        out = []
        for i, (n_in, n_out) in enumerate(layers[name]):
            gain = last_gain if i == len(layers[name]) - 1 else math.sqrt(2.0)
            w = jax.nn.initializers.orthogonal(scale=gain)(next(keys), (n_in, n_out), jnp.float32)
            out.append((w, jnp.zeros(n_out, jnp.float32)))
        net[name] = out
    if discrete:
        if use_sde:
            raise ConfigError("PPOConfig.use_sde: gSDE needs continuous (Box) actions")
        return net
    shape = (HIDDEN[-1], n_act) if use_sde else (n_act,)
    net["log_std"] = jnp.full(shape, log_std_init, jnp.float32)
    return net


def is_discrete(net: dict) -> bool:
    """Whether ``net`` is a categorical policy (``init_net(discrete=True)``: no log-std)."""
    return "log_std" not in net


@functools.cache
def dense_layer() -> Callable:
    """``dense(x_t, w, b) -> w.T @ x_t + b``: one linear layer on features-major activations
    (``x_t``: (n_in, N), out (n_out, N); ``w`` (n_in, n_out) as SB3 stores it), with its gradient
    written by hand. Why: in the usual samples-major form the weights' gradient x.T @ dy
    contracts the samples' axis of both operands, a product XLA's CPU backend leaves to its slow
    generic dot (about 80 us per 1024 x 64 layer, measured) while its fast library kernels take
    the other two. Features-major, the three products are w.T @ x_t (w.T copied: 64 x 64), w @ dy_t
    and x_t @ dy_t.T, all of the shapes the fast kernels take; the fast MountainCar pack's update went
    from 8.0 to 6.4-7.0 ms (one update timed alone, this 2-core machine). The same sums, in another order: results
    move by rounding."""
    jax, jnp, _ = modules()

    def forward(x_t, w, b):
        return jax.lax.optimization_barrier(w.T) @ x_t + b[:, None]  # the barrier keeps w.T a copy

    @jax.custom_vjp
    def dense(x_t, w, b):
        return forward(x_t, w, b)

    def fwd(x_t, w, b):
        return forward(x_t, w, b), (x_t, w)

    def bwd(res, dy_t):
        x_t, w = res
        return w @ dy_t, x_t @ dy_t.T, jnp.sum(dy_t, axis=1)

    dense.defvjp(fwd, bwd)
    return dense


def _hidden(layers: list, x: Any) -> Any:
    """The last hidden layer's features, features-major (64, N), for samples-major inputs (N, n_obs)."""
    import jax  # noqa: PLC0415  (imported by modules() before any call)
    import jax.numpy as jnp  # noqa: PLC0415

    dense, h = dense_layer(), jax.lax.optimization_barrier(x.T)  # a copy: the first weights' gradient a fast product too
    for w, b in layers[:-1]:
        h = jnp.tanh(dense(h, w, b))
    return h


def _mlp(layers: list, x: Any) -> Any:
    """The network's outputs, samples-major (N, n_out)."""
    w, b = layers[-1]
    return dense_layer()(_hidden(layers, x), w, b).T


def action_mean(net: dict, obs: Any) -> Any:
    """The policy's mean action (N, n_act) for float32 observations (N, n_obs)."""
    return _mlp(net["actor"], obs)


def value(net: dict, obs: Any) -> Any:
    """The critic's value (N,)."""
    return _mlp(net["critic"], obs)[:, 0]


SDE_EPS = 1e-6
"""SB3's ``StateDependentNoiseDistribution`` epsilon, added to the variance."""


def policy(net: dict, obs: Any) -> tuple[Any, Any, Any]:
    """(mean (N, n_act), std (N, n_act), latent features, features-major (64, N)) of the policy's
    Gaussian. Plain: std = exp(log_std) for every state. gSDE (a 2-D log-std): the std of mean +
    latent @ E with E ~ N(0, exp(log_std)^2) elementwise, i.e. sqrt(latent^2 @ exp(log_std)^2 +
    1e-6), the latent features taken without gradient (SB3's ``learn_features=False``)."""
    import jax  # noqa: PLC0415
    import jax.numpy as jnp  # noqa: PLC0415

    latent_t = _hidden(net["actor"], obs)
    w, b = net["actor"][-1]
    mean = dense_layer()(latent_t, w, b).T
    log_std = net["log_std"]
    if log_std.ndim == 1:
        std = jnp.broadcast_to(jnp.exp(log_std), mean.shape)
    else:
        std = jnp.sqrt((jnp.exp(log_std) ** 2).T @ jax.lax.stop_gradient(latent_t) ** 2 + SDE_EPS).T
    return mean, std, latent_t


def exploration_matrices(net: dict, key: Any, n: int) -> Any:
    """gSDE: one exploration matrix per env copy (n, 64, n_act), each entry N(0, exp(log_std)^2)
    (SB3's ``reset_noise``); None without gSDE."""
    import jax  # noqa: PLC0415
    import jax.numpy as jnp  # noqa: PLC0415

    log_std = net.get("log_std")
    if log_std is None or log_std.ndim == 1:
        return None
    return jnp.exp(log_std) * jax.random.normal(key, (n, *log_std.shape), jnp.float32)


def action_noise(net: dict, key: Any, n: int) -> Any:
    """The random part of ``sample_action`` without gSDE, for ``n`` observations, drawn from
    ``key``: Gumbel noise (n, n_actions) for a categorical policy (``jax.random.categorical``'s
    own draw), standard normals (n, n_act) for a Gaussian. Apart so that a rollout draws all its
    steps' noise in one batched call (``make_rollout``)."""
    import jax  # noqa: PLC0415
    import jax.numpy as jnp  # noqa: PLC0415

    draw = jax.random.gumbel if is_discrete(net) else jax.random.normal
    return draw(key, (n, net["actor"][-1][0].shape[-1]), jnp.float32)


def sample_action(net: dict, obs: Any, key: Any, explore: Any = None, noise: Any = None) -> tuple[Any, Any, Any]:
    """(action, its log-probability (N,), the deterministic action): plain Gaussian, mean + std x
    N(0, 1); gSDE (``explore``: ``exploration_matrices``), mean + latent @ E_i for copy i, as SB3
    samples (actions (N, n_act) float32); categorical, an index (N,) int32 drawn from the logits
    (the argmax of logits + Gumbel noise, as ``jax.random.categorical`` draws). ``noise``:
    ``action_noise(net, key, N)`` drawn already (then ``key`` is not read); the same draws, so
    the same actions."""
    import jax  # noqa: PLC0415
    import jax.numpy as jnp  # noqa: PLC0415

    if noise is None and explore is None:
        noise = action_noise(net, key, obs.shape[0])
    if is_discrete(net):
        logits = action_mean(net, obs)
        action = jnp.argmax(noise + logits, axis=-1).astype(jnp.int32)
        logp = jnp.take_along_axis(jax.nn.log_softmax(logits), action[:, None], axis=1)[:, 0]
        return action, logp, jnp.argmax(logits, axis=-1).astype(jnp.int32)
    mean, std, latent_t = policy(net, obs)
    if explore is None:
        action = mean + std * noise
    else:
        action = mean + jnp.einsum("in,nij->nj", latent_t, explore)
    return action, log_prob(action, mean, std), mean


def log_prob_entropy(net: dict, obs: Any, actions: Any) -> tuple[Any, Any]:
    """(log-probability (N,), entropy (N,)) of stored ``actions`` under the current policy."""
    import jax  # noqa: PLC0415
    import jax.numpy as jnp  # noqa: PLC0415

    if is_discrete(net):
        logp_all = jax.nn.log_softmax(action_mean(net, obs))
        logp = jnp.take_along_axis(logp_all, actions.astype(jnp.int32)[:, None], axis=1)[:, 0]
        return logp, -jnp.sum(jnp.exp(logp_all) * logp_all, axis=-1)
    mean, std, _ = policy(net, obs)
    return log_prob(actions, mean, std), entropy(std)


def deterministic_action(net: dict, obs: Any, low: Any = None, high: Any = None) -> Any:
    """The policy's deterministic action: the most probable index (categorical; (N,) int32) or
    the Gaussian's mean clipped to [low, high] (N, n_act)."""
    import jax.numpy as jnp  # noqa: PLC0415

    out = action_mean(net, obs)
    if is_discrete(net):
        return jnp.argmax(out, axis=-1).astype(jnp.int32)
    return jnp.clip(out, low, high)


class HostPolicy:
    """``net``'s deterministic action, as ``deterministic_action`` computes it, by numpy on the host:
    ``HostPolicy(net, low, high)(obs)`` for float32 observations (N, n_obs). Why not the jitted
    ``deterministic_action``: a call of a compiled program costs XLA's CPU runtime 50-90 us however
    small the program (a [64, 64] MLP on 1 to 10 observations, against 8 us for a program of one
    add), and numpy computes these layers in 8-10 us; a real-env evaluation calls it once per
    lockstep step (``rl.agents.evaluate_real``). Ten MountainCar episodes of 999 steps, a curve
    point of the fast pack: 4.3-5.1 s of evaluation per run with the jitted action, 1.3-1.6 s with
    this one, the curve's means the same (measured on this 2-core machine). The same layers, ops and
    dtype (float32); numpy's products may sum in another order, so actions can differ by rounding
    (tested against the jitted action and SB3's policy)."""

    def __init__(self, net: dict, low: Any = None, high: Any = None):
        self.layers = [(np.asarray(w), np.asarray(b)) for w, b in net["actor"]]
        self.discrete = is_discrete(net)
        self.low, self.high = low, high

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        h = np.asarray(obs, np.float32)
        for w, b in self.layers[:-1]:
            h = np.tanh(h @ w + b)
        w, b = self.layers[-1]
        out = h @ w + b
        return np.argmax(out, axis=-1).astype(np.int32) if self.discrete else np.clip(out, self.low, self.high)


def log_prob(actions: Any, mean: Any, std: Any) -> Any:
    """log N(actions; mean, std^2), summed over action dimensions (``std`` broadcasts)."""
    import jax.numpy as jnp  # noqa: PLC0415

    z = (actions - mean) / std
    return jnp.sum(-0.5 * z**2 - jnp.log(std) - 0.5 * math.log(2 * math.pi), axis=-1)


def entropy(std: Any) -> Any:
    """The Gaussian's entropy per state (..., summed over action dimensions)."""
    import jax.numpy as jnp  # noqa: PLC0415

    return jnp.sum(jnp.log(std) + 0.5 + 0.5 * math.log(2 * math.pi), axis=-1)
