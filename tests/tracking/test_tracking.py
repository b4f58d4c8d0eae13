"""End to end into a real SQLite MLflow store, read back through the MLflow client."""

from __future__ import annotations

import json
import os

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
    # the machine's CPU and its vector extensions (seeds repeat bit for bit only on machines alike in these)
    cpuinfo = open("/proc/cpuinfo").read().splitlines()
    name = next(x.split(":", 1)[1].strip() for x in cpuinfo if x.startswith("model name"))
    flags = next(x.split(":", 1)[1].split() for x in cpuinfo if x.startswith("flags"))
    assert run["tags.sdrl.cpu"].startswith(name)
    assert ("family" in run["tags.sdrl.cpu"]) == any(x.startswith("cpu family") for x in cpuinfo)
    vectors = run["tags.sdrl.cpu_vectors"].split()
    assert vectors and all(v in flags for v in vectors)
    assert ("avx2" in vectors) == ("avx2" in flags) and ("avx512f" in vectors) == ("avx512f" in flags)

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


def test_the_sqlite_store_is_put_in_wal_mode_and_stays_readable(new_store, tmp_path):
    """ensure_experiment switches a new store to write-ahead logging (kept in the file); runs
    written then read back through MLflow, and a second call leaves the mode alone."""
    import sqlite3

    from sdrl_bench import tracking

    store = new_store
    db = tracking.sqlite_path(store)
    assert not db.exists()
    tracking.ensure_experiment(store, "sdrl-bench")
    with sqlite3.connect(db) as con:
        assert con.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    with tracking.start_run(store, "sdrl-bench", "r", {"k": "v"}) as run:
        run.log_metrics({"m": 1.5})
    runs = search(store)
    assert runs["metrics.m"].tolist() == [1.5] and runs["status"].tolist() == ["FINISHED"]
    assert tracking.use_wal(db) is True


def _sig4(x: float) -> str:
    return f"{x:.3e}"


def test_no_shown_metric_differs_from_the_logged_one_in_its_first_4_significant_digits(store, tmp_path):
    """The exact MountainCar law's errors are ~1e-17: the per-state table artifact (the UI's
    table view) and the report's fidelity cells (one seed: the run's own values) show every
    metric as logged, to at least 4 significant digits (MLflow's own table writer rounds to 10
    decimals, which shows 3.77e-15 as 0)."""
    import re

    from sdrl_bench import tracking
    from sdrl_bench.report import tables as rt
    from sdrl_bench.report.build import Linker, table_blocks
    from sdrl_bench.report.render import render_markdown

    run_fit(compose_cfg(f"tracking.uri={store}", "seed=0"))
    row = search(store).iloc[0]
    logged = {k[len("metrics."):]: v for k, v in row.items() if k.startswith("metrics.")}
    assert logged["rollout50_mse/x"] < 1e-12  # the case that used to print as 0
    import pandas as pd

    client = MlflowClient(store)
    path = client.download_artifacts(row["run_id"], "fidelity/per_state.json", str(tmp_path))
    split = json.loads(open(path).read())
    table = pd.DataFrame(split["data"], columns=split["columns"])
    tagged = json.loads(client.get_run(row["run_id"]).data.tags["mlflow.loggedArtifacts"])
    assert {"path": "fidelity/per_state.json", "type": "table"} in tagged  # the UI shows it as a table
    for _, r in table.iterrows():
        for k in ("mse", "mse_norm", "corr", "r2", "rollout10_mse", "rollout50_mse"):
            assert _sig4(r[k]) == _sig4(logged[f"{k}/{r['state']}"]), (k, r["state"])
    runs = tracking.find_runs(store, "sdrl-bench")
    fid = rt.fidelity_table(runs).set_index(["env", "state"]).loc["mountain_car"]
    md = render_markdown(table_blocks(runs, Linker(runs, None)), tmp_path)
    for state in ("x", "v"):
        for col, key in (("mse", f"mse/{state}"), ("rollout", f"rollout50_mse/{state}")):
            assert _sig4(fid.loc[state, col]) == _sig4(logged[key])
            shown = f"{logged[key]:.3e}"
            assert re.search(re.escape(shown), md), (shown, key)


BLOCK_HARNESS = """
import importlib.abc, json, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "sdrl_bench" or name.startswith("sdrl_bench."):
            raise ImportError(f"{name} is blocked: the logged model must load without the harness")
sys.meta_path.insert(0, Block())
import mlflow, pandas as pd
case = json.loads(sys.argv[1])
mlflow.set_tracking_uri(case["uri"])
model = mlflow.pyfunc.load_model(case["model"])
print(json.dumps({"pred": model.predict(pd.DataFrame(case["z"], columns=case["inputs"])).to_numpy().tolist(),
                  "harness_loaded": any(m.startswith("sdrl_bench") for m in sys.modules)}))
"""


@pytest.mark.parametrize("surrogate", ["nn", "pe"])
def test_a_logged_nn_model_loads_and_predicts_without_the_harness(store, surrogate):
    """An MLP and a probabilistic ensemble, logged by a fit, load by their models:/ URI in a fresh
    process where sdrl_bench cannot be imported, and predict the harness's next states (1e-12)."""
    import subprocess
    import sys

    result = run_fit(compose_cfg(f"tracking.uri={store}", f"surrogate={surrogate}", "surrogate.model.max_steps=200"))
    spec = result.job.spec
    (out,) = MlflowClient(store).get_run(search(store).iloc[0]["run_id"]).outputs.model_outputs
    logged = MlflowClient(store).get_logged_model(out.model_id)
    assert logged.name == f"mountain_car-{surrogate}-{surrogate}"
    x, u = spec.model_inputs(result.test.states[:50], result.test.actions[:50])
    case = {"uri": store, "model": f"models:/{out.model_id}", "inputs": list(spec.input_names),
            "z": np.concatenate([x, u], axis=1).tolist()}
    proc = subprocess.run([sys.executable, "-c", BLOCK_HARNESS, json.dumps(case)], capture_output=True, text=True,
                          timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert not got["harness_loaded"]
    expected = result.model.predict(x, u)
    assert np.max(np.abs(np.asarray(got["pred"]) - expected)) <= 1e-12
    assert np.max(np.abs(expected - x)) > 0  # the model predicts a change: the comparison is not of inputs


def test_sb3_rows_are_batched_and_all_written_when_the_logger_closes(store):
    """``tracking.sb3.sb3_logger`` holds SB3's rows until its flush interval or ``close``; then
    every row is in the run at its own step."""
    from sdrl_bench.tracking.client import start_run
    from sdrl_bench.tracking.sb3 import sb3_logger

    with start_run(store, "sdrl-bench", "sb3-rows") as run:
        held, eager = sb3_logger(run, "arm/sb3", flush_seconds=3600.0), sb3_logger(run, "eager/sb3", flush_seconds=0.0)
        for step in (128, 256, 384):
            for logger in (held, eager):
                logger.record("train/value_loss", step / 1000)
                logger.record("train/flag", True)  # not a number: left out
                logger.dump(step=step)
        client = MlflowClient(store)
        history = lambda key: [(m.step, m.value) for m in client.get_metric_history(run.run_id, key)]  # noqa: E731
        assert history("arm/sb3/train/value_loss") == []
        assert sorted(history("eager/sb3/train/value_loss")) == [(128, 0.128), (256, 0.256), (384, 0.384)]
        held.close()
        assert sorted(history("arm/sb3/train/value_loss")) == [(128, 0.128), (256, 0.256), (384, 0.384)]
        assert "arm/sb3/train/flag" not in client.get_run(run.run_id).data.metrics


def test_a_run_whose_owner_is_a_zombie_is_stale_and_one_whose_owner_lives_is_not(store):
    """``end_stale_runs`` (a sweep's rerun) ends the RUNNING runs of dead owners: a zombie (a
    killed process not yet reaped, as a sweep's workers are a moment after a kill -9 of their
    driver) is dead; a live process's run is left alone."""
    import os
    import socket
    import subprocess
    import sys
    import time

    import psutil

    from sdrl_bench import tracking
    from sdrl_bench.tracking.client import process_start, process_tags, system_identity
    from sdrl_bench.tracking.read import owner_alive

    def owner(pid: int) -> dict[str, str]:  # the tags process ``pid`` would give its own runs
        machine, boot, namespace = system_identity()
        return {"sdrl.host": socket.gethostname(), "sdrl.pid": str(pid), "sdrl.machine": machine, "sdrl.boot": boot,
                "sdrl.pid_ns": namespace, "sdrl.pid_start": process_start(pid)}

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    try:
        deadline = time.monotonic() + 60
        while psutil.Process(dead.pid).status() != psutil.STATUS_ZOMBIE and time.monotonic() < deadline:
            time.sleep(0.05)  # exited, and not reaped: this process has not waited for it
        assert psutil.Process(dead.pid).status() == psutil.STATUS_ZOMBIE
        here = socket.gethostname()
        assert owner_alive({"sdrl.host": here, "sdrl.pid": str(dead.pid)}) is False
        assert owner_alive({"sdrl.host": here, "sdrl.pid": str(live.pid)}) is True
        assert owner_alive(owner(live.pid)) is True and owner(os.getpid()) == process_tags()
        assert all(owner(live.pid).values()) and owner(live.pid)["sdrl.pid_start"].isdigit()  # Linux says them all
        # the live pid, but started at another tick: the system reused the pid of a dead owner
        reused = {**owner(live.pid), "sdrl.pid_start": str(int(owner(live.pid)["sdrl.pid_start"]) - 1)}
        assert owner_alive(reused) is False
        # an earlier boot of this machine: nothing of it lives
        assert owner_alive({**owner(live.pid), "sdrl.boot": "an-earlier-boot"}) is False
        # another pid namespace or machine under the same host name (a container, a cloned VM):
        # not for this process to judge
        assert owner_alive({**owner(dead.pid), "sdrl.pid_ns": "pid:[1]"}) is None
        assert owner_alive({**owner(dead.pid), "sdrl.machine": "another-machine"}) is None
        assert owner_alive({**owner(live.pid), "sdrl.host": here + "-elsewhere"}) is None
        ids = {name: tracking.create_parent_run(store, "stale", name, {**owner(p.pid), "sdrl.test": "owners"})
               for name, p in (("dead", dead), ("live", live))}
        assert tracking.end_stale_runs(store, "stale", "tags.`sdrl.test` = 'owners'") == [ids["dead"]]
        status = {r["run_id"]: r["status"] for r in tracking.find_runs(store, "stale")}
        assert status == {ids["dead"]: "KILLED", ids["live"]: "RUNNING"}
        # any command's sweep: every dead owner's run but a study's parent, which its other workers share
        more = {kind: tracking.create_parent_run(store, "stale", kind, {**owner(dead.pid), "sdrl.kind": kind})
                for kind in ("fit", "study", "dyna")}
        assert sorted(tracking.end_runs_of_dead_processes(store, "stale")) == sorted([more["fit"], more["dyna"]])
        status = {r["run_id"]: r["status"] for r in tracking.find_runs(store, "stale")}
        assert [status[more[k]] for k in ("fit", "study", "dyna")] == ["KILLED", "RUNNING", "KILLED"]
        assert status[ids["live"]] == "RUNNING"
    finally:
        live.kill()
        live.wait()
        dead.wait()


def test_the_harness_commit_is_its_own_checkouts_never_an_enclosing_repositorys(tmp_path):
    """From this checkout, ``sdrl.package_commit`` is its HEAD. Installed in a venv that sits inside
    another git repository (``myproject/.venv``, a wheel's usual place), the package has no commit
    of its own: no ``sdrl.package_commit``, but the version it was installed as."""
    import shutil
    import subprocess
    import sys

    from helpers import ROOT
    from sdrl_bench.tracking import meta

    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    if head.returncode == 0 and (ROOT / ".git").exists():
        meta.package_commit.cache_clear()  # read once per process: HEAD may have moved since
        assert meta.package_commit() == head.stdout.strip()
    project = tmp_path / "myproject"
    site = project / ".venv" / "lib" / "python3.11" / "site-packages"
    shutil.copytree(ROOT / "sdrl_bench", site / "sdrl_bench", ignore=shutil.ignore_patterns("__pycache__"))
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q"], cwd=project, check=True)
    subprocess.run([*git, "commit", "-q", "--allow-empty", "-m", "theirs"], cwd=project, check=True)
    code = ("import json; from sdrl_bench.tracking import meta; "
            "print(json.dumps([meta.package_commit(), meta.standard_tags()]))")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                         env={**os.environ, "PYTHONPATH": str(site)})
    assert out.returncode == 0, out.stderr
    commit, tags = json.loads(out.stdout.strip().splitlines()[-1])
    assert commit == "unknown" and "sdrl.package_commit" not in tags
    assert tags["git_commit"] == "unknown" and tags["sdrl.package_version"] == meta.package_version()


def test_a_chain_of_sweep_reruns_notes_every_earlier_run_whose_jobs_moved(store):
    """Sweep A is killed; rerun B adopts A's finished job and is killed too (B never summarizes);
    rerun C adopts it from B. C's end notes A and B, each counted again and pointing to C, and
    leaves alone a run whose children did not move, a RUNNING one and a deleted one."""
    from sdrl_bench import tracking

    key = {"sdrl.kind": "sweep", "sdrl.sweep_key": "k1"}
    a, b, c, same, live, gone = (tracking.create_parent_run(store, "sdrl-bench", f"sweep-{n}", key)
                                 for n in ("a", "b", "c", "same", "live", "gone"))
    with tracking.start_run(store, "sdrl-bench", "job-0", {"sdrl.kind": "fit"}, parent_run_id=c) as run:
        run.set_tags({tracking.ADOPTED_BY_TAG: c, tracking.ADOPTED_FROM_TAG: b})  # C took it from B, B from A
    with tracking.start_run(store, "sdrl-bench", "job-1", {"sdrl.kind": "fit"}, parent_run_id=same):
        pass
    tracking.summarize_sweep(store, same)
    for r in (a, b, same, gone):
        tracking.end_run(store, r, "KILLED")
    MlflowClient(store).delete_run(gone)
    noted = tracking.note_adoptions(store, c, [a, b, c, same, live, gone])
    assert sorted(noted) == sorted([a, b])
    runs = {r["run_id"]: r for r in tracking.find_runs(store, "sdrl-bench")}
    for r in (a, b):
        assert runs[r]["tags"]["sdrl.resumed_by"] == c and runs[r]["metrics"]["n_children"] == 0
        assert "sdrl.package_version" not in runs[r]["tags"]  # no provenance stamped by another process
    assert runs[b]["tags"]["mlflow.note.content"].startswith(
        f"**Resumed** by the sweep run **sweep-c** (`{c}`), which adopted 1 of this run's finished jobs: they are "
        "listed there; this run keeps 0 runs.")
    assert runs[a]["tags"]["mlflow.note.content"].startswith(
        f"**Resumed** by the sweep run **sweep-c** (`{c}`), which holds the finished jobs this run had")
    assert "sdrl.resumed_by" not in runs[same]["tags"] and "sdrl.resumed_by" not in runs[live]["tags"]


def test_the_runs_running_below_a_sweep_are_its_jobs_and_theirs_whatever_their_parents_status(store):
    """A stopped sweep ends what its workers left RUNNING: a job's run, and the runs under a job
    (Dyna's rounds, a fidelity cluster's surrogates) also when the job's own run has ended; a
    RUNNING run of another sweep is left alone."""
    from sdrl_bench import tracking

    def run(name: str, parent: str, status: str) -> str:
        with tracking.start_run(store, "sdrl-bench", name, {"sdrl.kind": "fit"}, parent_run_id=parent) as r:
            pass
        tracking.Run(store, r.run_id).end(status)
        return r.run_id

    sweep, other = (tracking.create_parent_run(store, "sdrl-bench", n, {"sdrl.kind": "sweep"}) for n in ("s", "o"))
    done = run("job-0", sweep, "KILLED")
    rounds = [run("job-0-round0", done, "RUNNING")]
    rounds.append(run("job-0-round0-part", rounds[0], "RUNNING"))
    live = run("job-1", sweep, "RUNNING")
    run("job-1-round0", live, "FINISHED")
    middle = run("job-2-cluster", run("job-2", sweep, "FINISHED"), "FINISHED")
    rounds.append(run("job-2-cluster-surrogate", middle, "RUNNING"))  # three levels down, its parents ended
    theirs = run("other-job", other, "RUNNING")
    below = tracking.running_below(store, "sdrl-bench", sweep)
    assert sorted(below) == sorted([*rounds, live]) and theirs not in below
    assert tracking.running_below(store, "sdrl-bench", other) == [theirs]


def _log_the_same_params(uri: str, run_id: str, barrier, out) -> None:
    from sdrl_bench import tracking

    run = tracking.Run(uri, run_id)
    barrier.wait()  # every process logs at once: MLflow's check-then-insert races
    try:
        run.log_params({f"p{i}": i for i in range(40)})
        out.put("ok")
    except Exception as exc:  # noqa: BLE001 - reported to the test
        out.put(f"{type(exc).__name__}: {str(exc).splitlines()[0][:200]}")


def test_processes_logging_the_same_params_to_one_run_at_once_all_succeed(store):
    """The workers of a study summarize its parent run together: before, 4 processes logging the
    same 40 params to one run at once failed 10 times in 10 (UNIQUE constraint failed:
    params.key). A value the run holds with another value is still MLflow's error."""
    import multiprocessing as mp

    from mlflow.exceptions import MlflowException

    from sdrl_bench import tracking

    ctx = mp.get_context("spawn")
    for attempt in range(2):
        run_id = tracking.create_parent_run(store, "params-race", f"race-{attempt}", {})
        barrier, out = ctx.Barrier(4, timeout=120), ctx.Queue()
        procs = [ctx.Process(target=_log_the_same_params, args=(store, run_id, barrier, out), daemon=True) for _ in range(4)]
        try:
            for p in procs:
                p.start()
            got = [out.get(timeout=180) for _ in procs]
        finally:
            for p in procs:
                p.join(timeout=30)
                if p.is_alive():
                    p.kill()
        assert got == ["ok"] * 4
        params = MlflowClient(store).get_run(run_id).data.params
        assert params == {f"p{i}": str(i) for i in range(40)}
    with pytest.raises(MlflowException, match="p3"):
        tracking.Run(store, run_id).log_params({"p3": 4, "q": 1})
    assert "q" not in MlflowClient(store).get_run(run_id).data.params
