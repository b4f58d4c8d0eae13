"""The NN surrogates (``surrogate=nn``: ``models.nn.MLPDynamics``; ``surrogate=pe``:
``models.pe.GaussianEnsembleDynamics``) as pure JAX functions of their weights, for the compiled
training loop (``surrogate.jax_step``), as ``models.jax_eval.linear_predictor`` is for the sparse
models.

``network_model(model, members)`` returns a ``jax_eval.JaxModel``: ``predict(z, params)`` (the
model's ``predict``: the members' mean next state), ``members(z, params)`` (each member's, as
``predict_members``: the spread the task's pessimism reads), for a probabilistic ensemble
``sample(z, params, u, eps)`` (``sample``: a random elite's Gaussian step, its draws given as
inputs), and ``params``, the model's numbers as arrays: the stacked weights and biases of every
layer, the input and output normalisation, the elites' indices and the log-variance bounds.
The weights are arguments of the compiled program, not constants in it: a Dyna refit of the same
architecture, or another seed's fit, steps through the program compiled for the first (``key``:
the architecture).

Why hand-written and not the torch module run through a bridge: the compiled loop needs the
network inside one XLA program with the policy and the task; torch has no path into one. The
forward is the module's own (``models.mlp.EnsembleMLP``, ``models.pe.GaussianEnsembleMLP``): the
same affine maps per member, the same activation (torch's exact GELU, ELU with alpha 1), the same
soft bounds on a Gaussian head's log-variance, in the network's dtype, the normalisation and the
members' mean in float64 as ``MLPDynamics.predict`` computes them. XLA sums each product in
another order than torch's kernels: results agree to the network dtype's rounding (tested on
10,000 inputs per model kind; float64 networks to 1e-12). The products are asked for at
``Precision.HIGHEST``: on a GPU, JAX's default multiplies float32 layers in TF32 (10-bit
mantissas), which left the states 1e-5 to 1e-4 off ModelEnv's (docs/compiled.md, On a GPU); on the
CPU it changes nothing.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sdrl_bench.models.jax_eval import JaxModel, jax_modules


def _activation(jax: Any, jnp: Any, name: str) -> Any:
    """The jax counterpart of ``models.mlp.ACTIVATIONS[name]`` (torch's defaults)."""
    table = {"tanh": jnp.tanh, "relu": jax.nn.relu, "silu": jax.nn.silu, "elu": jax.nn.elu,
             "gelu": lambda x: jax.nn.gelu(x, approximate=False)}
    if name not in table:
        raise NotImplementedError(f"network_model: activation {name!r} has no jax counterpart here "
                                  f"(known: {sorted(table)})")
    return table[name]


def network_model(model: Any, members: bool = False) -> JaxModel:
    """The NN model ``model`` (fitted: ``net_``) as a ``JaxModel``; ``members``: with the
    members' predictions (the task's pessimism)."""
    jax, jnp = jax_modules("sdrl_bench.models.jax_nn")
    net = getattr(model, "net_", None)
    if net is None:
        raise TypeError(f"network_model: the {getattr(model, 'kind', type(model).__name__)!r} model is not fitted (no net_)")
    gaussian = hasattr(net, "body")  # models.pe.GaussianEnsembleMLP: (mean, log-variance) heads
    body = net.body if gaussian else net
    dtype = jnp.float32 if model.dtype == "float32" else jnp.float64
    HIGHEST = jax.lax.Precision.HIGHEST  # noqa: N806  (a GPU's default multiplies float32 in TF32)
    act = _activation(jax, jnp, model.activation)
    n_s, n_out = len(model.state_names_), len(np.atleast_1d(model.output_mean_))
    if n_s != n_out:
        raise NotImplementedError(f"network_model: {n_s} state inputs for {n_out} outputs (s + delta needs equal widths)")
    as_np = lambda t: t.detach().cpu().numpy().copy()  # noqa: E731
    params: dict[str, Any] = {
        "w": [as_np(layer.weight) for layer in body.layers], "b": [as_np(layer.bias) for layer in body.layers],
        "in_mean": np.asarray(model.input_mean_, float), "in_std": np.asarray(model.input_std_, float),
        "out_mean": np.asarray(model.output_mean_, float), "out_std": np.asarray(model.output_std_, float)}
    if gaussian:
        params.update(max_logvar=as_np(net.max_logvar), min_logvar=as_np(net.min_logvar),
                      elites=np.asarray(model.elites_, dtype=np.int32))
    last = len(params["w"]) - 1

    def outputs(z, p):
        """(K', N, width): the network's raw outputs (the elites' for a Gaussian ensemble), in
        its dtype, for model inputs ``z`` (N, n_inputs) float64."""
        zn = ((jnp.asarray(z, jnp.float64) - p["in_mean"]) / p["in_std"]).astype(dtype)
        h = zn
        for i, (w, b) in enumerate(zip(p["w"], p["b"], strict=True)):
            w, b = jnp.asarray(w, dtype), jnp.asarray(b, dtype)
            h = (jnp.einsum("ni,kio->kno", h, w, precision=HIGHEST) if h.ndim == 2
                 else jnp.matmul(h, w, precision=HIGHEST)) + b[:, None, :]
            if i < last:
                h = act(h)
        if gaussian:
            h = h[p["elites"]]
        return h

    def scale(z, delta, p):
        return jnp.asarray(z, jnp.float64)[..., :n_s] + (delta * p["out_std"] + p["out_mean"])

    def member_states(z, p):
        return scale(z, outputs(z, p)[..., :n_out].astype(jnp.float64), p)

    if gaussian:
        def predict(z, p):  # the elites' mean next state (GaussianEnsembleDynamics.predict)
            return member_states(z, p).mean(axis=0)

        def sample(z, p, u, eps):
            """A random elite's Gaussian step per row: elite ``floor(u * n_elites)`` (u uniform in
            [0, 1), (N,)), delta = mean + exp(logvar / 2) * eps (eps standard normal, (N, n))."""
            out = outputs(z, p)
            raw = out[..., n_out:]
            hi, lo = jnp.asarray(p["max_logvar"], dtype), jnp.asarray(p["min_logvar"], dtype)
            logvar = hi - jax.nn.softplus(hi - raw)
            logvar = (lo + jax.nn.softplus(logvar - lo)).astype(jnp.float64)
            k = out.shape[0]
            pick = jnp.minimum(jnp.floor(jnp.asarray(u, jnp.float64) * k).astype(jnp.int32), k - 1)
            rows = jnp.arange(out.shape[1])
            mean = out[pick, rows, :n_out].astype(jnp.float64)
            delta = mean + jnp.exp(0.5 * logvar[pick, rows]) * jnp.asarray(eps, jnp.float64)
            return scale(z, delta, p)
    else:
        sample = None

        def predict(z, p):  # MLPDynamics.predict: one member's, or the members' mean in float64
            out = outputs(z, p).astype(jnp.float64)
            return scale(z, out[0] if out.shape[0] == 1 else out.mean(axis=0), p)

    k = len(params["elites"]) if gaussian else params["w"][0].shape[0]
    key = ("network", type(model).__name__, model.activation, model.dtype,
           tuple(tuple(w.shape) for w in params["w"]), k, members)
    return JaxModel(predict, member_states if members else None, sample, params, key)
