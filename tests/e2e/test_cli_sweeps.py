"""``sdrl-bench -m`` sweeps as a user runs them: real processes, a real SQLite store read back."""

from __future__ import annotations

import numpy as np
import pytest
from mlflow.tracking import MlflowClient

from helpers import run_cli, search
from sdrl_bench import tracking
from sdrl_bench.models.base import load_model
from sdrl_bench.report.compare import pair_fit_runs, surrogate_ratios


def test_six_job_multirun_lands_six_children_under_one_parent(store, tmp_path):
    res = run_cli("-m", "env=mountain_car,lunar_lander", "library=polynomial,poly_trig,rational",
                  f"tracking.uri={store}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    runs = search(store)
    parents = runs[runs["tags.sdrl.kind"] == "sweep"]
    children = runs[runs["tags.sdrl.kind"] == "fit"]
    assert len(parents) == 1 and len(children) == 6
    parent_id = parents.iloc[0]["run_id"]
    assert parents.iloc[0]["status"] == "FINISHED"
    assert set(children["tags.mlflow.parentRunId"]) == {parent_id}
    assert set(children["status"]) == {"FINISHED"}
    assert set(zip(children["tags.env"], children["tags.library"], strict=True)) == {
        (e, lib) for e in ("mountain_car", "lunar_lander") for lib in ("polynomial", "poly_trig", "rational")}
    # the UI's runs table cuts names short (about 18 characters): the children's differ in their first 18
    names = children["tags.mlflow.runName"].tolist()
    assert len({n[:18] for n in names}) == 6 and any(n.startswith("poly_trig lunar_lander ·") for n in names), names
    # every child has its per-state metrics
    assert children["metrics.mse/v"].notna().sum() == 3 and children["metrics.mse/vx"].notna().sum() == 3
    # LunarLander fits also record the surrogate's task fidelity on the held-out transitions
    ll = children[children["tags.env"] == "lunar_lander"]
    assert (ll["metrics.surrogate/leg_left_accuracy"] > 0.9).all()
    assert ll["metrics.surrogate/terminated_recall"].notna().all() and ll["metrics.surrogate/reward_mse"].notna().all()
    # on MountainCar, trigonometric terms win by orders of magnitude (the paper's ablation, in direction)
    mc = children[children["tags.env"] == "mountain_car"].set_index("tags.library")["metrics.mse/v"]
    assert mc["poly_trig"] * 1e6 < mc["polynomial"]



def test_a_sweep_job_refused_by_its_check_stops_the_sweep_before_it_starts(store, tmp_path):
    """What a job's own check finds (a collector the env has not) stops a -m sweep in its driver:
    one line, no parent run, no job run (before, the sweep started and its parent ended FAILED)."""
    res = run_cli("-m", "env=mountain_car,pendulum", f"tracking.uri={store}", cwd=tmp_path)
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == ["sdrl-bench: error: collector: env 'pendulum' has no heuristic policy "
                                               "(env.spec.heuristic_fn); use collector=random"]
    assert len(search(store)) == 0


def test_a_sweep_job_failing_once_its_run_exists_leaves_no_run_running(store, tmp_path):
    """A failure only the data show (every transition on a state bound, found after the run
    started): the job's run ends FAILED with its reason, the sweep's parent FAILED, none RUNNING."""
    import pandas as pd

    from sdrl_bench.data import collect, heuristic_policy, save_csv
    from sdrl_bench.envs.mountain_car import MountainCarSpec

    spec = MountainCarSpec()
    path = save_csv(collect(spec, heuristic_policy, 40, 0.2, 0), spec, tmp_path / "d.csv")
    df = pd.read_csv(path)
    df["ns_x"] = -1.2
    df.to_csv(path, index=False)
    res = run_cli("-m", "seed=0,1", f"dataset.path={path}", "library=trig", f"tracking.uri={store}", cwd=tmp_path)
    assert res.returncode != 0
    assert "every transition lies on a state bound" in res.stderr
    runs = search(store)
    assert "RUNNING" not in set(runs["status"])
    assert runs[runs["tags.sdrl.kind"] == "sweep"].iloc[0]["status"] == "FAILED"
    jobs = runs[runs["tags.sdrl.kind"] == "fit"]
    assert len(jobs) >= 1 and set(jobs["status"]) == {"FAILED"}



def test_sindy_nn_multirun_fits_both_on_identical_data(store, tmp_path):
    # one process runs both jobs (hydra.launcher.n_jobs=1: same launcher, no worker processes to
    # start); the parallel path is the six-job test's and the faults tests'
    res = run_cli("-m", "surrogate=sindy,nn", "hydra.launcher.n_jobs=1", f"tracking.uri={store}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    runs = tracking.find_runs(store, "sdrl-bench", missing_ok=False)
    children = [r for r in runs if r["tags"].get("sdrl.kind") == "fit"]
    assert sorted(r["tags"]["surrogate"] for r in children) == ["nn", "sindy"]
    assert {r["status"] for r in children} == {"FINISHED"}
    assert len({r["tags"]["dataset_sha256"] for r in children}) == 1
    assert len({r["tags"]["test_set_sha256"] for r in children}) == 1
    (sindy, nn), = pair_fit_runs(runs)
    assert nn["metrics"]["n_parameters"] == (3 * 64 + 64) + (64 * 2 + 2) and nn["metrics"]["nn_epochs_run"] > 0
    ratios = surrogate_ratios(sindy["metrics"], nn["metrics"])
    assert ratios["sindy_over_nn/mse/x"] < 1e-2 and ratios["sindy_over_nn/mse/v"] < 1e-2  # the 100x
    assert sindy["metrics"]["n_parameters"] == 7  # the exact law: 7 active terms vs 386 weights
    assert ratios["sindy_over_nn/n_parameters"] == pytest.approx(7 / 386)
    client = MlflowClient(store)
    listed = {a.path for a in client.list_artifacts(nn["run_id"], "model")}
    assert listed == {"model/model.json", "model/model.pt", "model/architecture.txt"}
    local = client.download_artifacts(nn["run_id"], "model", str(tmp_path / "dl"))
    model = load_model(f"{local}/model.json")
    assert model.predict(np.array([[-0.5, 0.0]]), np.array([[1.0]])).shape == (1, 2)
