"""Hydra callback: one MLflow parent run per multirun sweep, created in the driver.

The driver creates the tracking store and the parent run before any worker starts (workers
racing to create SQLite tables crash) and writes the parent's id into the sweep folder, where
each job finds it. The parent ends FINISHED when the sweep ends, or FAILED if the driver exits
first (a job raised) or any child failed.
"""

from __future__ import annotations

import atexit
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from sdrl_bench import tracking

PARENT_FILE = "mlflow_parent_run_id"


class MlflowSweepCallback(Callback):
    def __init__(self) -> None:
        self._parent: tuple[str, str, str] | None = None

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        uri = tracking.resolve_uri(config.tracking.uri)
        sweep_dir = Path(config.hydra.sweep.dir)
        experiment = config.tracking.experiment
        run_id = tracking.create_parent_run(
            uri, experiment, f"sweep-{sweep_dir.name}",
            {"sdrl.kind": "sweep", "sdrl.sweep_dir": str(sweep_dir.resolve()),
             "sdrl.overrides": " ".join(config.hydra.overrides.task),
             **tracking.standard_tags("sdrl-bench -m")},
        )
        sweep_dir.mkdir(parents=True, exist_ok=True)
        (sweep_dir / PARENT_FILE).write_text(run_id)
        self._parent = (uri, run_id, experiment)
        atexit.register(self._finish, "FAILED")

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        if self._parent is not None:
            uri, run_id, experiment = self._parent
            failed = any(s != "FINISHED" for s in tracking.child_statuses(uri, experiment, run_id))
            try:
                tracking.summarize_sweep(uri, run_id)  # overrides as params, best child, description
            except Exception as exc:  # the summary is a courtesy: the sweep's status still counts
                print(f"sdrl-bench: could not summarize sweep run {run_id}: {exc}")
            self._finish("FAILED" if failed else "FINISHED")

    def _finish(self, status: str) -> None:
        if self._parent is not None:
            uri, run_id, _ = self._parent
            self._parent = None
            tracking.end_run(uri, run_id, status)


def parent_run_id(sweep_dir: str | Path) -> str | None:
    path = Path(sweep_dir) / PARENT_FILE
    return path.read_text().strip() if path.is_file() else None
