"""What the commands load before they answer: a bad command line or a damaged store is refused
(``sdrl-bench`` and ``sdrl-bench-search`` by cli.precheck, ``sdrl-bench-report`` after its
arguments) before pysindy, torch, SB3 or MLflow is imported, and a fit's command never imports
torch or SB3 (they serve the RL tasks alone), nor jax. Checked on the modules a real process holds
when it ends, not on its time."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

HEAVY = ("pysindy", "torch", "stable_baselines3", "mlflow")
MAIN, SEARCH, REPORT = "sdrl_bench.cli.main:main", "sdrl_bench.cli.precheck:search_main", "sdrl_bench.cli.report:main"

SCRIPT = """
import json, sys
import importlib
heavy = json.loads(sys.argv[2])
module, name = sys.argv[3].split(":")
sys.argv = [sys.argv[4], *json.loads(sys.argv[1])]
main = getattr(importlib.import_module(module), name)
try:
    ret = main()
except SystemExit as exc:
    code = exc.code
else:
    code = ret or 0
print("LOADED " + json.dumps({"code": code, "modules": [m for m in heavy if m in sys.modules]}))
"""


def run(args: list[str], cwd, entry: str = MAIN, prog: str = "sdrl-bench", heavy: tuple = HEAVY) -> dict:
    proc = subprocess.run([sys.executable, "-c", SCRIPT, json.dumps(args), json.dumps(heavy), entry, prog], cwd=cwd,
                          capture_output=True, text=True, timeout=300)
    line = [x for x in proc.stdout.splitlines() if x.startswith("LOADED ")]
    assert line, proc.stdout[-2000:] + proc.stderr[-2000:]
    return {**json.loads(line[-1][len("LOADED "):]), "stderr": proc.stderr}


def test_a_bad_command_line_is_refused_before_the_heavy_libraries_load(tmp_path):
    got = run(["n_transition=5"], tmp_path)
    assert got["code"] == 2 and got["modules"] == []
    assert got["stderr"].strip().splitlines() == [
        "sdrl-bench: error: n_transition: unknown config key; did you mean n_transitions? "
        "(to add a new key: +n_transition=...)"]
    assert not (tmp_path / "mlruns").exists() and not (tmp_path / "outputs").exists()


def test_the_search_command_refuses_a_bad_command_line_before_the_heavy_libraries_load(tmp_path):
    got = run(["n_trials=5"], tmp_path, SEARCH, "sdrl-bench-search")
    assert got["code"] == 2 and got["modules"] == []
    assert got["stderr"].strip().splitlines() == [
        "sdrl-bench-search: error: n_trials: unknown config key; did you mean search.n_trials? "
        "(to add a new key: +n_trials=...)"]
    assert not (tmp_path / "mlruns").exists()


def test_a_tracking_uri_that_is_not_a_string_is_one_line(tmp_path):
    got = run(["tracking.uri=5"], tmp_path)
    assert got["code"] == 2 and got["modules"] == []
    assert got["stderr"].strip().splitlines() == [
        "sdrl-bench: error: tracking.uri: a URI is required (sqlite:///<file> or http://<host>:<port>), got 5"]


@pytest.mark.parametrize("entry, prog", [(MAIN, "sdrl-bench"), (SEARCH, "sdrl-bench-search")])
@pytest.mark.parametrize("content", ["not a database", "damaged"])
def test_a_damaged_store_is_named_before_the_heavy_libraries_load_and_kept(tmp_path, entry, prog, content):
    """A store that is not SQLite, or one whose b-tree is overwritten: one line naming the file,
    exit 2, before the job's imports (about 10 s of them for an RL experiment), the file unchanged."""
    import sqlite3

    db = tmp_path / "mlruns" / "mlflow.db"
    db.parent.mkdir()
    if content == "not a database":
        db.write_bytes(b"these are not the bytes of a database\n" * 400)
        reasons = ("is not a usable SQLite store (file is not a database)",)
    else:
        with sqlite3.connect(db) as con:
            con.execute("CREATE TABLE t (k INTEGER PRIMARY KEY, v TEXT)")
            con.executemany("INSERT INTO t VALUES (?, ?)", [(i, "x" * 200) for i in range(2000)])
        con.close()
        page = int.from_bytes(db.read_bytes()[16:18], "big")
        with open(db, "r+b") as fh:  # a b-tree page's header in the middle of the table
            fh.seek((db.stat().st_size // page // 2) * page)
            fh.write(b"\xa5" * 512)
        reasons = ("is not a usable SQLite store (database disk image is malformed)",  # SQLite's words, by where
                   "is damaged (SQLite integrity check:")
    before = db.read_bytes()
    got = run([f"tracking.uri=sqlite:///{db}", "experiment=quick_mountain_car"] if entry == MAIN else
              [f"tracking.uri=sqlite:///{db}"], tmp_path, entry, prog)
    assert got["code"] == 2 and got["modules"] == [], got["stderr"][-2000:]
    lines = got["stderr"].strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(tuple(f"{prog}: error: tracking.uri: {db} {r}" for r in reasons)), lines
    assert lines[0].endswith("move it aside or restore it")
    assert db.read_bytes() == before
    assert sorted(p.name for p in db.parent.iterdir()) == ["mlflow.db"]  # no lock file, no Hydra run folder


@pytest.mark.parametrize("where", ["default", "given"])
def test_the_search_names_a_damaged_study_storage_before_optuna_loads(tmp_path, where):
    """The study's own SQLite file (by default ``mlruns/optuna.db``) is checked with the command
    line, as the MLflow store is: one line naming ``study.storage`` and the file, exit 2, before
    optuna, pysindy or MLflow load (8-12 s of them before), the file unchanged."""
    db = tmp_path / "mlruns" / "optuna.db" if where == "default" else tmp_path / "studies" / "s.db"
    db.parent.mkdir()
    db.write_bytes(b"these are not the bytes of a database\n" * 400)
    before = db.read_bytes()
    got = run([] if where == "default" else ["study.storage=sqlite:///studies/s.db"], tmp_path, SEARCH,
              "sdrl-bench-search", HEAVY + ("optuna",))
    assert got["code"] == 2 and got["modules"] == [], got["stderr"][-2000:]
    assert got["stderr"].strip().splitlines() == [
        f"sdrl-bench-search: error: study.storage: {db} is not a usable SQLite store (file is not a database); "
        "move it aside or restore it"]
    assert db.read_bytes() == before
    assert sorted(p.name for p in db.parent.iterdir()) == [db.name]


def test_a_study_storage_that_is_not_a_string_is_one_line(tmp_path):
    got = run(["study.storage=5"], tmp_path, SEARCH, "sdrl-bench-search", HEAVY + ("optuna",))
    assert got["code"] == 2 and got["modules"] == []
    assert got["stderr"].strip().splitlines() == [
        "sdrl-bench-search: error: study.storage: a URI is required (sqlite:///<file>, an SQLAlchemy URL or "
        "journal:<file>), got 5"]


def _free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.mark.parametrize("case", ["folder", "path", "no server", "scheme", "in memory", "no experiment", "optuna's file"])
def test_a_store_that_cannot_serve_is_named_before_the_heavy_libraries_load(tmp_path, case):
    """A tracking store that is a folder, a server that does not answer (MLflow's client retried
    it for minutes; a folder took about 2), a plain path (MLflow 3's file store refuses with a
    traceback), a scheme MLflow has no store for (a traceback), an
    in-memory SQLite store (its runs lost at exit), an empty experiment name (a traceback), an
    Optuna study's file (MLflow would add its tables to it): one line, exit 2, nothing loaded."""
    if case == "folder":
        (tmp_path / "store.db").mkdir()
        args, line = ["tracking.uri=sqlite:///store.db"], f"tracking.uri: {tmp_path / 'store.db'} is a folder, not an SQLite file"
    elif case == "path":
        (tmp_path / "runs").mkdir()
        args = [f"tracking.uri={tmp_path / 'runs'}"]
        line = (f"tracking.uri: {tmp_path / 'runs'} is a folder store, which MLflow 3 refuses (its file store is in "
                "maintenance mode); give sqlite:///<file> (sqlite:///mlruns/mlflow.db is the default) or "
                "http://<host>:<port>, or set MLFLOW_ALLOW_FILE_STORE=true")
    elif case == "no server":
        port = _free_port()
        args = [f"tracking.uri=http://127.0.0.1:{port}"]
        line = (f"tracking.uri: the tracking server at http://127.0.0.1:{port} does not answer ([Errno 111] Connection "
                "refused); start it, or fix the URI")
    elif case == "scheme":
        args = ["tracking.uri=foo://bar"]
        line = "tracking.uri: MLflow has no store for 'foo://' (sqlite:///<file>, http://<host>:<port>, or a database URL)"
    elif case == "in memory":
        args = ["tracking.uri=sqlite://"]
        line = "tracking.uri: sqlite:// is an in-memory store, lost when the process ends; give a file (sqlite:///<file>)"
    elif case == "no experiment":
        args, line = ["tracking.experiment="], "tracking.experiment: an experiment name is required, got ''"
    else:
        import optuna

        optuna.storages.RDBStorage(f"sqlite:///{tmp_path / 'study.db'}")
        args = ["tracking.uri=sqlite:///study.db"]
        line = f"tracking.uri: {tmp_path / 'study.db'} is an Optuna study storage, not an MLflow store; give another file"
    before = sorted(p.name for p in tmp_path.iterdir())
    got = run([*args, "experiment=quick_mountain_car"], tmp_path)
    assert got["code"] == 2 and got["modules"] == [], got["stderr"][-2000:]
    assert got["stderr"].strip().splitlines() == [f"sdrl-bench: error: {line}"]
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_the_search_refuses_the_mlflow_store_as_its_study_storage(tmp_path, made_store_file):
    """Optuna would add its tables to MLflow's file (and name a version mismatch): one line."""
    import shutil

    (tmp_path / "mlruns").mkdir()
    shutil.copyfile(made_store_file, tmp_path / "mlruns" / "other.db")
    before = (tmp_path / "mlruns" / "other.db").read_bytes()
    for storage, line in [
        ("sqlite:///mlruns/mlflow.db", f"sqlite:///{tmp_path / 'mlruns' / 'mlflow.db'} is the MLflow store (tracking.uri); "
                                       "give the study its own file"),
        ("sqlite:///mlruns/other.db", f"{tmp_path / 'mlruns' / 'other.db'} is an MLflow tracking store, not an Optuna "
                                      "study storage; give another file"),
    ]:
        got = run([f"study.storage={storage}"], tmp_path, SEARCH, "sdrl-bench-search", HEAVY + ("optuna",))
        assert got["code"] == 2 and got["modules"] == [], got["stderr"][-2000:]
        assert got["stderr"].strip().splitlines() == [f"sdrl-bench-search: error: study.storage: {line}"]
    assert (tmp_path / "mlruns" / "other.db").read_bytes() == before


def test_the_report_names_a_damaged_store_before_the_heavy_libraries_load(tmp_path):
    db = tmp_path / "mlruns" / "mlflow.db"
    db.parent.mkdir()
    db.write_bytes(b"these are not the bytes of a database\n" * 400)
    got = run(["--uri", f"sqlite:///{db}", "--out", str(tmp_path / "reports")], tmp_path, REPORT, "sdrl-bench-report")
    assert got["code"] == 2 and got["modules"] == []
    assert got["stderr"].strip().splitlines() == [
        f"sdrl-bench-report: error: --uri: {db} is not a usable SQLite store (file is not a database); "
        "move it aside or restore it"]
    assert not (tmp_path / "reports").exists()


def test_a_fit_command_does_not_import_torch_or_sb3(tmp_path):
    got = run(["env=mountain_car", "n_transitions=60", f"tracking.uri=sqlite:///{tmp_path / 'mlruns' / 'mlflow.db'}"],
              tmp_path)
    assert got["code"] == 0, got["stderr"][-2000:]
    assert got["modules"] == ["pysindy", "mlflow"]  # the fit and its run; nothing of the RL stack
    assert (tmp_path / "mlruns" / "mlflow.db").exists()


@pytest.mark.jax
def test_a_fit_command_does_not_load_jax_where_the_jax_extra_is_installed(tmp_path):
    """pysindy tries its SBR optimizer, whose module imports jax and then numpyro, which the
    ``[jax]`` extra does not bring: ``sdrl_bench.models`` marks that module absent first, so a fit
    no longer loads jax for nothing (0.7-0.9 s a process)."""
    import importlib.util

    pytest.importorskip("jax")
    if importlib.util.find_spec("numpyro") is not None:
        pytest.skip("numpyro is installed: pysindy's SBR loads, and jax with it, as it should")
    got = run(["env=mountain_car", "n_transitions=60", f"tracking.uri=sqlite:///{tmp_path / 'mlruns' / 'mlflow.db'}"],
              tmp_path, heavy=("pysindy", "jax", "numpyro"))
    assert got["code"] == 0, got["stderr"][-2000:]
    assert got["modules"] == ["pysindy"]


def test_the_report_refuses_a_folder_of_the_users_before_the_heavy_libraries_load(tmp_path, made_store_file):
    """``--out``/``--name`` naming a folder with the user's files: one line, exit 2, in a fraction
    of a second (4 s of pandas and MLflow before; before that, the files were deleted)."""
    import shutil

    (tmp_path / "mlruns").mkdir()
    shutil.copyfile(made_store_file, tmp_path / "mlruns" / "mlflow.db")
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "report.md").write_bytes(b"x")
    got = run(["--out", str(tmp_path), "--name", "mine", "--no-log"], tmp_path, REPORT, "sdrl-bench-report",
              HEAVY + ("pandas",))
    assert got["code"] == 2 and got["modules"] == []
    assert got["stderr"].strip().splitlines() == [
        f"sdrl-bench-report: error: --out/--name: {tmp_path / 'mine'} holds files this report did not write under the "
        "names it writes (report.md); choose another folder or move them"]
    assert (tmp_path / "mine" / "report.md").read_bytes() == b"x"
