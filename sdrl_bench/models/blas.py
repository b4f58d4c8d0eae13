"""Matrix products in blocks small enough that OpenBLAS runs each on one thread.

A tall, skinny product (16384 x 15 times 15 x 6) is handed to every BLAS thread; on a 2-core
machine that is busy with anything else it measured 2-17 ms instead of 0.1-0.4 ms. Blocks of at
most ``BLOCK_FLOPS`` multiply-adds stay single-threaded and cost the same. Used by
``SindyModel.predict`` (row blocks) and the batch evaluator of ``models.fast`` (column blocks).
"""

from __future__ import annotations

import numpy as np

BLOCK_FLOPS = 1 << 17


def matmul_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` in row blocks of ``a``."""
    rows = max(1, BLOCK_FLOPS // max(1, a.shape[1] * b.shape[1]))
    if len(a) <= rows:
        return a @ b
    out = np.empty((len(a), b.shape[1]))
    for i in range(0, len(a), rows):
        np.matmul(a[i : i + rows], b, out=out[i : i + rows])
    return out


def matmul_cols(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """``out += a @ b`` in column blocks of ``b``."""
    block = max(1, BLOCK_FLOPS // max(1, a.size))
    for i in range(0, b.shape[1], block):
        out[:, i : i + block] += a @ b[:, i : i + block]
