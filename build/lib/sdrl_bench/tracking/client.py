"""The tracking store and its runs: where the store is, creating it, one run's writes.

Default store: ``sqlite:///<cwd>/mlruns/mlflow.db`` with artifacts under ``mlruns/artifacts``.
``MLFLOW_TRACKING_URI`` (e.g. an ``mlflow server``) or an explicit URI takes precedence.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import tempfile
from pathlib import Path
from typing import Any
from collections.abc import Iterator, Mapping

from sdrl_bench import ConfigError

DEFAULT_DB = Path("mlruns") / "mlflow.db"
PARENT_TAG = "mlflow.parentRunId"
RUN_NAME_TAG = "mlflow.runName"

os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")


def resolve_uri(uri: str | None = None) -> str:
    """Explicit URI, else ``MLFLOW_TRACKING_URI``, else the project's SQLite store (absolute)."""
    uri = uri or os.environ.get("MLFLOW_TRACKING_URI")
    if not uri:
        return f"sqlite:///{(Path.cwd() / DEFAULT_DB).resolve()}"
    if uri.startswith("sqlite:///") and not uri.startswith("sqlite:////"):
        return f"sqlite:///{Path(uri[len('sqlite:///'):]).resolve()}"
    return uri


def display_uri(uri: str) -> str:
    """The URI as a user would type it: a SQLite store under the current folder, relative."""
    local = _sqlite_path(uri)
    if local is None:
        return uri
    try:
        return f"sqlite:///{local.relative_to(Path.cwd())}"
    except ValueError:
        return uri


def _sqlite_path(uri: str) -> Path | None:
    return Path(uri[len("sqlite:///"):]) if uri.startswith("sqlite:///") else None


def check_writable(uri: str) -> None:
    """Fail fast, naming the location, when a local store cannot be written."""
    local = _sqlite_path(uri)
    if local is None:
        return
    folder = local.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder):
            pass
        if local.exists() and not os.access(local, os.W_OK):
            raise PermissionError(f"{local} is read-only")
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise ConfigError(f"tracking.uri: cannot write the tracking store at {folder} ({reason})") from None


def mlflow_client(uri: str):
    """An ``MlflowClient`` on ``uri`` (mlflow imported on first use)."""
    from mlflow.tracking import MlflowClient

    return MlflowClient(tracking_uri=uri)


def use_wal(db: Path) -> bool:
    """Put a SQLite store in write-ahead-log mode (a setting kept in the file): readers (the
    MLflow UI, a report) no longer block the writers of a running sweep, and parallel jobs
    commit faster (``benchmarks/tracking_writes.py``). Returns whether the store is in WAL mode;
    a store busy right now is left as it is."""
    import sqlite3

    try:
        with contextlib.closing(sqlite3.connect(db, timeout=1.0)) as con:
            mode = con.execute("PRAGMA journal_mode").fetchone()[0]
            if mode != "wal":
                mode = con.execute("PRAGMA journal_mode=WAL").fetchone()[0]
        return mode == "wal"
    except sqlite3.Error:
        return False


def ensure_experiment(uri: str, name: str) -> str:
    """Create the store (tables) and the experiment if needed; returns the experiment id.

    Call this once in the driver before parallel workers start: processes racing to create
    the SQLite tables crash.
    """
    check_writable(uri)
    client = mlflow_client(uri)
    exp = client.get_experiment_by_name(name)  # creates the tables of a new store
    local = _sqlite_path(uri)
    if local is not None:
        use_wal(local)
    if exp is not None:
        return exp.experiment_id
    location = None
    if local is not None:
        location = (local.parent / "artifacts" / name).resolve().as_uri()
    try:
        return client.create_experiment(name, artifact_location=location)
    except Exception:  # created meanwhile by another process
        exp = client.get_experiment_by_name(name)
        if exp is None:
            raise
        return exp.experiment_id


def flatten(d: Mapping[str, Any], prefix: str = "") -> dict[str, str]:
    """Nested mapping -> {"a.b.c": "value"} with values as strings (lists kept as one value)."""
    out: dict[str, str] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(flatten(v, key + "."))
        else:
            out[key] = str(v)
    return out


def git_commit(cwd: str | Path | None = None) -> str:
    try:
        res = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, cwd=cwd, timeout=5)
        return res.stdout.strip() if res.returncode == 0 else "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


class Run:
    """A handle on one MLflow run: the only way the rest of the project logs."""

    def __init__(self, uri: str, run_id: str):
        self.uri = uri
        self.run_id = run_id
        self._client = mlflow_client(uri)

    def log_params(self, params: Mapping[str, Any]) -> None:
        from mlflow.entities import Param

        items = [Param(k[:250], str(v)[:6000]) for k, v in params.items()]
        for i in range(0, len(items), 100):
            self._client.log_batch(self.run_id, params=items[i : i + 100])

    def log_metrics(self, metrics: Mapping[str, float], step: int = 0) -> None:
        import math
        import time

        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        items = [Metric(k, float(v), now, step) for k, v in metrics.items() if v is not None and not math.isnan(float(v))]
        for i in range(0, len(items), 1000):
            self._client.log_batch(self.run_id, metrics=items[i : i + 1000])

    def set_tags(self, tags: Mapping[str, Any]) -> None:
        from mlflow.entities import RunTag

        self._client.log_batch(self.run_id, tags=[RunTag(k, str(v)) for k, v in tags.items()])

    def log_artifact(self, path: str | Path, artifact_path: str | None = None) -> None:
        self._client.log_artifact(self.run_id, str(path), artifact_path)

    def log_text(self, text: str, artifact_file: str) -> None:
        self._client.log_text(self.run_id, text, artifact_file)

    def log_dict(self, d: Mapping, artifact_file: str) -> None:
        self._client.log_dict(self.run_id, dict(d), artifact_file)

    def log_figure(self, figure, artifact_file: str) -> None:
        """A matplotlib ``Figure`` (built without pyplot, so nothing to close)."""
        self._client.log_figure(self.run_id, figure, artifact_file)

    def end(self, status: str = "FINISHED") -> None:
        self._client.set_terminated(self.run_id, status)


@contextlib.contextmanager
def start_run(
    uri: str,
    experiment: str,
    run_name: str,
    tags: Mapping[str, Any] | None = None,
    parent_run_id: str | None = None,
) -> Iterator[Run]:
    """Create a run; it ends FINISHED, or FAILED (KILLED on Ctrl-C) if the body raises."""
    exp_id = ensure_experiment(uri, experiment)
    all_tags = {RUN_NAME_TAG: run_name, **(tags or {})}
    if parent_run_id:
        all_tags[PARENT_TAG] = parent_run_id
    run_info = mlflow_client(uri).create_run(exp_id, tags={k: str(v) for k, v in all_tags.items()}, run_name=run_name)
    run = Run(uri, run_info.info.run_id)
    try:
        yield run
    except KeyboardInterrupt:
        run.end("KILLED")
        raise
    except BaseException:
        run.end("FAILED")
        raise
    run.end("FINISHED")


def create_parent_run(uri: str, experiment: str, run_name: str, tags: Mapping[str, Any]) -> str:
    """Create a sweep's parent run (left RUNNING; end it with ``end_run``)."""
    exp_id = ensure_experiment(uri, experiment)
    info = mlflow_client(uri).create_run(exp_id, tags={RUN_NAME_TAG: run_name, **{k: str(v) for k, v in tags.items()}}, run_name=run_name)
    return info.info.run_id


def end_run(uri: str, run_id: str, status: str) -> None:
    client = mlflow_client(uri)
    if client.get_run(run_id).info.status == "RUNNING":
        client.set_terminated(run_id, status)


def delete_run(uri: str, run_id: str) -> None:
    """Mark a run deleted (it leaves searches and the UI's default view)."""
    mlflow_client(uri).delete_run(run_id)


def log_report(uri: str, experiment: str, name: str, folder: str | Path, tags: Mapping[str, Any]) -> str:
    """A "report" run holding the report folder's files as artifacts; returns its run id."""
    with start_run(uri, experiment, f"report-{name}", {"sdrl.kind": "report", **tags}) as run:
        for path in sorted(Path(folder).rglob("*")):
            if path.is_file():
                rel = path.parent.relative_to(folder)
                run.log_artifact(path, "report" if str(rel) == "." else f"report/{rel}")
    return run.run_id
