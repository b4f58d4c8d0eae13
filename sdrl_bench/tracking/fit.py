"""Recording a fit: params and config, metrics, hashes, datasets, the saved and the logged model,
the equations as the description, per-state tables, figures."""

from __future__ import annotations

import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from sdrl_bench.tracking.client import Run, mlflow_client


def fit_metrics(result) -> dict[str, float]:
    """The metrics a fit run records (``result`` is a ``pipeline.FitResult``), with its real
    steps by purpose (``rl.accounting``: the model's data, the held-out set that judges it, the
    env's priors and a trained collector behind it)."""
    from sdrl_bench.rl.accounting import expert_of, headline

    model, data = result.model, result.data
    spec = result.spec  # with own_data, the priors its learned constants replaced are gone
    counts = {"model_data": len(data), "judge": len(result.test)}
    accounting = headline(counts, spec.declared_priors, [expert_of(result.job.policy, spec.name)],
                          tuning=result.job.tuning_real_steps)
    return {**accounting,
        **result.fidelity.metrics,
        "n_transitions": len(data),
        "n_fit_rows": result.n_fit_rows,
        "n_excluded_at_bound": len(data) - result.n_fit_rows,
        "n_episodes": len(set(data.episode.tolist())),
        "n_test_transitions": len(result.test),
        **model.summary_metrics(),
        **{f"{k}_seconds": v for k, v in result.seconds.items()},
    }


def log_fit(run: Run, result, params: Mapping[str, Any] | None = None, prefix: str = "", *,
            config: Mapping[str, Any] | None = None, task: str = "fit", model: bool = True, rows=None,
            accounting_prefix: str | None = None) -> None:
    """Record a fit: lean params and ``config.yaml`` (from ``config``, the resolved config as a
    plain dict; or ``params`` as given), metrics (unprefixed: the same names in fit and transfer
    runs), data and test-set hashes, the datasets (inputs with digests), the model (the saved
    ``model.json`` and an MLflow pyfunc model logged from code), the equations as the run's
    description, per-state fidelity as a table, and the predicted-vs-true figure. ``rows``: the
    transitions to store as the run's data (default: all of ``result.data``; a Dyna round
    stores the rows it added, so the rounds' files together are the model's data).
    ``accounting_prefix``: where the fit's real-step accounting goes, if not under ``prefix`` (a
    transfer run: ``fit/real_steps/...``, so that its only headlines are its arms')."""
    from sdrl_bench.data import save_csv
    from sdrl_bench.plots import predicted_vs_true
    from sdrl_bench.rl.accounting import PREFIXES
    from sdrl_bench.tracking.meta import describe_experiment, experiment_id_of, log_config, set_description
    from sdrl_bench.tracking.model import log_datasets, log_priors, log_surrogate_model

    spec, model_ = result.job.spec, result.model
    if config is not None:
        log_config(run, config, run.uri, task)
    elif params is not None:
        run.log_params(params)
    counted = prefix if accounting_prefix is None else accounting_prefix
    run.log_metrics({f"{counted if k.startswith(PREFIXES) else prefix}{k}": v for k, v in fit_metrics(result).items()})
    run.set_tags({"dataset_sha256": result.dataset_hash, "test_set": result.test_name, "test_set_sha256": result.test_hash,
                  "fit_regime": spec.fit_regime or "all"})
    if result.spec.task is not None:  # the surrogate's step noise and pessimism, or why it has none
        from sdrl_bench.surrogate.model_env import surrogate_settings

        run.set_tags(surrogate_settings(model_, result.spec))
    set_description(run, fit_description(result))
    with tempfile.TemporaryDirectory() as tmp:
        csv = save_csv(result.data if rows is None else rows, spec, Path(tmp) / f"{spec.name}_transitions.csv")
        run.log_artifact(csv, "data")
        run.log_artifact(f"{csv}.stats.json", "data")
        model_dir = Path(tmp) / "model"
        model_.save(model_dir / "model.json")
        for path in sorted(model_dir.iterdir()):
            run.log_artifact(path, "model")
    run.log_text(model_.describe(), f"model/{model_.summary_file}")
    log_datasets(run, result, f"data/{spec.name}_transitions.csv", rows)
    log_priors(run, result.spec.declared_priors)
    if result.learned:  # the constants learned from this fit's data (own_data), infinite ones included
        run.log_dict({k: (v if np.isfinite(v) else str(v)) for k, v in result.learned.items()}, "own_data/learned.json")
    if model:
        log_surrogate_model(run, result)
    _log_table(run, per_state_table(result), "fidelity/per_state.json")
    fig = predicted_vs_true(
        spec.target_names, result.fidelity.true_next, result.fidelity.pred_next,
        result.episode_true, result.episode_pred,
        title=f"{spec.name}: {result.test_name} (one step; episode 0 open loop)",
    )
    run.log_figure(fig, "figures/predicted_vs_true.png")
    if result.fidelity.pred_std is not None:
        run.log_text(uncertainty_table(result).to_csv(index=False), "fidelity/uncertainty.csv")
    for name, event_model in (result.events or {}).items():  # the learned event models, as plain numbers
        if event_model is not None:
            run.log_dict(event_model.to_dict(), f"events/{name}.json")
    describe_experiment(run.uri, experiment_id_of(run))


def _log_table(run: Run, df, artifact_file: str) -> None:
    """A DataFrame as an MLflow table (the UI's artifact view shows it; ``mlflow.load_table``
    reads it), its numbers at full precision: MLflow writes tables with 10 decimals (pandas'
    default), which prints 3.77e-15 as 0, so the file is then rewritten with round-trip floats
    in the same "split" layout."""
    import json

    mlflow_client(run.uri).log_table(run.run_id, df, artifact_file)  # the UI's table tag
    rows = [[None if isinstance(v, float) and v != v else (v.item() if hasattr(v, "item") else v) for v in row]
            for row in df.itertuples(index=False, name=None)]
    run.log_text(json.dumps({"columns": [str(c) for c in df.columns], "data": rows}), artifact_file)


def fit_description(result) -> str:
    """The run's description: what was fitted on what, the headline error, the equations."""
    job, m = result.job, result.fidelity.metrics
    names = job.names
    what = (f"SINDy ({names.get('library', '?')} library, {names.get('optimizer', '?')})" if job.surrogate == "sindy"
            else f"{job.surrogate.upper()} surrogate")
    head = (f"**{job.spec.name}**: {what} fitted on {len(result.data)} real transitions "
            f"({names.get('collector', '?')} collector, seed {job.seed}); held-out `{result.test_name}` "
            f"({len(result.test)} transitions): normalized one-step MSE {m.get('mse_norm/mean', float('nan')):.3g}.")
    return f"{head}\n\n```\n{result.model.describe().strip()}\n```\n"


def per_state_table(result):
    """One row per regressed state: one-step MSE (raw, normalized), correlation, R^2, k-step MSE."""
    import pandas as pd

    m = result.fidelity.metrics
    rows = []
    for n in result.job.spec.target_names:
        rows.append({"state": n, **{k: m.get(f"{k}/{n}", float("nan"))
                                    for k in ("mse", "mse_norm", "corr", "r2", "rollout10_mse", "rollout50_mse")}})
    return pd.DataFrame(rows)


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
