"""Hydra callback: one MLflow parent run per multirun sweep, created in the driver.

The driver creates the tracking store and the parent run before any worker starts and writes
the parent's id and the sweep's key into the sweep folder, where each job finds them.

* **Resume.** The sweep key is a hash of the sweep's overrides and experiment: a rerun of the
  same sweep on the same store has the same key. The driver first ends the RUNNING runs that
  dead processes of this host left in the experiment, an earlier run of this sweep's among them
  (``tracking.end_runs_of_dead_processes``; ``tracking.owner_alive`` tells a dead owner); each
  job then looks for a FINISHED run of its own config under that key and, when there is one, adopts it under the new parent instead of running again
  (``cli.main``; ``resume=false`` reruns every job).
* **Stop signals.** SIGTERM or SIGINT to the driver stops the workers (terminate, then kill
  after a grace period), ends the runs they left RUNNING and the parent KILLED, and exits with
  128 + the signal's number.
* The parent ends FINISHED when the sweep ends, or FAILED if the driver exits first (a job
  raised) or any child failed.
"""

from __future__ import annotations

import atexit
import hashlib
import json
import os
import shlex
import signal
import sys
from pathlib import Path
from collections.abc import Sequence
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from sdrl_bench import redact, redact_arg, run_stop_hooks, tracking
from sdrl_bench.cli import NOT_OF_THE_RESULT

PARENT_FILE = "mlflow_parent_run_id"
KEY_FILE = "mlflow_sweep_key"
VARYING_FILE = "sweep_varying_keys.json"
SWEEP_KEY_TAG = "sdrl.sweep_key"
CONFIG_KEY_TAG = "sdrl.config_key"
WORKER_GRACE_SECONDS = 5.0


def sweep_key(overrides: list[str], experiment: str) -> str:
    """Same sweep (the same overrides, in any order, less ``cli.NOT_OF_THE_RESULT``) on the same
    experiment: same key."""
    kept = [o for o in overrides if o.partition("=")[0].lstrip("+~") not in NOT_OF_THE_RESULT]
    body = json.dumps({"overrides": sorted(kept), "experiment": experiment})
    return hashlib.sha256(body.encode()).hexdigest()[:16]


class MlflowSweepCallback(Callback):
    def __init__(self) -> None:
        self._parent: tuple[str, str, str] | None = None
        self._browse = ""
        self._key = ""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        uri = tracking.resolve_uri(config.tracking.uri)
        sweep_dir = Path(config.hydra.sweep.dir)
        experiment = config.tracking.experiment
        overrides = list(config.hydra.overrides.task)
        key = sweep_key(overrides, experiment)
        experiment_id = tracking.ensure_experiment(uri, experiment)
        tracking.end_runs_of_dead_processes(uri, experiment)  # an earlier run of this sweep's, or any command's
        run_id = tracking.create_parent_run(
            uri, experiment, f"sweep-{sweep_dir.name}",
            {"sdrl.kind": "sweep", "sdrl.sweep_dir": str(sweep_dir.resolve()),
             "sdrl.overrides": " ".join(redact_arg(o) for o in overrides), SWEEP_KEY_TAG: key,
             **tracking.standard_tags("sdrl-bench -m")},
        )
        sweep_dir.mkdir(parents=True, exist_ok=True)
        (sweep_dir / PARENT_FILE).write_text(run_id)
        (sweep_dir / KEY_FILE).write_text(key)
        (sweep_dir / VARYING_FILE).write_text(json.dumps(varying_keys(overrides)))
        self._parent = (uri, run_id, experiment)
        self._key = key
        self._browse = tracking.browse_hint(uri, experiment_id, run_id, tracking.display_uri(uri))
        print(f"sdrl-bench: sweep run {run_id} in {tracking.display_uri(uri)}, experiment {experiment!r}: "
              "its jobs' runs are its children", flush=True)
        atexit.register(self._abort)
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, self._on_stop_signal)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        if self._parent is not None:
            uri, run_id, experiment = self._parent
            failed = any(s != "FINISHED" for s in tracking.child_statuses(uri, experiment, run_id))
            try:
                tracking.summarize_sweep(uri, run_id)  # overrides as params, best child, description
            except Exception as exc:  # the summary is a courtesy: the sweep's status still counts
                print(f"sdrl-bench: could not summarize sweep run {run_id}: {exc}")
            try:  # the earlier runs of this sweep (a chain of reruns too): where their jobs went
                earlier = tracking.find_runs(uri, experiment, f"tags.`{SWEEP_KEY_TAG}` = '{self._key}' "
                                                              "and tags.`sdrl.kind` = 'sweep'")
                tracking.note_adoptions(uri, run_id, [r["run_id"] for r in earlier])
            except Exception as exc:  # a courtesy too
                print(f"sdrl-bench: could not note this rerun on the earlier runs of sweep {self._key}: {exc}")
            self._finish("FAILED" if failed else "FINISHED")
            ui = [] if tracking.ui_base(uri) else ["--ui-url", "http://127.0.0.1:5000"]  # links for `mlflow ui`
            report = shlex.join(["sdrl-bench-report", "--uri", tracking.display_uri(uri), "--experiment", experiment,
                                 "--parent-run", run_id, "--name", f"sweep-{run_id[:8]}", *ui])
            print(f"sdrl-bench: sweep run {run_id} ended {'FAILED' if failed else 'FINISHED'}; its report: {report}\n"
                  f"{self._browse}", flush=True)

    def _finish(self, status: str) -> None:
        if self._parent is not None:
            uri, run_id, _ = self._parent
            self._parent = None
            tracking.end_run(uri, run_id, status)

    def _abort(self) -> None:
        """The driver exits before the sweep ended (a job raised): stop the other workers, end
        the runs they left RUNNING (and the runs under those) KILLED and the parent FAILED."""
        if self._parent is None:
            return
        stop_children(WORKER_GRACE_SECONDS)
        uri, run_id, experiment = self._parent
        for rid in tracking.running_below(uri, experiment, run_id):
            tracking.end_run(uri, rid, "KILLED")
        self._finish("FAILED")

    def _on_stop_signal(self, signum: int, frame: Any) -> None:
        """Stop the workers, end what they left RUNNING and the parent KILLED, exit."""
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, signal.SIG_IGN)  # one cleanup, however many signals arrive
        run_stop_hooks()  # a tracking server that does not answer costs seconds from here on
        n_workers = stop_children(WORKER_GRACE_SECONDS)
        n_runs, unanswered = 0, None
        if self._parent is not None:
            uri, run_id, experiment = self._parent
            try:  # the jobs' runs and the runs under them (Dyna rounds, fidelity surrogates)
                for rid in tracking.running_below(uri, experiment, run_id):
                    tracking.end_run(uri, rid, "KILLED")
                    n_runs += 1
                self._finish("KILLED")
            except Exception:  # the store is gone: say so, and exit all the same
                unanswered = redact(uri)
        name = signal.Signals(signum).name
        if unanswered:
            ended = (f"the tracking store at {unanswered} did not answer, so the sweep's runs may still show RUNNING "
                     f"({n_runs} ended KILLED; the next command on this experiment ends the rest)")
        else:
            ended = f"{n_runs} run(s) and the sweep's parent run ended KILLED"
        print(f"sdrl-bench: stopped by {name}: {n_workers} worker process(es) stopped, {ended}; "
              "rerun the same command to resume", file=sys.stderr, flush=True)
        sys.stdout.flush()
        os._exit(128 + signum)  # joblib would otherwise wait for (or restart) its workers


def stop_children(grace: float) -> int:
    """Terminate this process's descendants (joblib's workers), kill those still alive after
    ``grace`` seconds; returns how many there were."""
    import psutil

    children = psutil.Process().children(recursive=True)
    for c in children:
        try:
            c.terminate()
        except psutil.NoSuchProcess:
            pass
    _, alive = psutil.wait_procs(children, timeout=grace)
    for c in alive:
        try:
            c.kill()
        except psutil.NoSuchProcess:
            pass
    return len(children)


def varying_keys(overrides: list[str]) -> list[str]:
    """The keys a sweep varies, those with the most values first (a job's run name leads with them)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parsed = [o for o in OverridesParser.create().parse_overrides(overrides) if o.is_sweep_override()]
    counts = {o.key_or_group: len(list(o.sweep_string_iterator())) for o in parsed}
    return sorted(counts, key=lambda k: -counts[k])


def job_label(sweep_dir: str | Path, job_overrides: list[str], groups: Sequence[str] = ()) -> str:
    """A sweep job told from its siblings in a few characters (the UI's runs table shows about
    18): its values of the swept keys, the most varied first; a config group's option as it is
    (``poly_trig``), another key as ``name=value`` by its last part (``seed=3``)."""
    path = Path(sweep_dir) / VARYING_FILE
    keys = json.loads(path.read_text()) if path.is_file() else []
    values = dict(o.lstrip("+~").split("=", 1) for o in job_overrides if "=" in o)
    values = {k: redact_arg(v) for k, v in values.items()}
    parts = [values[k] if k in groups else f"{k.rsplit('.', 1)[-1]}={values[k]}" for k in keys if k in values]
    return " ".join(parts) or " ".join(redact_arg(o) for o in job_overrides)


def sweep_context(sweep_dir: str | Path) -> tuple[str | None, str | None]:
    """(parent run id, sweep key) a job finds in its sweep folder (None, None outside a sweep)."""
    folder = Path(sweep_dir)
    parent, key = folder / PARENT_FILE, folder / KEY_FILE
    return (parent.read_text().strip() if parent.is_file() else None,
            key.read_text().strip() if key.is_file() else None)
