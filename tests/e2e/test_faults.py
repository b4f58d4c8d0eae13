"""Faults as a user meets them, done for real: kills (SIGKILL, SIGTERM) of a sweep driver and of
a study, parallel first use of an empty store, damaged stores, bad numbers. Real processes, a
real SQLite store, real signals."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import optuna
import psutil
import pytest

from helpers import compose_cfg, run_cli
from sdrl_bench import ConfigError, tracking
from sdrl_bench.cli.main import run_fit

EXP = "sdrl-bench"


def _env() -> dict:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    env.pop("MLFLOW_TRACKING_URI", None)
    return env


def _start(args: list[str], cwd: Path, module: str = "sdrl_bench.cli.main") -> subprocess.Popen:
    """A process in a session of its own (so a kill of its group reaches its workers too)."""
    return subprocess.Popen([sys.executable, "-m", module, *args], cwd=cwd, env=_env(), start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _runs(uri: str, filt: str = "", experiment: str = EXP) -> list[dict]:
    return tracking.find_runs(uri, experiment, filt) if Path(tracking.sqlite_path(uri)).is_file() else []


def _wait_for(predicate, timeout: float, what: str) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return
        time.sleep(0.5)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def _kinds(runs: list[dict], kind: str, status: str | None = None) -> list[dict]:
    return [r for r in runs if r["tags"].get("sdrl.kind") == kind and (status is None or r["status"] == status)]


# ------------------------------------------------------------------ parallel first use
def test_parallel_processes_create_one_store_safely(tmp_path):
    """Four processes open the same new store at once: all runs land, the store stays usable
    (eight, through the real command, in the slow test below)."""
    uri = f"sqlite:///{tmp_path / 'mlruns' / 'mlflow.db'}"
    code = ("import sys; from sdrl_bench import tracking\n"
            "with tracking.start_run(sys.argv[1], 'sdrl-bench', 'p' + sys.argv[2], {'sdrl.kind': 'probe'}) as run:\n"
            "    run.log_metrics({'m': float(sys.argv[2])})\n")
    procs = [subprocess.Popen([sys.executable, "-c", code, uri, str(i)], env=_env(), stderr=subprocess.PIPE, text=True)
             for i in range(4)]
    errs = [p.communicate(timeout=120)[1] for p in procs]
    assert [p.returncode for p in procs] == [0] * 4, errs
    runs = _runs(uri)
    assert len(runs) == 4 and {r["status"] for r in runs} == {"FINISHED"}
    assert sorted(r["metrics"]["m"] for r in runs) == [float(i) for i in range(4)]
    tracking.check_integrity(tracking.sqlite_path(uri))


def test_parallel_runs_logging_the_same_new_dataset_all_land(tmp_path):
    """Four processes log the same new dataset (name and digest) as an input of their own run at
    the same moment, ten times over: MLflow looks for the dataset and then inserts it, so all
    but one can hit its UNIQUE constraint; every run must still get its input (retried).
    Without the retry (attempts=1) this failed here."""
    uri = f"sqlite:///{tmp_path / 'mlruns' / 'mlflow.db'}"
    tracking.ensure_experiment(uri, EXP)
    code = ("import sys, time\n"
            "import mlflow.data, pandas as pd\n"
            "from mlflow.entities import DatasetInput\n"
            "from sdrl_bench import tracking\n"
            "from sdrl_bench.tracking.model import log_inputs_retrying\n"
            "uri, i, t0 = sys.argv[1], sys.argv[2], float(sys.argv[3])\n"
            "for k in range(10):\n"
            "    ds = mlflow.data.from_pandas(pd.DataFrame({'x': [float(k), 1.0]}), source='test', name=f'shared-{k}')\n"
            "    with tracking.start_run(uri, 'sdrl-bench', f'p{i}-{k}', {'sdrl.kind': 'probe'}) as run:\n"
            "        time.sleep(max(0.0, t0 + 0.5 * k - time.time()))\n"
            "        log_inputs_retrying(run, [DatasetInput(ds._to_mlflow_entity())])\n")
    t0 = time.time() + 8.0  # all four have imported MLflow by then
    procs = [subprocess.Popen([sys.executable, "-c", code, uri, str(i), str(t0)], env=_env(), stderr=subprocess.PIPE,
                              text=True) for i in range(4)]
    errs = [p.communicate(timeout=120)[1] for p in procs]
    assert [p.returncode for p in procs] == [0] * 4, [e[-1500:] for e in errs]
    from mlflow.tracking import MlflowClient

    runs = MlflowClient(uri).search_runs([tracking.ensure_experiment(uri, EXP)], max_results=100)
    assert len(runs) == 40 and {r.info.status for r in runs} == {"FINISHED"}
    names = sorted(d.dataset.name for r in runs for d in r.inputs.dataset_inputs)
    assert names == sorted(f"shared-{k}" for k in range(10) for _ in range(4))


@pytest.mark.slow
def test_eight_parallel_first_fits_on_an_empty_folder(tmp_path):
    """The issue's case with the real command: ``sdrl-bench seed=i`` x 8 at once in an empty folder."""
    procs = [_start([f"seed={i}", "tracking.uri=sqlite:///mlruns/mlflow.db"], tmp_path) for i in range(8)]
    outs = [p.communicate(timeout=600) for p in procs]
    assert [p.returncode for p in procs] == [0] * 8, [e for _, e in outs]
    uri = f"sqlite:///{tmp_path / 'mlruns' / 'mlflow.db'}"
    assert Counter(r["status"] for r in _kinds(_runs(uri), "fit")) == {"FINISHED": 8}
    assert run_cli("seed=9", f"tracking.uri={uri}", cwd=tmp_path).returncode == 0  # and it works afterwards
    assert len(_kinds(_runs(uri), "fit", "FINISHED")) == 9


# ------------------------------------------------------------------ sweeps: kill, resume, signals
SWEEP = ["-m", "env=mountain_car", "seed=0,1,2,3", "hydra.launcher.n_jobs=2"]


def test_switches_that_change_no_result_keep_a_rerun_the_same_sweep():
    """``resume=true`` or ``progress_bar=false`` added to a rerun: still the same sweep (its finished
    jobs adopted); an override that changes a job, or another experiment, is another sweep."""
    from sdrl_bench.cli.callbacks import sweep_key

    base = sweep_key(["env=mountain_car", "seed=0,1"], EXP)
    assert sweep_key(["seed=0,1", "resume=true", "env=mountain_car", "progress_bar=false"], EXP) == base
    assert sweep_key(["env=mountain_car", "seed=0,1", "n_transitions=80"], EXP) != base
    assert sweep_key(["env=mountain_car", "seed=0,1"], "other") != base


def test_sigkill_mid_sweep_then_rerun_leaves_one_finished_run_per_job(tmp_path):
    uri = f"sqlite:///{tmp_path / 'mlruns' / 'mlflow.db'}"
    args = [*SWEEP, f"tracking.uri={uri}"]
    proc = _start(args, tmp_path)
    _wait_for(lambda: len(_kinds(_runs(uri), "fit", "FINISHED")) >= 1, 240, "a finished job")
    os.killpg(proc.pid, signal.SIGKILL)  # the driver and its workers, no cleanup at all
    proc.wait(timeout=30)
    before = _runs(uri)
    finished_before = {r["run_id"] for r in _kinds(before, "fit", "FINISHED")}
    assert _kinds(before, "sweep", "RUNNING")  # what a kill -9 leaves behind
    rerun = subprocess.run([sys.executable, "-m", "sdrl_bench.cli.main", *args], cwd=tmp_path, env=_env(),
                           capture_output=True, text=True, timeout=600)
    assert rerun.returncode == 0, rerun.stderr[-2000:]
    runs = _runs(uri)
    assert not [r for r in runs if r["status"] == "RUNNING"]
    fits = _kinds(runs, "fit", "FINISHED")
    by_config = Counter(r["tags"]["sdrl.config_key"] for r in fits)
    assert len(by_config) == 4 and set(by_config.values()) == {1}  # one FINISHED run per job, no duplicate
    assert finished_before <= {r["run_id"] for r in fits}  # adopted, not rerun
    assert rerun.stderr.count("adopted, not rerun") == len(finished_before)
    new_parent = [r for r in _kinds(runs, "sweep") if r["status"] == "FINISHED"]
    assert len(new_parent) == 1 and {r["tags"][tracking.PARENT_TAG] for r in fits} == {new_parent[0]["run_id"]}
    sweep_id = new_parent[0]["run_id"]
    assert f"sdrl-bench: sweep run {sweep_id} in " in rerun.stdout
    assert (f"sdrl-bench: sweep run {sweep_id} ended FINISHED; its report: sdrl-bench-report --uri "
            "sqlite:///mlruns/mlflow.db "  # the store as the user named it, from the folder they ran in
            f"--experiment {EXP} --parent-run {sweep_id} --name sweep-{sweep_id[:8]} --ui-url http://127.0.0.1:5000"
            ) in rerun.stdout  # a local store: links for `mlflow ui`
    # the killed sweep's parent says where its finished jobs went, and counts what it kept
    old_parent = [r for r in _kinds(runs, "sweep") if r["status"] == "KILLED"]
    assert len(old_parent) == 1 and old_parent[0]["tags"]["sdrl.resumed_by"] == new_parent[0]["run_id"]
    adopted = [r for r in fits if r["run_id"] in finished_before]
    assert {r["tags"]["sdrl.adopted_from"] for r in adopted} == {old_parent[0]["run_id"]}
    kept = [r for r in runs if r["tags"].get(tracking.PARENT_TAG) == old_parent[0]["run_id"]]
    assert old_parent[0]["metrics"]["n_children"] == len(kept)
    assert old_parent[0]["tags"]["mlflow.note.content"].startswith(
        f"**Resumed** by the sweep run **{new_parent[0]['tags']['mlflow.runName']}** (`{new_parent[0]['run_id']}`), "
        f"which adopted {len(finished_before)} of this run's finished jobs")
    # resume=false forces finished jobs to run again (a new run each; two of them, in one process: n_jobs=1)
    one_process = [a for a in args if not a.startswith(("hydra.launcher.n_jobs=", "seed="))] + ["seed=0,1",
                                                                                                  "hydra.launcher.n_jobs=1"]
    forced = subprocess.run([sys.executable, "-m", "sdrl_bench.cli.main", *one_process, "resume=false"], cwd=tmp_path,
                            env=_env(), capture_output=True, text=True, timeout=600)
    assert forced.returncode == 0 and "adopted" not in forced.stderr
    assert len(_kinds(_runs(uri), "fit", "FINISHED")) == 6


def test_sigterm_to_a_sweep_driver_stops_workers_and_ends_runs_killed(tmp_path):
    uri = f"sqlite:///{tmp_path / 'mlruns' / 'mlflow.db'}"
    proc = _start(["-m", "env=lunar_lander", "seed=0,1,2,3", f"tracking.uri={uri}"], tmp_path)
    _wait_for(lambda: bool(_kinds(_runs(uri), "fit", "RUNNING")), 240, "a running job")
    workers = psutil.Process(proc.pid).children(recursive=True)
    assert workers
    proc.send_signal(signal.SIGTERM)  # the driver alone, as a scheduler or `kill` does
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM, err[-2000:]
    assert "stopped by SIGTERM" in err
    psutil.wait_procs(workers, timeout=10)
    assert not [w for w in workers if w.is_running() and w.status() != psutil.STATUS_ZOMBIE]
    runs = _runs(uri)
    assert not [r for r in runs if r["status"] == "RUNNING"]
    assert _kinds(runs, "sweep")[0]["status"] == "KILLED"
    assert {r["status"] for r in _kinds(runs, "fit")} <= {"FINISHED", "KILLED"}


def test_sigterm_to_a_study_ends_its_runs_killed_and_the_rerun_resumes(tmp_path):
    uri = f"sqlite:///{tmp_path / 'mlruns' / 'mlflow.db'}"
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    args = [f"tracking.uri='{uri}'", f"study.storage='{storage}'", "study.name=term", "search.n_trials=400",
            f"study.export_dir='{tmp_path / 'export'}'"]
    proc = _start(args, tmp_path, module="sdrl_bench.cli.search")
    _wait_for(lambda: bool(_kinds(_runs(uri, experiment="sdrl-bench-search"), "trial", "RUNNING")), 240, "a running trial")
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM, err[-2000:]
    # Optuna logs the failed trial's traceback itself; the command's last word is one line
    assert err.strip().splitlines()[-1].startswith("sdrl-bench-search: stopped by SIGTERM; the trial and study runs")
    runs = _runs(uri, experiment="sdrl-bench-search")
    assert not [r for r in runs if r["status"] == "RUNNING"]
    assert _kinds(runs, "study")[0]["status"] == "KILLED"
    assert {r["status"] for r in _kinds(runs, "trial")} <= {"FINISHED", "KILLED"}
    study = optuna.load_study(study_name="term", storage=storage)
    assert optuna.trial.TrialState.RUNNING not in {t.state for t in study.trials}


def test_a_held_stop_signal_is_raised_at_the_next_allowed_point():
    """A real SIGTERM inside ``stop_signals_held`` waits; a nested ``held=False`` block, or the
    end of the held block, raises it (this is how Optuna's bookkeeping is kept whole)."""
    import sdrl_bench
    from sdrl_bench import Terminated, raise_on_stop_signals, stop_signals_held

    saved = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    raise_on_stop_signals()
    reached = []
    try:
        with pytest.raises(Terminated) as caught, stop_signals_held():
            os.kill(os.getpid(), signal.SIGTERM)
            reached.append("after the signal")  # held: the body goes on
            with stop_signals_held(False):
                reached.append("never")  # the held signal is raised on entry
        assert reached == ["after the signal"] and caught.value.signum == signal.SIGTERM
        with pytest.raises(Terminated), stop_signals_held():  # no allowed point: raised at the end
            os.kill(os.getpid(), signal.SIGINT)
            reached.append("held to the end")
        assert reached[-1] == "held to the end" and sdrl_bench.stop_signal_received() == signal.SIGINT
        with pytest.raises(Terminated):  # not held: at once
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1)
    finally:
        for s, h in saved.items():
            signal.signal(s, h)
        sdrl_bench._stop.update(signum=None, pending=False, held=0)


# ------------------------------------------------------------------ damaged stores
@pytest.fixture(scope="module")
def one_fit_store(tmp_path_factory) -> Path:
    """A store holding one fit, written by a process that has exited (its WAL checkpointed)."""
    folder = tmp_path_factory.mktemp("one_fit")
    res = run_cli(f"tracking.uri=sqlite:///{folder / 'mlflow.db'}", cwd=folder)
    assert res.returncode == 0, res.stderr[-2000:]
    return folder / "mlflow.db"


@pytest.mark.parametrize("where", ["header", "middle", "end"])
def test_a_damaged_store_is_named_in_one_line_before_any_work_and_kept(tmp_path, one_fit_store, where):
    db = tmp_path / "mlruns" / "mlflow.db"
    db.parent.mkdir()
    db.write_bytes(one_fit_store.read_bytes())
    uri = f"sqlite:///{db}"
    size = db.stat().st_size
    page = int.from_bytes(db.read_bytes()[16:18], "big")  # the page size, from the file's header
    # the start of a page (its b-tree header): bytes inside a page's free space are not checked
    offset = {"header": 0, "middle": (size // page // 2) * page, "end": size - page}[where]
    with open(db, "r+b") as fh:
        fh.seek(offset)
        fh.write(b"\xa5" * 512)
    damaged = db.read_bytes()
    res = run_cli(f"tracking.uri={uri}", cwd=tmp_path)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and str(db) in lines[0] and "move it aside or restore it" in lines[0], res.stderr
    assert db.read_bytes() == damaged  # nothing the user had is changed
    rep = run_cli("--uri", uri, "--out", str(tmp_path / "reports"), cwd=tmp_path, module="sdrl_bench.cli.report")
    assert rep.returncode == 2 and str(db) in rep.stderr and rep.stdout == ""


# ------------------------------------------------------------------ bad numbers
@pytest.mark.parametrize("override, needle", [
    ("optimizer.threshold=nan", "optimizer.threshold: a finite number is required, got nan"),
    ("optimizer.threshold=inf", "optimizer.threshold: a finite number is required, got inf"),
    ("seed=x", "seed: an integer is required, got 'x'"),
    ("seed=-1", "seed must be >= 0, got -1"),
    ("n_transitions=abc", "n_transitions: an integer is required, got 'abc'"),
    ("n_transitions=1.5", "n_transitions: an integer is required, got 1.5"),
    ("collector.epsilon=1.5", "collector.epsilon must be within [0.0, 1.0], got 1.5"),
])
def test_bad_numbers_are_one_line_errors_before_any_run(store, override, needle):
    with pytest.raises(ConfigError) as err:
        run_fit(compose_cfg(f"tracking.uri={store}", override))
    assert str(err.value) == needle
    assert _runs(store) == []


def test_bad_number_from_the_command_line_exits_2_with_one_line(store, tmp_path):
    res = run_cli("optimizer.threshold=nan", f"tracking.uri={store}", cwd=tmp_path)
    assert res.returncode == 2
    assert res.stderr.strip() == "sdrl-bench: error: optimizer.threshold: a finite number is required, got nan"
    assert _runs(store) == []


def test_hydra_errors_reach_stderr_with_a_non_zero_exit(store, tmp_path):
    res = run_cli("library=nope", f"tracking.uri={store}", cwd=tmp_path)
    assert res.returncode == 2 and res.stdout == ""
    assert "library=nope: no such option of 'library'" in res.stderr and "Traceback" not in res.stderr


def test_sigterm_mid_dyna_ends_the_parent_and_the_open_round_killed(tmp_path):
    """A Dyna run stopped by SIGTERM while it trains: its finished round runs stay FINISHED, the
    parent ends KILLED, nothing is left RUNNING; exit 128 + SIGTERM."""
    uri = f"sqlite:///{tmp_path / 'mlruns' / 'mlflow.db'}"
    proc = _start(["experiment=dyna_mountain_car", "rl.dyna.first_round_steps=10000000", f"tracking.uri={uri}",
                   "progress_bar=false"], tmp_path)
    _wait_for(lambda: bool(_kinds(_runs(uri), "dyna_round", "FINISHED")), 240, "round 0's run")
    time.sleep(2)  # inside round 1's training
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM, err[-2000:]
    assert "stopped by SIGTERM" in err
    runs = _runs(uri)
    assert not [r for r in runs if r["status"] == "RUNNING"]
    assert [r["status"] for r in _kinds(runs, "dyna")] == ["KILLED"]
    assert [(r["tags"]["dyna.round"], r["status"]) for r in _kinds(runs, "dyna_round")] == [("0", "FINISHED")]


# ------------------------------------------------------------------ a single command killed
def test_a_single_command_killed_with_sigkill_has_its_runs_ended_by_the_next_command(tmp_path):
    """``kill -9`` of a single ``sdrl-bench`` command leaves its runs RUNNING, and no sweep or
    search rerun will end them: the next command on the same experiment does (KILLED, tagged
    ``sdrl.ended_by``), and leaves a live process's run alone."""
    uri = f"sqlite:///{tmp_path / 'mlruns' / 'mlflow.db'}"
    proc = _start(["experiment=quick_mountain_car", "rl.surrogate_steps=10000000", "rl.arms=[surrogate]",
                   f"tracking.uri={uri}", "progress_bar=false"], tmp_path)
    _wait_for(lambda: bool(_kinds(_runs(uri), "transfer", "RUNNING")), 240, "the train command's run")
    time.sleep(2)  # inside its training
    os.killpg(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=30)
    left = [r["run_id"] for r in _runs(uri) if r["status"] == "RUNNING"]
    assert left and {r["tags"]["sdrl.kind"] for r in _runs(uri)} >= {"transfer"}
    alive = tracking.create_parent_run(uri, EXP, "a live process's run", {"sdrl.kind": "probe"})  # this test's own
    rerun = run_cli("seed=1", f"tracking.uri={uri}", cwd=tmp_path)
    assert rerun.returncode == 0, rerun.stderr[-2000:]
    assert (f"sdrl-bench: ended {len(left)} run(s) of experiment 'sdrl-bench' KILLED that processes of this host "
            "left RUNNING when they died (tag sdrl.ended_by)") in rerun.stderr
    status = {r["run_id"]: (r["status"], r["tags"].get("sdrl.ended_by")) for r in _runs(uri)}
    assert {status[i] for i in left} == {("KILLED", "a later process: its owner had died")}
    assert status[alive] == ("RUNNING", None)
    assert [r["status"] for r in _kinds(_runs(uri), "fit") if r["tags"].get("seed") == "1"] == ["FINISHED"]
    tracking.end_run(uri, alive, "FINISHED")
