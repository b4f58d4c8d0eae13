"""Terms: the one table of the operations a library feature is made of, in its three forms.

A *term* is a product of factors ``(input index, op, parameter)``; the empty product is the
constant term. ``op`` is one of ``OPS``:

=======  ======================  =============================================
op       value at input x        parameter
=======  ======================  =============================================
pow      x                       always 1 (a power x^2 is the factor repeated)
sin      sin(p x)                frequency p
cos      cos(p x)                frequency p
rat      1 / (1 + x^2)           unused (1)
xrat     x / (1 + x^2)           unused (1)
=======  ======================  =============================================

Each op is written here once, in the three forms the package evaluates it in:

- ``column(p, x)``: numpy, on a column of N inputs (the feature matrix of ``SindyModel``, the
  batch evaluator of a vectorized surrogate env);
- ``scalar(p, x)``: one Python float (folding fixed inputs into coefficients);
- ``source(p, x)``: the Python expression text the code generator of the one-state evaluator
  writes (``models.fast``), given the parameter as ``repr(float)`` text and a variable name;
  None for ``pow``, which is the variable itself.

The three must agree bit for bit on float64 (the tests check every op): the MountainCar
surrogate replays the real env exactly only because they do. Terms are plain data: a saved
model is JSON, never code; ``validate_terms`` checks terms read from a file.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

Factor = tuple[int, str, float]
Term = tuple[Factor, ...]


@dataclass(frozen=True)
class Op:
    """One factor operation: its numpy column, scalar and generated-source forms."""

    column: Callable[[float, np.ndarray], np.ndarray]
    scalar: Callable[[float, float], float]
    source: Callable[[str, str], str] | None


# p == 1.0 skips the product (1.0 * x == x exactly, so the values are the same either way).
TABLE: dict[str, Op] = {
    "pow": Op(
        column=lambda p, x: x,
        scalar=lambda p, x: x,
        source=None,
    ),
    "sin": Op(
        column=lambda p, x: np.sin(x if p == 1.0 else p * x),
        scalar=lambda p, x: math.sin(p * x),
        source=lambda p, x: f"_sin({p} * {x})",
    ),
    "cos": Op(
        column=lambda p, x: np.cos(x if p == 1.0 else p * x),
        scalar=lambda p, x: math.cos(p * x),
        source=lambda p, x: f"_cos({p} * {x})",
    ),
    "rat": Op(
        column=lambda p, x: 1.0 / (1.0 + x * x),
        scalar=lambda p, x: 1.0 / (1.0 + x * x),
        source=lambda p, x: f"1.0 / (1.0 + {x} * {x})",
    ),
    "xrat": Op(
        column=lambda p, x: x / (1.0 + x * x),
        scalar=lambda p, x: x / (1.0 + x * x),
        source=lambda p, x: f"{x} / (1.0 + {x} * {x})",
    ),
}
OPS = tuple(TABLE)
SOURCE_NAMESPACE = {"_sin": math.sin, "_cos": math.cos}
"""The names the generated source may call (and nothing else: no builtins)."""


def is_factor(f: object, n_inputs: int) -> bool:
    """A factor with an int input index in range, a known op and a finite number as parameter."""
    return (
        isinstance(f, (list, tuple)) and len(f) == 3
        and isinstance(f[0], (int, np.integer)) and 0 <= f[0] < n_inputs
        and f[1] in TABLE and isinstance(f[2], (int, float)) and bool(np.isfinite(f[2]))
    )


def validate_terms(terms: object, n_inputs: int) -> list[Term]:
    """Check terms read from a file: every factor (int index in range, known op, finite param)."""
    if not isinstance(terms, list):
        raise ValueError("terms must be a list")
    out = []
    for t in terms:
        if not isinstance(t, list):
            raise ValueError(f"term {t!r} must be a list of factors")
        for f in t:
            if not isinstance(f, list) or not is_factor(f, n_inputs):
                raise ValueError(f"bad factor {f!r} (want [input index, op in {OPS}, number])")
        out.append(tuple((int(f[0]), str(f[1]), float(f[2])) for f in t))
    return out


def term_column(term: Term, column_of: Callable[[int], np.ndarray], cache: dict[Factor, np.ndarray]) -> np.ndarray | None:
    """The values of ``term`` (None for the constant term), with input j's column ``column_of(j)``;
    each factor's column is computed once per ``cache``."""
    col = None
    for f in term:
        v = cache.get(f)
        if v is None:
            v = cache[f] = TABLE[f[1]].column(f[2], column_of(f[0]))
        col = v if col is None else col * v
    return col


def evaluate_terms(terms: Sequence[Term], z: np.ndarray) -> np.ndarray:
    """Feature matrix (N, len(terms)) of ``terms`` at inputs ``z`` (N, n_inputs)."""
    z = np.asarray(z, dtype=float)
    out = np.empty((z.shape[0], len(terms)))
    cache: dict[Factor, np.ndarray] = {}
    for k, term in enumerate(terms):
        col = term_column(term, lambda j: z[:, j], cache)
        out[:, k] = 1.0 if col is None else col
    return out


def scalar_factor(f: Factor, value: float) -> float:
    """Factor ``f`` at the input value ``value`` (a Python float)."""
    return TABLE[f[1]].scalar(f[2], value)
