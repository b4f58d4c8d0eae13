"""Figures of a study: optimization history, parameter importance, Pareto front (matplotlib).

Each function takes plain data (or a study for importances) and returns a Figure; the caller
logs it through ``tracking``.
"""

from __future__ import annotations

from typing import Any
from collections.abc import Sequence

import numpy as np
from matplotlib.figure import Figure


def history_figure(numbers: Sequence[int], errors: Sequence[float], title: str) -> Any:
    """Held-out error of every completed trial by trial number, and the best so far."""
    fig = Figure(figsize=(6.4, 3.6), layout="constrained")
    ax = fig.subplots()
    order = np.argsort(numbers)
    n, e = np.asarray(numbers)[order], np.asarray(errors, dtype=float)[order]
    ax.scatter(n, e, s=12, alpha=0.6, label="trial")
    if len(e):
        ax.step(n, np.minimum.accumulate(e), where="post", color="C3", label="best so far")
    ax.set_yscale("log")
    ax.set_xlabel("trial number")
    ax.set_ylabel("held-out error (normalized)")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    return fig


def importance_figure(importances: dict[str, float], title: str) -> Any:
    """Horizontal bars of parameter importances (fractions summing to one)."""
    fig = Figure(figsize=(5.0, 0.5 + 0.45 * max(1, len(importances))), layout="constrained")
    ax = fig.subplots()
    names = list(importances)[::-1]
    ax.barh(names, [importances[k] for k in names], color="C0")
    ax.set_xlabel("importance for the held-out error")
    ax.set_xlim(0, 1)
    ax.set_title(title, fontsize=9)
    return fig


def pareto_figure(
    errors: Sequence[float], n_terms: Sequence[int], front: Sequence[bool], title: str
) -> Any:
    """Error against number of active terms for every completed trial, front highlighted."""
    fig = Figure(figsize=(6.0, 4.0), layout="constrained")
    ax = fig.subplots()
    e, k, f = np.asarray(errors, float), np.asarray(n_terms, float), np.asarray(front, bool)
    ax.scatter(k[~f], e[~f], s=12, alpha=0.4, color="0.5", label="dominated")
    order = np.argsort(k[f])
    ax.plot(k[f][order], e[f][order], "o-", color="C3", ms=5, drawstyle="steps-post", label="Pareto front")
    ax.set_yscale("log")
    ax.set_xlabel("active terms (sum over equations)")
    ax.set_ylabel("held-out error (normalized)")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    return fig


def refinement_figure(labels: Sequence[str], errors: Sequence[float], accepted: Sequence[bool], title: str) -> Any:
    """Held-out error of each library tried during refinement, accepted stages highlighted."""
    fig = Figure(figsize=(6.0, 3.4), layout="constrained")
    ax = fig.subplots()
    colors = ["C2" if a else "0.6" for a in accepted]
    ax.bar(range(len(labels)), errors, color=colors)
    ax.set_xticks(range(len(labels)), labels, rotation=20, ha="right", fontsize=8)
    ax.set_yscale("log")
    ax.set_ylabel("held-out error (normalized)")
    ax.set_title(title, fontsize=9)
    return fig
