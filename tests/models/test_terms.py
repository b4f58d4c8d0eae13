"""The term table: every op's numpy, scalar and generated-source forms agree bit for bit, and
terms read from a file are validated."""

from __future__ import annotations

import numpy as np
import pytest

from sdrl_bench.models.fast import compile_scalar
from sdrl_bench.models.terms import OPS, SOURCE_NAMESPACE, TABLE, evaluate_terms, validate_terms

VALUES = np.array([-3.7, -1.0, -0.25, 0.0, 1e-8, 0.3, 1.0, 2.5, 41.0])


CASES = [(op, 1.0) for op in OPS] + [(op, p) for op in ("sin", "cos") for p in (0.5, 3.0)]


@pytest.mark.parametrize("op,p", CASES)
def test_the_three_forms_of_every_op_agree_bit_for_bit(op, p):
    column = TABLE[op].column(p, VALUES)
    scalar = [TABLE[op].scalar(p, float(v)) for v in VALUES]
    source = TABLE[op].source
    expr = "z0" if source is None else source(repr(p), "z0")
    generated = [eval(expr, {"__builtins__": {}, **SOURCE_NAMESPACE}, {"z0": float(v)}) for v in VALUES]
    assert np.array_equal(column, scalar) and np.array_equal(column, generated)
    predict = compile_scalar([((0, op, p),)], np.array([[1.5]]), 1)  # through the code generator
    assert np.array_equal([predict([float(v)])[0] for v in VALUES], 1.5 * column)


def test_evaluate_terms_multiplies_factors_and_has_a_constant_term():
    z = np.array([[0.5, -2.0], [1.5, 3.0]])
    theta = evaluate_terms([(), ((0, "pow", 1.0), (1, "sin", 2.0)), ((1, "rat", 1.0),)], z)
    assert np.array_equal(theta[:, 0], [1.0, 1.0])
    assert np.array_equal(theta[:, 1], z[:, 0] * np.sin(2.0 * z[:, 1]))
    assert np.array_equal(theta[:, 2], 1.0 / (1.0 + z[:, 1] ** 2))


@pytest.mark.parametrize("terms", [
    "not a list", [[[0, "tan", 1.0]]], [[[2, "pow", 1.0]]], [[[-1, "pow", 1.0]]], [[[0.0, "pow", 1.0]]],
    [[[0, "sin", float("inf")]]], [[[0, "sin"]]], [(0, "pow", 1.0)], [[[0, "sin", "1"]]],
])
def test_bad_terms_from_a_file_are_rejected(terms):
    with pytest.raises(ValueError):
        validate_terms(terms, 2)


def test_valid_terms_from_a_file_become_tuples():
    assert validate_terms([[], [[1, "cos", 3]]], 2) == [(), ((1, "cos", 3.0),)]
