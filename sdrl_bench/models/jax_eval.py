"""A float64 JAX evaluator of a fitted sparse dynamics model: the surrogate's prediction as a pure function.

What it is for: the compiled training loop of issue 31, where the surrogate step runs as one
pure JAX function (``jax.jit`` / ``vmap`` / ``lax.scan`` over the agent's rollouts) instead of
numpy called from Python. ``jax_predictor(model)`` returns ``f(z) -> next regressed states``
for model inputs ``z`` of shape (N, n_inputs) (states, then encoded controls: the transpose of
the rows ``surrogate.model_env.ModelEnv.model_inputs`` makes, i.e. the layout of
``model.predict``), giving (N, n_states); a single input vector (n_inputs,) gives (n_states,).

How: nothing here restates an env's law or an op. The function is generated from the model's
own data, exactly as the one-state evaluator is (``models.fast.scalar_source``): its term table
(``terms_``), coefficients (``coef_``) and, for a per-equation model whose primed terms read
bounded next values, its stages (``stages_``: the rows of each stage, then the env's bounds
applied, ``jnp.clip`` as ``np.clip`` in ``models.fast._staged_batch``). Each op is the source
form of the one term table (``terms.TABLE[op].source``), run with the jax.numpy function of the
same name as each numpy/math function the generated source may call (``terms.SOURCE_NAMESPACE``:
``_sin`` -> ``jnp.sin``): a new op works here once its source form names a function jax.numpy
has.

Rounding: evaluated eagerly (op by op), the function computes what the one-state evaluator
(``models.fast.scalar_predictor``) computes, bit for bit (the same source, on columns; tested on
every built-in env's fit); it agrees with ``models.fast.batch_predictor`` and ``model.predict``
to rounding (their sums run in another order; tested to 1e-12). Under ``jax.jit``, XLA's CPU
backend turns a*b + c inside a fused kernel into one fused multiply-add (always: jaxlib 0.10.2
has no option against it but the ISA limit below), so compiled results differ from eager ones by rounding (a few 1e-15 on values up to ~25,
measured); started with ``XLA_FLAGS=--xla_cpu_max_isa=AVX`` (no FMA instructions) the compiled
function gives the eager bits exactly (tested). A compiled function is deterministic: the same
inputs give the same bits.

Precision: importing jax through this module (``jax_predictor``) turns on float64 for the
whole process (``jax.config.update("jax_enable_x64", True)``): the models' coefficients are
float64 and the surrogate computes in float64. jax is an optional extra (``sdrl-bench[jax]``);
the package imports without it, and ``jax_predictor`` says how to install it.

Supported: ``SindyModel`` and ``PerEquationModel`` (staged or not). An ensemble member is
evaluated with ``jax_predictor(model, coef=model.members_[k])`` (its coefficients over the same
terms and stages). Not supported here: models without term tables (the NN models ``nn`` and
``pe``: a clear error names the kind); ``jax_model`` evaluates those through ``models.jax_nn``.

The rest of ``ModelEnv.step`` (bounds, divergence guard, the task's reward and termination, the
step noise as an input) is ``surrogate.jax_step``; what neither covers yet is listed there.
"""

from __future__ import annotations

import logging
import os
import warnings
from typing import Any, NamedTuple
from collections.abc import Callable, Sequence

import numpy as np

from sdrl_bench.models.fast import scalar_source
from sdrl_bench.models.terms import SOURCE_NAMESPACE, Term

JaxPredict = Callable[[Any], Any]


class JaxModel(NamedTuple):
    """A fitted model as pure jax functions of its numbers (``params``: arrays, an argument of a
    compiled program), what ``surrogate.jax_step`` steps through. ``jax_model`` builds one."""

    predict: Callable
    """``predict(z, params) -> (N, n_states)``: the model's ``predict`` at inputs ``z`` (N, n_inputs)."""
    members: Callable | None
    """``members(z, params) -> (K, N, n_states)``: each ensemble member's prediction (the spread
    the task's pessimism reads); None where not asked for."""
    sample: Callable | None
    """``sample(z, params, u, eps) -> (N, n_states)``: a model that draws its own steps (a
    probabilistic ensemble), its draws as inputs (u (N,) uniform, eps (N, n_states) standard
    normal); None for the others."""
    params: dict
    key: tuple
    """The structure the functions depend on besides ``params``: models of equal keys share a
    compiled program."""


INSTALL_HINT = "pip install 'sdrl-bench[jax]'"


SINGLE_THREAD_MATMULS = "--xla_cpu_multi_thread_eigen=false"
"""XLA's CPU matmuls on one thread. The harness's matrices are small (64-wide layers, minibatches
of ~1024): splitting each over two threads costs more than it saves. Measured on this 2-core
machine, one update of the fast MountainCar pack (16 minibatches of 1024): 18.2 ms with the
default, 12.5 ms with this flag (median of 20)."""


WIDE_VECTORS = "--xla_cpu_prefer_vector_width=512"
"""XLA's CPU code in the widest vectors the CPU has (its default stops at 256 bits, to spare
older CPUs' clock; LLVM uses no wider than the CPU's ISA). Measured on this 2-core AVX-512
machine, the fast MountainCar pack's compiled training, one core: 526,000 -> 589,000 steps/s
(``benchmarks/compiled_ppo.py``, median of 7, two rounds alternated)."""

DETERMINISTIC_GPU = "--xla_gpu_deterministic_ops=true"
"""XLA's GPU kernels chosen and run deterministically (no autotuned choice that can change from one
process to the next, no reductions by atomics). Without it, on an H200 (jax 0.11.2, 2026-11-30), a
fresh process trained the compiled PPO to other bits than the test's own process
(``test_through_the_lowering_cache_training_is_what_it_is_compiled_directly``); with it, every
process of that test trained the same bits (one run). Its cost there was not measured. The CPU
ignores it."""

DEFAULT_XLA_FLAGS = {"xla_cpu_multi_thread_eigen": SINGLE_THREAD_MATMULS, "xla_cpu_prefer_vector_width": WIDE_VECTORS,
                     "xla_gpu_deterministic_ops": DETERMINISTIC_GPU}


MATMUL_PRECISION_VAR = "JAX_DEFAULT_MATMUL_PRECISION"
"""Where unset, ``jax_modules`` sets JAX's default matmul precision to ``highest``: float32
products in full precision, as SB3's torch computes them (its default on a GPU too: TF32 off for
matmuls). JAX's own default multiplies float32 in TF32 on a GPU; on an H200 (2026-11-30) the
compiled PPO's and SAC's updates and policies then left SB3's beyond the tests' tolerances (12 of
the agents' tests failed there; with ``highest``, 1: bits across processes, ``DETERMINISTIC_GPU``). On the CPU it changes no program's
code (the same compiled HLO, the precision annotated)."""


def jax_modules(who: str = "sdrl_bench.models.jax_eval"):
    """jax and jax.numpy, with float64 on (imported on first use: jax is an optional extra);
    ``who`` names the caller in the install hint. Each of ``DEFAULT_XLA_FLAGS`` that
    ``XLA_FLAGS`` does not already set is added to it (XLA's CPU matmuls on one thread, wide
    vectors; deterministic GPU kernels); they take effect when no jax computation ran before in the process. Products in
    full precision unless ``$JAX_DEFAULT_MATMUL_PRECISION`` says otherwise (``MATMUL_PRECISION_VAR``)."""
    flags = os.environ.get("XLA_FLAGS", "")
    extra = [flag for name, flag in DEFAULT_XLA_FLAGS.items() if name not in flags]
    if extra:  # read when XLA's CPU client starts (first use), not at import
        os.environ["XLA_FLAGS"] = " ".join([flags, *extra]).strip()
    try:
        import jax  # noqa: PLC0415
        import jax.numpy as jnp  # noqa: PLC0415
    except ImportError as exc:
        raise ImportError(f"{who} needs jax, an optional extra: {INSTALL_HINT}") from exc
    if extra and _backend_started(jax):
        warnings.warn(f"{who}: JAX's backend started before sdrl_bench set XLA_FLAGS ({' '.join(extra)}); XLA reads "
                      "them once, so this process's compiled programs run without them (slower here, and their "
                      "numbers may differ by rounding from a run that starts jax through sdrl_bench). Set XLA_FLAGS "
                      "before the first jax computation, or import sdrl_bench's jax modules first", stacklevel=2)
    jax.config.update("jax_enable_x64", True)
    if MATMUL_PRECISION_VAR not in os.environ:  # the user's choice, where made, stands
        jax.config.update("jax_default_matmul_precision", "highest")
    # its backend probe logs a failed TPU/GPU lookup at INFO, which a Hydra run prints as noise
    logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)
    return jax, jnp


def _backend_started(jax: Any) -> bool:
    """Whether this process's JAX backends exist (XLA has read ``XLA_FLAGS``). Hand-written: jax
    has no public query for it; its private ``xla_bridge.backends_are_initialized`` (jax 0.10) is
    read if it is there, else the answer is no (nothing to warn of)."""
    try:
        from jax._src import xla_bridge  # noqa: PLC0415
    except ImportError:
        return False
    started = getattr(xla_bridge, "backends_are_initialized", None)
    return bool(started()) if callable(started) else False


def jax_namespace(jnp: Any) -> dict[str, Any]:
    """The names the generated source may call (``terms.SOURCE_NAMESPACE``), each bound to the
    jax.numpy function of the same name (``_sin``: ``math.sin`` -> ``jnp.sin``)."""
    out = {}
    for name, fn in SOURCE_NAMESPACE.items():
        jfn = getattr(jnp, fn.__name__, None)
        if jfn is None:
            raise NotImplementedError(f"term op function {name} ({fn.__name__}) has no jax.numpy counterpart")
        out[name] = jfn
    return out


def _compile(terms: Sequence[Term], coef: np.ndarray, n_inputs: int, namespace: dict[str, Any]) -> Callable:
    """``predict(columns) -> list of output columns``: the generated source of
    ``models.fast.scalar_source`` over columns (any array shape, elementwise), with jnp ops."""
    scope: dict[str, Any] = {"__builtins__": {}, **namespace}
    exec(compile(scalar_source(terms, coef, n_inputs), "<sindy-jax>", "exec"), scope)
    return scope["predict"]


def _check(model: Any, coef: Any) -> tuple[list[Term], np.ndarray, dict | None, int]:
    """The model's term table, coefficients (``coef`` or ``coef_``), stages and input count."""
    terms = getattr(model, "terms_", None)
    if terms is None or getattr(model, "coef_", None) is None:
        kind = getattr(model, "kind", None) or type(model).__name__
        raise TypeError(f"jax_predictor: a {kind!r} model ({type(model).__name__}) has no term table (terms_, coef_); "
                        "only the sparse models (kind 'sindy', 'per_equation') have a JAX evaluator")
    coef = np.asarray(model.coef_ if coef is None else coef, dtype=float)
    if coef.shape != (len(model.state_names_), len(terms)):
        raise ValueError(f"jax_predictor: coefficients of shape {coef.shape} for {len(model.state_names_)} states "
                         f"and {len(terms)} terms")
    n_inputs = len(model.state_names_) + len(model.control_names_)
    stages = getattr(model, "stages_", None) or None
    if stages is not None and stages["n_inputs"] != n_inputs:
        raise ValueError(f"jax_predictor: stages for {stages['n_inputs']} inputs, the model has {n_inputs}")
    return list(terms), coef, stages, n_inputs


def _layout(stages: dict | None, n_inputs: int, m: int) -> tuple[list[tuple[list[int], list[tuple]]], int]:
    """([(output rows, clips applied after them)] per stage, the column count they read): one
    stage of every row, or as ``models.fast._staged_batch``: each stage over the inputs and the
    bounded next values so far (clips: (row, column, low, high))."""
    if stages is None:
        return [(list(range(m)), [])], n_inputs
    n_ext = n_inputs + sum(len(st["clips"]) for st in stages["stages"])
    return [(list(st["rows"]), [(int(r), int(col), float(lo), float(hi)) for r, col, lo, hi in st["clips"]])
            for st in stages["stages"]], n_ext


def _run_stages(jnp: Any, z: Any, n_inputs: int, n_ext: int, m: int, parts: list, who: str) -> Any:
    """(..., m): the stages ``parts`` [(rows, clips, evaluate(cols) -> one value per row)] over
    inputs ``z`` (..., n_inputs), each stage's clipped outputs becoming columns the next reads."""
    z = jnp.asarray(z, dtype=jnp.float64)
    if z.ndim < 1 or z.shape[-1] != n_inputs:
        raise ValueError(f"{who}: inputs of shape {z.shape}, expected (..., {n_inputs})")
    cols = [z[..., j] for j in range(n_inputs)] + [jnp.zeros(z.shape[:-1], dtype=jnp.float64)] * (n_ext - n_inputs)
    out: list[Any] = [None] * m
    for rows, clips, evaluate in parts:
        for r, v in zip(rows, evaluate(cols), strict=True):
            out[r] = jnp.broadcast_to(jnp.asarray(v, dtype=jnp.float64), z.shape[:-1])  # a constant equation too
        for r, col, lo, hi in clips:
            cols[col] = jnp.clip(out[r], lo, hi)
    return jnp.stack(out, axis=-1)


def jax_predictor(model: Any, coef: Any = None) -> JaxPredict:
    """``f(z) -> (..., n_states)``: the model's prediction at inputs ``z`` (..., n_inputs), a
    pure jax.numpy function (jit-able, vmap-able, float64). ``coef``: evaluate these coefficients
    (an ensemble member's, ``members_[k]``) over the model's terms and stages instead of ``coef_``."""
    terms, coef, stages, n_inputs = _check(model, coef)
    _, jnp = jax_modules()
    namespace = jax_namespace(jnp)
    m = coef.shape[0]
    layout, n_ext = _layout(stages, n_inputs, m)
    parts = [(rows, clips, _compile(terms, coef[rows], n_ext, namespace)) for rows, clips in layout]
    return lambda z: _run_stages(jnp, z, n_inputs, n_ext, m, parts, "jax_predictor")


def is_network(model: Any) -> bool:
    """Whether ``model`` is a fitted NN model (``net_``: ``surrogate=nn`` or ``pe``), which
    ``jax_model`` evaluates through ``models.jax_nn``."""
    return getattr(model, "net_", None) is not None


def jax_model(model: Any, members: bool = False) -> JaxModel:
    """``model`` as a ``JaxModel``: a sparse model through ``linear_predictor`` (its coefficients,
    and its members' with ``members``, in ``params["coef"]`` and ``params["members"]``); an NN
    model (``net_``: ``surrogate=nn`` or ``pe``) through ``models.jax_nn.network_model``."""
    if is_network(model):
        from sdrl_bench.models.jax_nn import network_model  # noqa: PLC0415  (jax_nn imports this module)

        return network_model(model, members)
    jax, _ = jax_modules()
    lin, key, columns = linear_predictor(model)
    stacked = columns(model.members_) if members else None
    params = {"coef": columns(model.coef_), "members": stacked}
    spread = (lambda z, p: jax.vmap(lambda c: lin(z, c))(p["members"])) if members else None
    return JaxModel(lambda z, p: lin(z, p["coef"]), spread, None, params,
                    (key, None if stacked is None else stacked.shape))


def linear_predictor(model: Any) -> tuple[Callable, tuple, Callable]:
    """``(predict(z, coef) -> (..., n_states), key, columns)``: the model's prediction with its
    coefficients an *argument* (``coef`` (n_states, n_table), traced under ``jit``), so that a
    compiled program serves every model of the same structure: a Dyna refit, another seed's fit
    of the same library, or an ensemble member steps through it without compiling again.
    ``columns(c)`` puts coefficients (..., n_states, len(model.terms_)) (``coef_``, ``members_``)
    into the table's columns.

    The table: the model's ``candidate_structure()`` where it has one (every term its library
    can keep: a per-equation fit lists only the terms it kept, so keying on those, a refit that
    drops or regains one would compile again), else its own term table, put in one canonical
    order (a fit lists terms as it found them). Every term of the table is evaluated (the
    generated source of ``scalar_source`` over an identity matrix, per stage for a staged model
    as in ``jax_predictor``), and each output sums coefficient x term over the terms whose
    coefficient is not 0: a term the fit did not keep adds exactly 0, even where it is not
    finite, as in the numpy evaluators, which never compute it. ``key``: the structure (term
    table, stages, input count): models with equal keys share the compiled program, whatever
    their sparsity. Equal to ``jax_predictor`` to rounding (the terms are summed in another order)."""
    own, _, stages, n_inputs = _check(model, None)
    candidates = getattr(model, "candidate_structure", None)
    terms, stages = candidates() if callable(candidates) else (own, stages)
    terms = sorted(terms, key=repr)
    where = {repr(t): k for k, t in enumerate(terms)}
    missing = [t for t in own if repr(t) not in where]
    if missing:
        raise ValueError(f"linear_predictor: the model's candidate structure lacks {len(missing)} of its terms "
                         f"(first: {missing[0]!r})")
    index = np.array([where[repr(t)] for t in own], dtype=int)

    def columns(c: Any) -> np.ndarray:
        c = np.asarray(c, dtype=float)
        out = np.zeros((*c.shape[:-1], len(terms)))
        out[..., index] = c
        return out

    coef = columns(model.coef_)
    _, jnp = jax_modules()
    namespace = jax_namespace(jnp)
    m, n_terms = coef.shape
    layout, n_ext = _layout(stages, n_inputs, m)
    features = [(rows, clips, _compile(terms, np.eye(n_terms), n_ext, namespace)) for rows, clips in layout]

    def stage(fn, rows, c):
        def evaluate(cols):
            feats = jnp.stack([jnp.broadcast_to(jnp.asarray(v, dtype=jnp.float64), cols[0].shape) for v in fn(cols)],
                              axis=-1)[..., None, :]  # (..., 1, n_terms)
            cs = c[jnp.asarray(rows)]  # (len(rows), n_terms)
            vals = jnp.sum(jnp.where(cs != 0, cs * feats, 0.0), axis=-1)  # (..., len(rows))
            return [vals[..., i] for i in range(len(rows))]

        return evaluate

    def predict(z, c):
        c = jnp.asarray(c, dtype=jnp.float64)
        if c.shape != (m, n_terms):
            raise ValueError(f"linear_predictor: coefficients of shape {c.shape}, expected {(m, n_terms)}")
        parts = [(rows, clips, stage(fn, rows, c)) for rows, clips, fn in features]
        return _run_stages(jnp, z, n_inputs, n_ext, m, parts, "linear_predictor")

    return predict, (repr(terms), repr(stages), n_inputs, (m, n_terms)), columns
