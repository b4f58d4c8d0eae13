"""The one door to MLflow: every MLflow call of the project is in this module.

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


def _client(uri: str):
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
    client = _client(uri)
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
        self._client = _client(uri)

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
    run_info = _client(uri).create_run(exp_id, tags={k: str(v) for k, v in all_tags.items()}, run_name=run_name)
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
    info = _client(uri).create_run(exp_id, tags={RUN_NAME_TAG: run_name, **{k: str(v) for k, v in tags.items()}}, run_name=run_name)
    return info.info.run_id


def end_run(uri: str, run_id: str, status: str) -> None:
    client = _client(uri)
    if client.get_run(run_id).info.status == "RUNNING":
        client.set_terminated(run_id, status)


def find_runs(uri: str, experiment: str, filter_string: str = "") -> list[dict[str, Any]]:
    """Active runs of ``experiment`` matching an MLflow filter, oldest first (ties by run id):
    dicts with ``run_id``, ``status``, ``start_time``, ``tags``, ``params``, ``metrics``."""
    client = _client(uri)
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        return []
    runs = client.search_runs([exp.experiment_id], filter_string=filter_string, max_results=50000)
    out = [
        {"run_id": r.info.run_id, "status": r.info.status, "start_time": r.info.start_time,
         "tags": dict(r.data.tags), "params": dict(r.data.params), "metrics": dict(r.data.metrics)}
        for r in runs
    ]
    return sorted(out, key=lambda r: (r["start_time"] or 0, r["run_id"]))


def delete_run(uri: str, run_id: str) -> None:
    """Mark a run deleted (it leaves searches and the UI's default view)."""
    _client(uri).delete_run(run_id)


def child_statuses(uri: str, experiment: str, parent_run_id: str) -> list[str]:
    exp = _client(uri).get_experiment_by_name(experiment)
    runs = _client(uri).search_runs([exp.experiment_id], filter_string=f"tags.{PARENT_TAG} = '{parent_run_id}'")
    return [r.info.status for r in runs]


def runs_as_data(uri: str, experiment: str, filter_string: str = "") -> list[dict[str, Any]]:
    """An experiment's runs as plain dicts (run_id, status, tags, metrics), newest first, for
    pure comparisons (``compare.py``); an unknown experiment raises ConfigError."""
    client = _client(uri)
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        raise ConfigError(f"tracking.experiment: no experiment {experiment!r} in {uri}")
    runs = client.search_runs([exp.experiment_id], filter_string=filter_string, max_results=50_000)
    return [{"run_id": r.info.run_id, "status": r.info.status, "tags": dict(r.data.tags),
             "metrics": dict(r.data.metrics)} for r in runs]


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


# ---------------------------------------------------------------------- RL transfer runs
def sb3_logger(run: Run, prefix: str):
    """An SB3 Logger whose only output is this run: SB3's training metrics reach MLflow here."""
    from stable_baselines3.common.logger import KVWriter, Logger

    class MlflowKVWriter(KVWriter):
        def write(self, key_values, key_excluded, step=0):
            numeric = {f"{prefix}/{k}": v for k, v in key_values.items()
                       if isinstance(v, (int, float)) and not isinstance(v, bool)}
            run.log_metrics(numeric, step=int(step))

        def close(self):
            pass

    return Logger(folder=None, output_formats=[MlflowKVWriter()])


def log_curve_point(run: Run, arm: str, step: int, mean: float, std: float) -> None:
    run.log_metrics({f"{arm}/curve_return_mean": mean, f"{arm}/curve_return_std": std}, step=step)


def log_arm(run: Run, arm_result, metrics: Mapping[str, float]) -> None:
    """An arm's accounting metrics (prefixed ``<arm>/``), its curve and its trained agent."""
    import pandas as pd

    arm = arm_result.arm
    run.log_metrics({f"{arm}/{k}": v for k, v in metrics.items()})
    if arm_result.surrogate_stats:
        run.log_metrics({f"{arm}/surrogate_{k}": v for k, v in arm_result.surrogate_stats.items()})
    c = arm_result.curve
    curve = pd.DataFrame({"train_steps": c.steps, "return_mean": c.means, "return_std": c.stds, "train_wall_seconds": c.wall})
    run.log_text(curve.to_csv(index=False), f"curves/{arm}.csv")
    run.log_text(pd.DataFrame({"return": arm_result.final_returns, "success": arm_result.final_successes}).to_csv(index=False),
                 f"final_eval/{arm}.csv")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"{arm}.zip"
        arm_result.model.save(path)
        run.log_artifact(path, "agents")


def find_real_arm(uri: str, experiment: str, key: str) -> dict | None:
    """A finished run whose real arm has the same key: its id, real/* metrics and curve."""
    client = _client(uri)
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        return None
    runs = client.search_runs([exp.experiment_id], filter_string=f"tags.real_arm_key = '{key}' and attributes.status = 'FINISHED'",
                              order_by=["attributes.start_time DESC"], max_results=5)
    for r in runs:
        if "real/final_return_mean" in r.data.metrics and r.data.tags.get("real_arm_reused_from") is None:
            return {"run_id": r.info.run_id, "metrics": {k: v for k, v in r.data.metrics.items() if k.startswith("real/")}}
    return None


def reuse_real_arm(run: Run, found: dict, local_dir: str | Path) -> tuple[Path, Path]:
    """Copy a reused real arm's metrics and curve into ``run``; returns (agent zip, curve CSV)."""
    run.log_metrics(found["metrics"])
    run.set_tags({"real_arm_reused_from": found["run_id"]})
    client = _client(run.uri)
    curve = client.download_artifacts(found["run_id"], "curves/real.csv", str(local_dir))
    run.log_artifact(curve, "curves")
    for m in client.get_metric_history(found["run_id"], "real/curve_return_mean"):
        run.log_metrics({"real/curve_return_mean": m.value}, step=m.step)
    return Path(client.download_artifacts(found["run_id"], "agents/real.zip", str(local_dir))), Path(curve)


# ---------------------------------------------------------------------- report (read side)
def list_experiments(uri: str) -> list[str]:
    """Names of the store's active experiments (an empty or missing store: [])."""
    try:
        return sorted(e.name for e in _client(uri).search_experiments())
    except Exception:  # a store that cannot be opened holds nothing to report
        return []


def report_runs(uri: str, experiment: str, filter_string: str = "") -> list[dict[str, Any]]:
    """An experiment's active runs for the report: run_id, experiment_id, status, start_time,
    tags, params, metrics; oldest first. An unknown experiment raises ConfigError."""
    client = _client(uri)
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        raise ConfigError(f"--experiment: no experiment {experiment!r} in {display_uri(uri)}")
    runs = client.search_runs([exp.experiment_id], filter_string=filter_string, max_results=50_000)
    out = [{"run_id": r.info.run_id, "experiment_id": r.info.experiment_id, "status": r.info.status,
            "start_time": r.info.start_time, "tags": dict(r.data.tags), "params": dict(r.data.params),
            "metrics": dict(r.data.metrics)} for r in runs]
    return sorted(out, key=lambda r: (r["start_time"] or 0, r["run_id"]))


def run_exists(uri: str, run_id: str) -> bool:
    """Whether the store holds a run with this id."""
    try:
        _client(uri).get_run(run_id)
        return True
    except Exception:
        return False


def list_artifacts(uri: str, run_id: str, folder: str | None = None) -> list[str]:
    """Artifact paths directly under ``folder`` of a run ([] when there are none)."""
    try:
        return [a.path for a in _client(uri).list_artifacts(run_id, folder)]
    except Exception:
        return []


def download_artifact(uri: str, run_id: str, path: str, dst: str | Path) -> Path | None:
    """Fetch one artifact of a run into ``dst``; None when the run has no such artifact."""
    Path(dst).mkdir(parents=True, exist_ok=True)
    try:
        return Path(_client(uri).download_artifacts(run_id, path, str(dst)))
    except Exception:
        return None


def log_report(uri: str, experiment: str, name: str, folder: str | Path, tags: Mapping[str, Any]) -> str:
    """A "report" run holding the report folder's files as artifacts; returns its run id."""
    with start_run(uri, experiment, f"report-{name}", {"sdrl.kind": "report", **tags}) as run:
        for path in sorted(Path(folder).rglob("*")):
            if path.is_file():
                rel = path.parent.relative_to(folder)
                run.log_artifact(path, "report" if str(rel) == "." else f"report/{rel}")
    return run.run_id
