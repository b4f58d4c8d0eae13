"""The run lifecycle every tracked job shares: fit, train, Dyna, and the search's trials and refits.

One helper (as lightning-hydra-template's ``task_wrapper`` owns a task's start and end) so that
every run of the harness is made the same way: the store's experiment, the run with its kind,
MLflow's standard tags (user, source, commit: the UI's columns) and the job's own tags, its
resolved config as lean params and ``config.yaml``, a description, system metrics while the body
runs, and its end: FINISHED, FAILED if the body raises, KILLED on a stop signal (``start_run``).
A top-level run first ends the runs of its experiment that dead processes of this host left
RUNNING (``end_runs_of_dead_processes``, which a sweep's driver and a search also call before
their parent runs): a single command killed with SIGKILL, or stopped while its tracking server
was down, has nobody else to end its runs.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator, Mapping
from typing import Any

from sdrl_bench.tracking.client import Run, sqlite_path, start_run
from sdrl_bench.tracking.read import end_stale_runs
from sdrl_bench.tracking.meta import log_config, set_description, standard_tags, system_metrics


@contextlib.contextmanager
def tracked_run(uri: str, experiment: str, run_name: str, kind: str, tags: Mapping[str, Any] | None = None,
                parent: str | None = None, *, source: str | None = None, config: Mapping[str, Any] | None = None,
                task: str | None = None, description: str | None = None, system: bool = False) -> Iterator[Run]:
    """A run of ``kind`` (``sdrl.kind``) under ``parent``, as the module docstring says.

    ``source``: the command the UI shows (default ``sdrl-bench task=<task or kind>``); ``config``:
    the resolved config as a plain dict (logged with ``log_config``); ``system``: sample system
    metrics while the body runs (long jobs: training, Dyna)."""
    name = source or f"sdrl-bench task={task or kind}"
    if parent is None:
        end_runs_of_dead_processes(uri, experiment)
    all_tags = {"sdrl.kind": kind, **standard_tags(name), **(tags or {})}
    with start_run(uri, experiment, run_name, all_tags, parent) as run:
        run.log_metrics(machine_load("start"))
        if config is not None:
            log_config(run, config, uri, task=task or kind)
        if description:
            set_description(run, description)
        with system_metrics(run) if system else contextlib.nullcontext():
            yield run
        run.log_metrics(machine_load("end"))


def end_runs_of_dead_processes(uri: str, experiment: str, prog: str = "sdrl-bench") -> list[str]:
    """End KILLED every RUNNING run of ``experiment`` whose owning process on this host is dead
    (``read.end_stale_runs``), saying so in one line on stderr; returns their ids. That is what a
    ``kill -9``, an out-of-memory kill or a tracking server that died under a stopped command left
    behind. Runs of live processes, of other hosts or of other pid namespaces are left alone, and
    so are studies' parent runs: a study's workers share its parent, whose maker may die while
    the others work on (each worker ends it when it finishes)."""
    if (local := sqlite_path(uri)) is not None and not local.is_file():
        return []  # a new store: nothing to end, and no store to make before the run does
    ended = end_stale_runs(uri, experiment, "attributes.status = 'RUNNING'", skip_kinds=("study",))
    if ended:
        print(f"{prog}: ended {len(ended)} run(s) of experiment {experiment!r} KILLED that processes of this host "
              "left RUNNING when they died (tag sdrl.ended_by)", file=sys.stderr)
    return ended


def machine_load(when: str) -> dict[str, float]:
    """The machine's load as the run saw it (``machine/load1_<when>``: the 1-minute load average,
    beside ``machine/cpus``): how many processes shared the cores, for the report to say."""
    import os

    try:
        load1 = os.getloadavg()[0]
    except OSError:  # no load average on this platform
        return {}
    return {f"machine/load1_{when}": float(load1), "machine/cpus": float(os.cpu_count() or 1)}
