"""Fast evaluators of a SINDy model for surrogate stepping: one state, or columns of states.

These are why the project compiles models by hand: pysindy's ``predict`` costs about a
millisecond a call, more than a hundred real MountainCar steps; a surrogate slower than the env
it replaces defeats its purpose. Both evaluators take every op from the one term table
(``models.terms``): its numpy column form for columns, its source form for one state.

**One state** (``scalar_predictor``). ``SindyModel.predict`` is batched numpy: its per-call
overhead (array creation, a loop over terms, a matrix product) is several microseconds, more
than a whole step of the real MountainCar env. A single surrogate env steps one state at a
time, so the model's structured terms and coefficients are turned into the source of a small
Python function of scalars::

    def predict(z):
        z0, z1, z2, = z
        f0 = _cos(3.0 * z0)
        o1 = z1 + (0.0015 * z2 + -0.0025 * f0)
        o0 = z0 + o1
        return [o0, o1]

An equation whose own state enters with coefficient exactly 1 is evaluated in increment form,
``s + (the other terms)``, the way a simulator writes its update; one whose other terms are
exactly another equation (x' = x + v': semi-implicit Euler, as MountainCar's exact law has it)
reuses that equation's result (``integrates_from`` finds these pairs). The function uses no
type of its own: given the numpy scalars a real env keeps, numpy's promotion rules make it
compute in that env's arithmetic (float32 for MountainCar), which lets the MountainCar
surrogate replay the real env bit for bit.

The source is generated only from validated data: input indices (ints), op names from the term
table (``terms.TABLE``, whose ``source`` forms are the only expressions written), and
coefficients / parameters written with ``repr(float)`` (finite numbers only), so nothing from a
model file reaches ``exec`` as text. Results agree with ``SindyModel.predict``
to rounding (the sums run in a different order); the tests check this.

**Columns** (``batch_predictor``). A vectorized env holds N states; its per-variable columns
are contiguous (structure of arrays), so features are computed column by column into a
(terms, N) matrix and multiplied from the left by the active coefficients, in column blocks
that keep OpenBLAS single-threaded (``models.blas``). The result is (N, outputs)
in Fortran order: each output variable is again a contiguous column.
"""

from __future__ import annotations

import math
from typing import Any
from collections.abc import Callable, Sequence

import numpy as np

from sdrl_bench.models.blas import matmul_cols
from sdrl_bench.models.terms import SOURCE_NAMESPACE, TABLE, Factor, Term, is_factor, scalar_factor

ScalarPredict = Callable[[Sequence[float]], list[float]]


def _number(value: Any) -> str:
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"non-finite number {value!r} in a model")
    return repr(v)


def partial_terms(
    terms: Sequence[Term], coef: np.ndarray, fixed: dict[int, float]
) -> tuple[list[Term], np.ndarray]:
    """Terms and coefficients with the inputs in ``fixed`` replaced by their values: factors of
    fixed inputs fold into the coefficients, and terms left identical are merged (e.g. the
    one-hot action terms of a discrete action become part of the constant term)."""
    merged: dict[Term, np.ndarray] = {}
    coef = np.asarray(coef, dtype=float)
    for k, term in enumerate(terms):
        scale, rest = 1.0, []
        for f in term:
            if f[0] in fixed:
                scale *= scalar_factor(f, float(fixed[f[0]]))
            else:
                rest.append(f)
        key = tuple(rest)
        merged[key] = merged.get(key, 0.0) + scale * coef[:, k]
    return list(merged), np.stack(list(merged.values()), axis=1)


def scalar_source(terms: Sequence[Term], coef: np.ndarray, n_inputs: int, fixed: Sequence[int] = (),
                  chains: dict[int, int] | None = None) -> str:
    """Source of ``predict(z) -> list`` for ``coef @ [term(z) for term in terms]``; ``z`` holds
    the inputs not in ``fixed``, in index order (terms must not use the ``fixed`` inputs).
    ``chains``: ``integrates_from(terms, coef)``, if the caller has it already."""
    coef = np.asarray(coef, dtype=float)
    if coef.ndim != 2 or coef.shape[1] != len(terms):
        raise ValueError(f"coefficients of shape {coef.shape} for {len(terms)} terms")
    if not isinstance(n_inputs, int) or n_inputs <= 0:
        raise ValueError(f"n_inputs must be a positive int, got {n_inputs!r}")
    names = [f"z{i}" for i in range(n_inputs)]
    free = [names[i] for i in range(n_inputs) if i not in set(fixed)]
    lines = ["def predict(z):", f"    {', '.join(free)}, = z"]
    factors: dict[Factor, str] = {}

    def factor(f: Factor) -> str:
        if not is_factor(f, n_inputs) or f[0] in fixed:
            raise ValueError(f"bad term factor {f!r}")
        j, op, p = int(f[0]), str(f[1]), f[2]
        source = TABLE[op].source
        if source is None:  # pow: the input itself
            return names[j]
        key = (j, op, float(p))
        if key not in factors:
            factors[key] = f"f{len(factors)}"
            lines.append(f"    {factors[key]} = {source(_number(p), names[j])}")
        return factors[key]

    active = [k for k in range(len(terms)) if np.any(coef[:, k] != 0)]
    term_expr: dict[int, str | None] = {}
    for k in active:
        parts = [factor(f) for f in terms[k]]
        if not parts:
            term_expr[k] = None  # the constant term
        elif len(parts) == 1:
            term_expr[k] = parts[0]
        else:
            term_expr[k] = f"t{k}"
            lines.append(f"    t{k} = {' * '.join(parts)}")

    def total(row: np.ndarray) -> str:
        summands = [
            _number(row[k]) if term_expr[k] is None else f"{_number(row[k])} * {term_expr[k]}"
            for k in active
            if row[k] != 0
        ]
        return " + ".join(summands) if summands else "0.0"

    chains = integrates_from(terms, coef) if chains is None else chains
    for i in _evaluation_order(len(coef), chains):
        own = _identity_term(terms, i)
        if i in chains:
            expr = f"{names[i]} + o{chains[i]}"
        elif own is not None and coef[i, own] == 1.0 and np.count_nonzero(coef[i]) > 1:
            rest = coef[i].copy()
            rest[own] = 0.0
            expr = f"{names[i]} + ({total(rest)})"
        else:
            expr = total(coef[i])
        lines.append(f"    o{i} = {expr}")
    lines.append(f"    return [{', '.join(f'o{i}' for i in range(len(coef)))}]")
    return "\n".join(lines) + "\n"


def _identity_term(terms: Sequence[Term], i: int) -> int | None:
    """Index of the term that is input ``i`` itself (the state's own value), if any."""
    for k, term in enumerate(terms):
        if len(term) == 1 and term[0][0] == i and term[0][1] == "pow":
            return k
    return None


def integrates_from(terms: Sequence[Term], coef: np.ndarray) -> dict[int, int]:
    """{i: j} for every equation i that reads s_i' = s_i + s_j' exactly: its own state with
    coefficient 1 plus precisely the terms and coefficients of equation j (semi-implicit Euler:
    a position moved by the *new* velocity). Equation i is input i (states come first)."""
    coef = np.asarray(coef, dtype=float)
    out: dict[int, int] = {}
    for i in range(len(coef)):
        own = _identity_term(terms, i)
        if own is None or coef[i, own] != 1.0:
            continue
        rest = coef[i].copy()
        rest[own] = 0.0
        for j in range(len(coef)):
            if j != i and np.any(rest != 0) and np.array_equal(rest, coef[j]):
                out[i] = j
                break
    return out


def _evaluation_order(n: int, chains: dict[int, int]) -> list[int]:
    """Equations in an order that computes each chained equation's source first."""
    order: list[int] = []

    def visit(i: int) -> None:
        if i not in order:
            if i in chains:
                visit(chains[i])
            order.append(i)

    for i in range(n):
        visit(i)
    return order


def compile_scalar(
    terms: Sequence[Term], coef: np.ndarray, n_inputs: int, fixed: dict[int, float] | None = None
) -> ScalarPredict:
    """A function of one input vector -> list of outputs. With ``fixed`` ({input index: value}),
    the function takes only the other inputs, in index order, and is specialised to the values.
    Its ``integrates`` attribute holds ``integrates_from``'s pairs."""
    if fixed:
        terms, coef = partial_terms(terms, coef, fixed)
    chains = integrates_from(terms, coef)
    namespace: dict[str, Any] = {"__builtins__": {}, **SOURCE_NAMESPACE}
    source = scalar_source(terms, coef, n_inputs, tuple(fixed or ()), chains)
    exec(compile(source, "<sindy-scalar>", "exec"), namespace)
    predict = namespace["predict"]
    if np.max(np.abs(coef), initial=0.0) > _QUIET_ABOVE:
        predict = _quiet(predict)
    predict.integrates = chains
    return predict


# Inputs of a surrogate step are bounded (clipped states, clipped actions), so float32 arithmetic
# on numpy scalars can overflow only through absurd coefficients; such a model's evaluator runs
# with numpy's floating-point warnings off (its inf / NaN end the episode in the divergence guard).
_QUIET_ABOVE = 1e30


def _quiet(predict: ScalarPredict) -> ScalarPredict:
    def quiet(z: Sequence[float]) -> list:
        with np.errstate(all="ignore"):
            return predict(z)

    return quiet


def scalar_predictor(model: Any, fixed: dict[int, float] | None = None) -> ScalarPredict:
    """The fastest one-state evaluator available for ``model`` (inputs: the model's states,
    then its controls, less the ``fixed`` ones).

    A model with structured terms (``terms_``, ``coef_``: SINDy) gets a generated function; any
    other model with a batched ``predict(x, u)`` is wrapped (correct, not fast).
    """
    n_states, n_inputs = len(model.state_names_), len(model.state_names_) + len(model.control_names_)
    terms, coef = getattr(model, "terms_", None), getattr(model, "coef_", None)
    if terms is not None and coef is not None and getattr(model, "stages_", None):
        return _staged_scalar(terms, np.asarray(coef, dtype=float), model.stages_, fixed)
    if terms is not None and coef is not None:
        return compile_scalar(terms, coef, n_inputs, fixed)
    fixed = dict(fixed or {})
    free = [i for i in range(n_inputs) if i not in fixed]

    def predict(z: Sequence[float]) -> list[float]:
        row = np.empty((1, n_inputs))
        row[0, free] = z
        for i, v in fixed.items():
            row[0, i] = v
        return np.asarray(model.predict(row[:, :n_states], row[:, n_states:]))[0].tolist()

    return predict


def _staged_scalar(terms: Sequence[Term], coef: np.ndarray, stages: dict, fixed: dict[int, float] | None) -> ScalarPredict:
    """A staged model (a per-equation model whose primed terms read bounded next values,
    ``PerEquationModel.stages_``) for one state: each stage a generated function over the
    inputs and the bounded next values computed so far."""
    n, parts = stages["n_inputs"], []
    n_ext = n + sum(len(st["clips"]) for st in stages["stages"])
    for st in stages["stages"]:
        parts.append((st["rows"], compile_scalar(terms, coef[st["rows"]], n_ext), st["clips"]))
    fixed = dict(fixed or {})
    free = [i for i in range(n) if i not in fixed]
    m = coef.shape[0]

    def predict(z: Sequence[float]) -> list:
        ext = [0.0] * n_ext
        for i, v in zip(free, z, strict=True):
            ext[i] = v
        for i, v in fixed.items():
            ext[i] = v
        out = [0.0] * m
        for rows, fn, clips in parts:
            for r, v in zip(rows, fn(ext), strict=True):
                out[r] = v
            for r, col, lo, hi in clips:
                v = out[r]
                ext[col] = lo if v < lo else (hi if v > hi else v)
        return out

    return predict


BatchPredict = Callable[[np.ndarray], np.ndarray]


def batch_predictor(model: Any) -> BatchPredict:
    """``predict(z) -> (n_outputs, N)`` for inputs ``z`` of shape (n_inputs, N): the model's
    inputs (states, then controls) as rows. Constant and linear terms are one product with ``z``;
    only the other terms are computed as feature rows. Models without structured terms are
    wrapped around their ``predict(x, u)``; a staged model (``stages_``) runs stage by stage."""
    n_states = len(model.state_names_)
    n_inputs = n_states + len(model.control_names_)
    terms, coef = getattr(model, "terms_", None), getattr(model, "coef_", None)
    if terms is None or coef is None:
        return lambda z: np.asarray(model.predict(z[:n_states].T, z[n_states:].T)).T
    coef = np.asarray(coef, dtype=float)
    stages = getattr(model, "stages_", None)
    if stages:
        return _staged_batch(terms, coef, stages)
    return _batch(terms, coef, n_inputs)


def _staged_batch(terms: Sequence[Term], coef: np.ndarray, stages: dict) -> BatchPredict:
    n = stages["n_inputs"]
    n_ext = n + sum(len(st["clips"]) for st in stages["stages"])
    parts = [(st["rows"], _batch(terms, coef[st["rows"]], n_ext), st["clips"]) for st in stages["stages"]]

    def predict(z: np.ndarray) -> np.ndarray:
        ext = np.zeros((n_ext, z.shape[1]))
        ext[:n] = z
        out = np.empty((coef.shape[0], z.shape[1]))
        for rows, fn, clips in parts:
            out[rows] = fn(ext)
            for r, col, lo, hi in clips:
                np.clip(out[r], lo, hi, out=ext[col])
        return out

    return predict


def _batch(terms: Sequence[Term], coef: np.ndarray, n_inputs: int) -> BatchPredict:
    bias = np.zeros((coef.shape[0], 1))
    linear = np.zeros((coef.shape[0], n_inputs))
    other: list[int] = []
    for k, term in enumerate(terms):
        if not np.any(coef[:, k] != 0):
            continue
        if not term:
            bias[:, 0] += coef[:, k]
        elif len(term) == 1 and term[0][1] == "pow":
            linear[:, term[0][0]] += coef[:, k]
        else:
            other.append(k)
    used = np.flatnonzero(np.any(linear != 0, axis=0))
    linear = np.ascontiguousarray(linear[:, used])
    nl_coef = np.ascontiguousarray(coef[:, other])
    # Each nonlinear term as its factors, the op's column function looked up once, here.
    plan = [tuple((f, f[0], TABLE[f[1]].column, f[2]) for f in terms[k]) for k in other]

    def predict(z: np.ndarray) -> np.ndarray:
        out = np.empty((coef.shape[0], z.shape[1]))
        out[:] = bias
        if len(used):
            matmul_cols(linear, z[used] if len(used) < len(z) else z, out)
        if plan:  # terms.term_column's loop, inlined: this runs at every step of a vectorized env
            theta = np.empty((len(plan), z.shape[1]))
            cache: dict[Factor, np.ndarray] = {}
            for r, factors in enumerate(plan):
                col = None
                for f, j, column, p in factors:
                    v = cache.get(f)
                    if v is None:
                        v = cache[f] = column(p, z[j])
                    col = v if col is None else col * v
                theta[r] = col
            matmul_cols(nl_coef, theta, out)
        return out

    return predict
