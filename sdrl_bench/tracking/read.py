"""The read side: runs of an experiment as plain dicts, statuses, artifacts (the report's and
the search's view of the store)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from sdrl_bench import ConfigError
from sdrl_bench.tracking.client import PARENT_TAG, display_uri, mlflow_client, process_start, process_tags, system_identity


def find_runs(uri: str, experiment: str, filter_string: str = "", *, missing_ok: bool = True,
              key: str = "tracking.experiment") -> list[dict[str, Any]]:
    """Active runs of ``experiment`` matching an MLflow filter, oldest first (ties by run id):
    dicts with ``run_id``, ``experiment_id``, ``status``, ``start_time``, ``tags``, ``params``,
    ``metrics``. An unknown experiment gives [] (``missing_ok``) or a ConfigError naming ``key``."""
    client = mlflow_client(uri)
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        if missing_ok:
            return []
        raise ConfigError(f"{key}: no experiment {experiment!r} in {display_uri(uri)}")
    runs = client.search_runs([exp.experiment_id], filter_string=filter_string, max_results=50_000)
    out = [{"run_id": r.info.run_id, "experiment_id": r.info.experiment_id, "status": r.info.status,
            "start_time": r.info.start_time, "tags": dict(r.data.tags), "params": dict(r.data.params),
            "metrics": dict(r.data.metrics)} for r in runs]
    return sorted(out, key=lambda r: (r["start_time"] or 0, r["run_id"]))


def child_statuses(uri: str, experiment: str, parent_run_id: str) -> list[str]:
    exp = mlflow_client(uri).get_experiment_by_name(experiment)
    runs = mlflow_client(uri).search_runs([exp.experiment_id], filter_string=f"tags.{PARENT_TAG} = '{parent_run_id}'")
    return [r.info.status for r in runs]


def running_below(uri: str, experiment: str, root: str) -> list[str]:
    """The RUNNING runs under ``root``, at any depth and whatever their ancestors' status: the
    jobs' runs and the runs under them (a Dyna job's round runs, a fidelity cluster's surrogate
    runs). Each RUNNING run's ancestry is followed up to a run without a parent; only the
    ancestors that are not RUNNING are read one by one (a sweep's finished jobs are not loaded)."""
    running = {r["run_id"]: r["tags"].get(PARENT_TAG) for r in find_runs(uri, experiment, "attributes.status = 'RUNNING'")}
    parent_of: dict[str, str | None] = dict(running)
    client = mlflow_client(uri)

    def parent(run_id: str) -> str | None:
        if run_id not in parent_of:
            try:
                parent_of[run_id] = client.get_run(run_id).data.tags.get(PARENT_TAG)
            except Exception:  # a deleted or unknown ancestor: the chain ends there
                parent_of[run_id] = None
        return parent_of[run_id]

    out = []
    for rid in running:
        seen, up = {rid}, parent(rid)
        while up is not None and up != root and up not in seen:
            seen.add(up)
            up = parent(up)
        if up == root and rid != root:
            out.append(rid)
    return out


def list_experiments(uri: str) -> list[str]:
    """Names of the store's active experiments (an empty or missing store: [])."""
    client = mlflow_client(uri)  # a damaged store raises a ConfigError naming it
    try:
        return sorted(e.name for e in client.search_experiments())
    except Exception:  # a server that is not there holds nothing to report
        return []


def run_exists(uri: str, run_id: str) -> bool:
    """Whether the store holds a run with this id."""
    try:
        mlflow_client(uri).get_run(run_id)
        return True
    except Exception:
        return False


def list_artifacts(uri: str, run_id: str, folder: str | None = None) -> list[str]:
    """Artifact paths directly under ``folder`` of a run ([] when there are none)."""
    try:
        return [a.path for a in mlflow_client(uri).list_artifacts(run_id, folder)]
    except Exception:
        return []


def download_artifact(uri: str, run_id: str, path: str, dst: str | Path) -> Path | None:
    """Fetch one artifact of a run into ``dst``; None when the run has no such artifact."""
    Path(dst).mkdir(parents=True, exist_ok=True)
    try:
        return Path(mlflow_client(uri).download_artifacts(run_id, path, str(dst)))
    except Exception:
        return None


def owner_alive(tags: dict[str, str]) -> bool | None:
    """Whether the process that owns a run (``client.process_tags``) is alive: None when that
    cannot be told here (no tags; another host name, machine id or pid namespace, as in a
    container that shares the host name). A run of an earlier boot of this machine is dead. A
    zombie is dead: a sweep's worker killed with its driver stays one until init reaps it, which
    can come after a rerun looks (seen here: the workers of a sweep killed with SIGKILL were
    zombies a moment later, and a rerun that asked then left their runs RUNNING). A live process
    whose start is not the run's (``sdrl.pid_start``, clock ticks since boot) holds a reused
    pid: the owner is dead. Runs made before these tags existed are judged by host and pid."""
    import socket

    import psutil

    host, pid = tags.get("sdrl.host"), tags.get("sdrl.pid")
    if host != socket.gethostname() or not (pid or "").isdigit():
        return None
    machine, boot, namespace = system_identity()
    if tags.get("sdrl.machine", machine) != machine or tags.get("sdrl.pid_ns", namespace) != namespace:
        return None
    if tags.get("sdrl.boot", boot) != boot:
        return False  # this machine has rebooted since: no process of that boot lives
    try:
        if psutil.Process(int(pid)).status() == psutil.STATUS_ZOMBIE:
            return False
    except psutil.NoSuchProcess:
        return False
    except psutil.AccessDenied:
        return True
    started = tags.get("sdrl.pid_start")
    return not started or process_start(int(pid)) in (started, "")


def end_stale_runs(uri: str, experiment: str, filter_string: str, status: str = "KILLED",
                   skip_kinds: tuple[str, ...] = ()) -> list[str]:
    """End the RUNNING runs matching ``filter_string`` whose owning process is dead (same host);
    returns their ids. Runs of live processes, or of other hosts, are left alone."""
    stale = [r for r in find_runs(uri, experiment, filter_string)
             if r["status"] == "RUNNING" and r["tags"].get("sdrl.kind") not in skip_kinds
             and owner_alive(r["tags"]) is False]
    client = mlflow_client(uri)
    ended = []
    for r in stale:
        if client.get_run(r["run_id"]).info.status != "RUNNING":
            continue  # ended since the search above (a search's worker summarizing its study)
        client.set_tag(r["run_id"], "sdrl.ended_by", "a later process: its owner had died")
        client.set_terminated(r["run_id"], status)
        ended.append(r["run_id"])
    return ended


def runs_of_this_process(uri: str, experiment: str, status: str | None = None) -> list[dict[str, Any]]:
    """The runs of ``experiment`` this process owns (``sdrl.pid``/``sdrl.host``), of ``status``
    (None: any), as ``find_runs`` gives them."""
    filt = " and ".join(f"tags.`{k}` = '{v}'" for k, v in process_tags().items())
    return find_runs(uri, experiment, filt + (f" and attributes.status = '{status}'" if status else ""))


def end_runs_of_this_process(uri: str, experiment: str, status: str = "KILLED") -> list[str]:
    """End every RUNNING run this process owns: the last word of a process stopped by a signal,
    for a run whose creation the signal interrupted."""
    mine = runs_of_this_process(uri, experiment, "RUNNING")
    client = mlflow_client(uri)
    for r in mine:
        client.set_terminated(r["run_id"], status)
    return [r["run_id"] for r in mine]
