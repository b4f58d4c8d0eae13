"""Against a real ``mlflow server`` on 127.0.0.1 (SQLite backend and artifacts in a temp dir):
a fit run as MLflow users expect it (datasets, a logged model that loads and predicts, the
equations as description, standard tags, lean params) and a sweep parent's summary."""

from __future__ import annotations

import contextlib
import subprocess
import urllib.request
from pathlib import Path

import mlflow
import numpy as np
import pandas as pd
import pytest
from mlflow.tracking import MlflowClient

from helpers import ROOT, compose_cfg, run_cli, start_mlflow_server, stop_mlflow_server
from sdrl_bench import tracking
from sdrl_bench.cli.main import run_fit


def test_a_fit_run_on_a_server_has_datasets_a_loadable_model_equations_tags_and_lean_params(mlflow_server, monkeypatch, capsys,
                                                                                             tmp_path):
    server = mlflow_server
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    parent = tracking.create_parent_run(server, "sdrl-bench", "sweep-test",
                                        {"sdrl.kind": "sweep", "sdrl.overrides": "seed=1,2 library=poly_trig"})
    result = run_fit(compose_cfg(f"tracking.uri={server}", "seed=1"), parent=parent)
    printed = capsys.readouterr().out
    client = MlflowClient(server)
    exp = client.get_experiment_by_name("sdrl-bench")
    (run,) = client.search_runs([exp.experiment_id], "tags.`sdrl.kind` = 'fit'")
    rid = run.info.run_id

    # datasets: the training transitions and the held-out test set, with digests and contexts
    inputs = {i.tags[0].value: i.dataset for i in run.inputs.dataset_inputs}
    assert set(inputs) == {"training", "testing", "prior:knowledge"}  # + MountainCar's declared knowledge prior
    assert inputs["prior:knowledge"].name == "mountain_car-interface"
    assert inputs["testing"].name == "mountain_car-heldout-v1" and inputs["training"].name == f"mountain_car-transitions-{rid[:8]}"
    assert rid in inputs["training"].source  # this run's own file
    assert all(len(inputs[k].digest) >= 8 for k in ("training", "testing")) and inputs["training"].digest != inputs["testing"].digest
    assert '"num_rows": 75' in inputs["training"].profile

    # the logged model: a self-contained pyfunc that predicts the next states from the model's inputs
    (out,) = run.outputs.model_outputs
    logged = client.get_logged_model(out.model_id)
    assert logged.source_run_id == rid and logged.name == "mountain_car-poly_trig-sindy" and logged.status == "READY"
    assert "x[k+1] = 1 x +1 v +0.0015 u -0.0025 cos(3 x)" in logged.tags["mlflow.note.content"]
    assert logged.experiment_id == exp.experiment_id  # listed on the run page and the experiment's Models tab
    mlflow.set_tracking_uri(server)
    try:
        pyfunc = mlflow.pyfunc.load_model(f"models:/{out.model_id}")
        per_state = client.load_table(exp.experiment_id, "fidelity/per_state.json", run_ids=[rid])  # reads the global URI
    finally:
        mlflow.set_tracking_uri(None)
    spec, test = result.job.spec, result.test
    x, u = spec.model_inputs(test.states, test.actions)
    frame = pd.DataFrame(np.concatenate([x, u], axis=1), columns=list(spec.input_names))
    pred = pyfunc.predict(frame)
    assert list(pred.columns) == ["x_next", "v_next"] and len(pred) == len(test)
    assert np.max(np.abs(pred.to_numpy() - result.model.predict(x, u))) <= 1e-12
    assert pyfunc.metadata.signature.inputs.input_names() == ["x", "v", "u"]

    # description = the equations; standard tags; lean params with the real tracking URI
    tags = run.data.tags
    for line in result.model.describe().strip().splitlines():
        assert line.strip() in tags["mlflow.note.content"]
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    assert tags["mlflow.source.git.commit"] == head and len(head) == 40
    assert tags["mlflow.user"] and tags["mlflow.source.name"]
    params = run.data.params
    assert len(params) <= 30 and params["tracking.uri"] == server and params["library.name"] == "poly_trig"
    assert not any(k.startswith(("agent.", "env.expert", "rl.")) for k in params)
    config = client.download_artifacts(rid, "config.yaml", str(tmp_path))  # the full resolved config
    assert "expert:" in Path(config).read_text()
    assert list(per_state["state"]) == ["x", "v"]
    m = result.fidelity.metrics  # the JSON table keeps 10 significant digits
    assert per_state["mse"].tolist() == pytest.approx([m["mse/x"], m["mse/v"]], rel=1e-9, abs=0)
    assert client.get_experiment(exp.experiment_id).tags["mlflow.note.content"].startswith("sdrl-bench:")

    # the CLI prints the server's run page, not an `mlflow ui` command that fails for servers
    url = tracking.run_url(server, exp.experiment_id, rid)
    assert f"open {url}" in printed and "mlflow ui" not in printed
    with urllib.request.urlopen(url.split("#")[0], timeout=10) as r:
        assert r.status == 200

    # the sweep parent's summary: overrides as params, the best child as metric, tag and description
    with tracking.start_run(server, "sdrl-bench", "worse-child", {"sdrl.kind": "fit"}, parent) as worse:
        worse.log_metrics({"mse_norm/mean": 1.0})
    summary = tracking.summarize_sweep(server, parent)
    prun = client.get_run(parent)
    assert prun.data.params == {"seed": "1,2", "library": "poly_trig"}
    best = result.fidelity.metrics["mse_norm/mean"]
    assert prun.data.metrics["best/mse_norm/mean"] == pytest.approx(best, rel=1e-12, abs=0)
    assert summary["n_children"] == 2 and prun.data.metrics["n_finished"] == 2
    assert prun.data.tags["best_run_id"] == rid and "fit-mountain_car" in prun.data.tags["mlflow.note.content"]
    assert prun.data.tags["mlflow.source.git.commit"] == head


STOPPED_COMMANDS = {
    # the README's train task, its fit logged, mid-training
    "sdrl-bench": (["sdrl_bench.cli.main", "task=train", "rl.arms=[surrogate]", "rl.surrogate_steps=1000000",
                    "rl.eval_every=500000", "agent.algo.batch_size=32", "agent.algo.train_freq=16",
                    "agent.algo.policy_kwargs.net_arch=[16]", "progress_bar=false"], "sdrl-bench", "transfer"),
    # a search mid-study (its trials log between fits; that logging once held the stop)
    "sdrl-bench-search": (["sdrl_bench.cli.search", "study.name=t", "search.n_trials=400"], "sdrl-bench-search", "trial"),
}


@pytest.mark.parametrize("command", list(STOPPED_COMMANDS))
def test_a_command_stopped_after_its_server_died_exits_in_one_line_not_after_minutes_of_retries(command, tmp_path):
    """The server dies mid-run (SIGKILL), then the command is stopped (SIGTERM): from the stop on,
    MLflow's retries on the server are capped (``tracking.client.STOP_SERVER_WAITS``), so the
    command gives up on the store within seconds, says in one line that its runs may still show
    RUNNING, and exits 143. Before the cap the train task retried each last request with MLflow's
    backoff and was still retrying over 10 minutes after the SIGTERM; the search waited out a
    trial's logging request (about 4 minutes) while it held the stop (``communicate``'s limit
    below fails either)."""
    import os
    import signal
    import sys
    import time

    argv, prog, ready = STOPPED_COMMANDS[command]
    server, url = start_mlflow_server(tmp_path)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p)}
    env.pop("MLFLOW_TRACKING_URI", None)
    extra = [f"study.storage=sqlite:///{tmp_path / 'optuna.db'}"] if command == "sdrl-bench-search" else []
    proc = subprocess.Popen([sys.executable, "-m", *argv, *extra, f"tracking.uri={url}"], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        client, deadline, started = MlflowClient(url), time.monotonic() + 180, False
        while not started and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(1)
            with contextlib.suppress(Exception):
                ids = [e.experiment_id for e in client.search_experiments()]
                runs = client.search_runs(ids, f"tags.`sdrl.kind` = '{ready}'")
                started = bool(runs) and (ready != "transfer" or bool(runs[0].outputs.model_outputs))
        assert started and proc.poll() is None, proc.communicate(timeout=30)[1][-2000:]
        stop_mlflow_server(server, signal.SIGKILL)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        for p in (proc, server):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
    assert proc.returncode == 128 + signal.SIGTERM, err[-2000:]
    assert err.strip().splitlines()[-1] == (f"{prog}: stopped by SIGTERM; the tracking store at {url} did not answer, "
                                            "so this command's runs may still show RUNNING (the next command on this experiment ends them)")


def test_credentials_in_the_tracking_uri_reach_no_output_run_or_report(tmp_path):
    """A tracking URI with a user and password (``http://user:password@host``, sent as Basic
    auth): the password appears nowhere the harness writes. Not in what the commands print, not
    in any run's params, tags or artifacts (the backend's database and artifact files are read as
    bytes), not in the report's files; its links carry no credentials (a browser asks for them).
    Before, the fit's ``tracking.uri`` param and ``config.yaml``, a sweep's ``sdrl.overrides`` tag
    and its summary's params, the printed run address and the report's links all carried it."""
    secret = "s3cret-Pa55"
    server_dir = tmp_path / "server"
    server_dir.mkdir()
    proc, url = start_mlflow_server(server_dir)
    try:
        host = url.removeprefix("http://")
        uri = f"http://alice:{secret}@{host}"
        work = tmp_path / "work"
        work.mkdir()
        commands = [
            ("sdrl_bench.cli.main", [f"tracking.uri={uri}", "seed=1"]),
            ("sdrl_bench.cli.main", ["-m", f"tracking.uri={uri}", "seed=2,3", "hydra.launcher.n_jobs=1"]),
            ("sdrl_bench.cli.search", [f"tracking.uri={uri}", "study.name=creds", "search.n_trials=2"]),
            ("sdrl_bench.cli.report", ["--uri", uri, "--out", str(work / "reports"), "--name", "r"]),
        ]
        printed = ""
        for module, args in commands:
            done = run_cli(*args, cwd=work, module=module, timeout=600)
            assert done.returncode == 0, (module, done.stderr[-2000:])
            # Hydra's launcher echoes each job's overrides as the user typed them: theirs, not ours
            printed += "".join(line for line in (done.stdout + done.stderr).splitlines(keepends=True)
                               if "[HYDRA]" not in line)
        assert secret not in printed and f"open {url}/#/experiments/" in printed
        assert f"http://alice:***@{host}" in printed  # the store each command names, its password hidden
        client = MlflowClient(uri)
        runs = client.search_runs([e.experiment_id for e in client.search_experiments()], max_results=1000)
        kinds = {r.data.tags.get("sdrl.kind") for r in runs}
        assert {"fit", "sweep", "study", "trial", "report"} <= kinds
        fit = next(r for r in runs if r.data.tags.get("sdrl.kind") == "fit" and r.data.params.get("seed") == "1")
        assert fit.data.params["tracking.uri"] == f"http://alice:***@{host}"
        sweep = next(r for r in runs if r.data.tags.get("sdrl.kind") == "sweep")
        assert f"tracking.uri=http://alice:***@{host}" in sweep.data.tags["sdrl.overrides"]
        stored = [p for p in server_dir.rglob("*") if p.is_file()] + [p for p in work.rglob("*") if p.is_file()]
        assert any(p.name == "config.yaml" for p in stored) and any(p.name == "report.html" for p in stored)
        hydra_record = work / "mlruns" / "hydra"  # Hydra's own record of each command line: the user's, kept as typed
        leaked = [str(p) for p in stored if secret.encode() in p.read_bytes() and p.name != "server.log"
                  and not p.is_relative_to(hydra_record)]
        assert leaked == []
    finally:
        stop_mlflow_server(proc)
