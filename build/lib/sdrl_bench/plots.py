"""Figures built from arrays (no tracking here): they return matplotlib figures."""

from __future__ import annotations

from matplotlib.figure import Figure
import numpy as np  # noqa: E402


def predicted_vs_true(
    names: tuple[str, ...],
    true_next: np.ndarray,
    pred_next: np.ndarray,
    episode_true: np.ndarray,
    episode_pred: np.ndarray,
    title: str,
) -> Figure:
    """Top row: one-step predicted vs true next state on the test set. Bottom row: one test
    episode, open loop from its first state with its recorded actions."""
    n = len(names)
    fig = Figure(figsize=(3.2 * n, 6.0))
    axes = fig.subplots(2, n, squeeze=False)
    for i, name in enumerate(names):
        ax = axes[0, i]
        t, p = true_next[:, i], pred_next[:, i]
        ax.scatter(t, p, s=4, alpha=0.5)
        ok = np.isfinite(p)
        lo, hi = np.nanmin(t), np.nanmax(t)
        ax.plot([lo, hi], [lo, hi], "k--", lw=0.8)
        ax.set_title(f"{name}: one step")
        ax.set_xlabel("true")
        ax.set_ylabel("predicted")
        if ok.any():
            ax.set_ylim(*_pad(min(lo, np.min(p[ok])), max(hi, np.max(p[ok]))))
        ax = axes[1, i]
        ax.plot(episode_true[:, i], label="real env", lw=1.5)
        ax.plot(episode_pred[:, i], "--", label="model, open loop", lw=1.2)
        ax.set_title(f"{name}: one episode")
        ax.set_xlabel("step")
        if i == 0:
            ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def _pad(lo: float, hi: float) -> tuple[float, float]:
    span = hi - lo if hi > lo else 1.0
    return lo - 0.05 * span, hi + 0.05 * span


def learning_curves(curves: dict[str, tuple[list, list, list]], threshold: float | None, title: str,
                    x_label: str = "training steps (in the env the agent trains in)") -> Figure:
    """Real-env return (mean +- std over evaluation episodes) against training steps, per arm."""
    fig = Figure(figsize=(7, 4))
    ax = fig.subplots()
    for arm, (steps, means, stds) in curves.items():
        steps, means, stds = map(np.asarray, (steps, means, stds))
        ax.plot(steps, means, label=arm)
        ax.fill_between(steps, means - stds, means + stds, alpha=0.2)
    if threshold is not None:
        ax.axhline(threshold, color="k", ls="--", lw=0.8, label=f"solved ({threshold:g})")
    ax.set_xlabel(x_label)
    ax.set_ylabel("return in the real env")
    ax.set_title(title)
    ax.legend()
    fig.tight_layout()
    return fig
