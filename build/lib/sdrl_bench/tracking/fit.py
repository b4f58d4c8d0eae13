"""Recording a fit: metrics, hashes, the dataset, the saved model, equations, figures."""

from __future__ import annotations

import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from sdrl_bench.tracking.client import Run


def fit_metrics(result) -> dict[str, float]:
    """The metrics a fit run records (``result`` is a ``pipeline.FitResult``)."""
    model, data = result.model, result.data
    return {
        **result.fidelity.metrics,
        "n_transitions": len(data),
        "n_fit_rows": result.n_fit_rows,
        "n_excluded_at_bound": len(data) - result.n_fit_rows,
        "n_episodes": len(set(data.episode.tolist())),
        "n_test_transitions": len(result.test),
        **model.summary_metrics(),
        **{f"{k}_seconds": v for k, v in result.seconds.items()},
    }


def log_fit(run: Run, result, params: Mapping[str, Any] | None, prefix: str = "") -> None:
    """Record a fit: params, metrics, data and test-set hashes, and the artifacts (dataset CSV
    with its normalization sidecar, the saved model, its equations or summary, the
    predicted-vs-true figure)."""
    from sdrl_bench.data import save_csv
    from sdrl_bench.plots import predicted_vs_true

    spec, model = result.job.spec, result.model
    if params is not None:
        run.log_params(params)
    run.log_metrics({f"{prefix}{k}": v for k, v in fit_metrics(result).items()})
    run.set_tags(
        {"dataset_sha256": result.dataset_hash, "test_set": result.test_name, "test_set_sha256": result.test_hash}
    )
    with tempfile.TemporaryDirectory() as tmp:
        csv = save_csv(result.data, spec, Path(tmp) / f"{spec.name}_transitions.csv")
        run.log_artifact(csv, "data")
        run.log_artifact(f"{csv}.stats.json", "data")
        model_dir = Path(tmp) / "model"
        model.save(model_dir / "model.json")
        for path in sorted(model_dir.iterdir()):
            run.log_artifact(path, "model")
    run.log_text(model.describe(), f"model/{model.summary_file}")
    fig = predicted_vs_true(
        spec.target_names, result.fidelity.true_next, result.fidelity.pred_next,
        result.episode_true, result.episode_pred,
        title=f"{spec.name}: {result.test_name} (one step; episode 0 open loop)",
    )
    run.log_figure(fig, "figures/predicted_vs_true.png")
    if result.fidelity.pred_std is not None:
        run.log_text(uncertainty_table(result).to_csv(index=False), "fidelity/uncertainty.csv")


def uncertainty_table(result):
    """Per held-out transition: episode, step, and per regressed state the true and predicted
    next value, the absolute error and the model's predicted std (an ensemble's spread)."""
    import pandas as pd

    rep, test, names = result.fidelity, result.test, result.job.spec.target_names
    cols = {"episode": test.episode, "step": test.step}
    for i, n in enumerate(names):
        cols[f"{n}_true"] = rep.true_next[:, i]
        cols[f"{n}_pred"] = rep.pred_next[:, i]
        cols[f"{n}_abs_err"] = abs(rep.pred_next[:, i] - rep.true_next[:, i])
        cols[f"{n}_std"] = rep.pred_std[:, i]
    return pd.DataFrame(cols)
