"""End to end into a real SQLite MLflow store, read back through the MLflow client."""

from __future__ import annotations

import json

import numpy as np
import pytest
from mlflow.tracking import MlflowClient

from helpers import compose_cfg, search
from sdrl_bench.cli.main import run_fit
from sdrl_bench.data import load_csv
from sdrl_bench.envs.mountain_car import MountainCarSpec
from sdrl_bench.models.sindy import SindyModel


def test_fit_run_lands_in_the_store_with_metrics_params_tags_and_artifacts(store, tmp_path):
    result = run_fit(compose_cfg(f"tracking.uri={store}", "seed=2"))
    runs = search(store)
    assert len(runs) == 1
    run = runs.iloc[0]
    assert run["status"] == "FINISHED"
    m = result.fidelity.metrics
    for key in ("mse/x", "mse/v", "corr/v", "r2/x", "rollout10_mse/v", "rollout50/diverged_fraction", "mse_norm/v"):
        assert run[f"metrics.{key}"] == pytest.approx(m[key], rel=1e-12, abs=1e-300)
    assert run["metrics.n_transitions"] == 75
    assert run["metrics.n_active_terms"] == 7
    assert run["metrics.fit_wall_seconds"] > 0 and run["metrics.fit_cpu_seconds"] >= 0
    assert run["params.library.name"] == "poly_trig" and run["params.seed"] == "2"
    assert run["params.optimizer.threshold"] == "0.003"
    for tag, value in {"env": "mountain_car", "library": "poly_trig", "optimizer": "stlsq",
                       "surrogate": "sindy", "collector": "heuristic", "test_set": "mountain_car-heldout-v1",
                       "dataset_sha256": result.dataset_hash}.items():
        assert run[f"tags.{tag}"] == value
    assert len(run["tags.git_commit"]) in (7, 40) or run["tags.git_commit"] == "unknown"

    client = MlflowClient(store)
    run_id = run["run_id"]
    listed = {a.path for d in ("data", "model", "figures") for a in client.list_artifacts(run_id, d)}
    assert listed == {"data/mountain_car_transitions.csv", "data/mountain_car_transitions.csv.stats.json",
                      "model/model.json", "model/equations.txt", "figures/predicted_vs_true.png"}
    local = tmp_path / "dl"
    model_path = client.download_artifacts(run_id, "model/model.json", str(local))
    model = SindyModel.load(model_path)
    x = np.array([[-0.5, 0.01], [0.3, -0.02]])
    u = np.array([[1.0], [-0.3]])
    assert np.array_equal(model.predict(x, u), result.model.predict(x, u))
    csv = client.download_artifacts(run_id, "data/mountain_car_transitions.csv", str(local))
    data = load_csv(MountainCarSpec(), csv)
    assert data.content_hash() == result.dataset_hash
    stats_path = client.download_artifacts(run_id, "data/mountain_car_transitions.csv.stats.json", str(local))
    stats = json.loads(open(stats_path).read())
    assert stats["sha256"] == result.dataset_hash and set(stats["normalization"]) == {"x", "v"}
    eq = open(client.download_artifacts(run_id, "model/equations.txt", str(local))).read()
    assert "cos(3 x)" in eq and eq.count("\n") == 2


def test_the_sqlite_store_is_put_in_wal_mode_and_stays_readable(store, tmp_path):
    """ensure_experiment switches a new store to write-ahead logging (kept in the file); runs
    written then read back through MLflow, and a second call leaves the mode alone."""
    import sqlite3

    from sdrl_bench import tracking

    db = tracking.sqlite_path(store)
    tracking.ensure_experiment(store, "sdrl-bench")
    with sqlite3.connect(db) as con:
        assert con.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    with tracking.start_run(store, "sdrl-bench", "r", {"k": "v"}) as run:
        run.log_metrics({"m": 1.5})
    runs = search(store)
    assert runs["metrics.m"].tolist() == [1.5] and runs["status"].tolist() == ["FINISHED"]
    assert tracking.use_wal(db) is True
