"""Error and agreement statistics on arrays (pure functions, per column)."""

from __future__ import annotations

import numpy as np


def mse(y_true: np.ndarray, y_pred: np.ndarray) -> np.ndarray:
    """Mean squared error per column."""
    d = np.asarray(y_pred, dtype=float) - np.asarray(y_true, dtype=float)
    return np.mean(d * d, axis=0)


def pearson(y_true: np.ndarray, y_pred: np.ndarray) -> np.ndarray:
    """Pearson correlation per column (nan where either column is constant)."""
    a = np.asarray(y_true, dtype=float)
    b = np.asarray(y_pred, dtype=float)
    a = a - a.mean(axis=0)
    b = b - b.mean(axis=0)
    denom = np.sqrt(np.sum(a * a, axis=0) * np.sum(b * b, axis=0))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(denom > 0, np.sum(a * b, axis=0) / np.where(denom > 0, denom, 1), np.nan)


def r2(y_true: np.ndarray, y_pred: np.ndarray) -> np.ndarray:
    """Coefficient of determination per column, 1 - SSE / SST (nan for a constant column)."""
    y = np.asarray(y_true, dtype=float)
    sse = np.sum((np.asarray(y_pred, dtype=float) - y) ** 2, axis=0)
    sst = np.sum((y - y.mean(axis=0)) ** 2, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(sst > 0, 1.0 - sse / np.where(sst > 0, sst, 1), np.nan)


def spearman(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Spearman rank correlation per column (average ranks for ties; nan for a constant column)."""
    from scipy.stats import rankdata

    ra = rankdata(np.asarray(a, dtype=float), axis=0)
    rb = rankdata(np.asarray(b, dtype=float), axis=0)
    return pearson(ra, rb)
