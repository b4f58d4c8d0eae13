"""Where studies live: Optuna storage URLs, studies checked against what they were created
for, and the one MLflow parent run per study (agreed on by every worker).

Default storage: ``sqlite:///<cwd>/mlruns/optuna.db``. Any SQLAlchemy URL works (PostgreSQL,
MySQL: shared by many machines), and ``journal:<path>`` selects Optuna's JournalStorage on a
file (a shared disk). SQLite and other RDB storages record heartbeats: a trial whose process
died (SIGKILL, a lost node) is marked FAIL after the grace period, and its MLflow run KILLED.
"""

from __future__ import annotations

import contextlib
import re
import time
import warnings
from pathlib import Path
from typing import Any
from collections.abc import Callable, Iterator, Mapping

import optuna

from sdrl_bench import ConfigError, redact, tracking
from sdrl_bench.search.space import space_differences

FINGERPRINT_ATTR = "sdrl.fingerprint"
_NAME = re.compile(r"^[A-Za-z0-9_.\-]+$")


def open_storage(
    url: str,
    heartbeat_interval: int | None = None,
    grace_period: int | None = None,
    on_stale: Callable[[optuna.Study, optuna.trial.FrozenTrial], None] | None = None,
) -> optuna.storages.BaseStorage:
    """Open (creating tables or files if needed) the storage at a resolved URL.

    Raises ``ConfigError`` naming the URL when it cannot be reached or written, so a bad
    storage fails before any data is collected or any trial starts.
    """
    try:
        if url.startswith("journal:"):
            from optuna.storages.journal import JournalFileBackend, JournalStorage

            path = Path(url[len("journal:"):])
            path.parent.mkdir(parents=True, exist_ok=True)
            return JournalStorage(JournalFileBackend(str(path)))
        engine_kwargs: dict[str, Any] = {}
        if url.startswith("sqlite:///"):
            Path(url[len("sqlite:///"):]).parent.mkdir(parents=True, exist_ok=True)
            engine_kwargs["connect_args"] = {"timeout": 60}  # several workers on one file
        elif url.startswith(("postgresql", "mysql")):
            engine_kwargs["connect_args"] = {"connect_timeout": 10}
            engine_kwargs["pool_pre_ping"] = True
        for attempt in range(3):
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)  # heartbeats
                    storage = optuna.storages.RDBStorage(
                        url, engine_kwargs=engine_kwargs, heartbeat_interval=heartbeat_interval,
                        grace_period=grace_period, heartbeat_stale_trial_callback=on_stale,
                    )
                if url.startswith("sqlite:///"):
                    _fast_sqlite(storage)
                return storage
            except Exception as exc:  # processes racing to create the tables: try again
                if "already exists" not in str(exc) or attempt == 2:
                    raise
                time.sleep(0.2 * (attempt + 1))
        raise AssertionError("unreachable")
    except ConfigError:
        raise
    except Exception as exc:
        reason = str(getattr(exc, "orig", None) or exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ConfigError(f"study.storage: cannot open {redact(url)} ({type(exc).__name__}: {reason})") from None


def local_file(url: str) -> Path | None:
    """The file of a local storage URL (``sqlite:///<path>``, ``journal:<path>``), else None."""
    local = next((url[len(p):] for p in ("sqlite:///", "journal:") if url.startswith(p)), None)
    return None if local is None else Path(local.split("?")[0])


@contextlib.contextmanager
def summary_lock(url: str, study: str, on_wait: Callable[[], None] | None = None) -> Iterator[None]:
    """Held while a worker summarizes study ``study`` (``search.summary.summarize``), so that the
    workers of one study that finish together summarize one after the other: the second reads
    the first's refit of the best trial and refits nothing, and they do not write the parent
    run's params at the same moment. A lock file beside a local storage (``<file>.<study>.summary.lock``,
    ``flock``), which covers workers on one host (Hydra's joblib and submitit_local launchers);
    a server storage has none, and workers on several hosts that finish in the same seconds may
    each refit the best trial (an extra refit run; the parent's params are safe either way,
    ``tracking.Run.log_params``). ``on_wait``: called once if another worker holds it."""
    path = local_file(url)
    if path is None:
        yield
        return
    with tracking.store_lock(path.with_name(f"{path.name}.{study}.summary"), on_wait):
        yield


def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
    cursor = dbapi_connection.cursor()
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA synchronous=NORMAL")
    cursor.close()


def _fast_sqlite(storage: optuna.storages.RDBStorage) -> None:
    """Write-ahead log and no fsync per commit: a trial costs ~10 ms of storage instead of
    ~300 ms on a disk with slow syncs. Still safe for several processes on one machine and
    against a killed process (a committed trial is never lost); on a network file system use an
    RDB server or a journal file instead."""
    from sqlalchemy import event

    event.listen(storage.engine, "connect", _sqlite_pragmas)
    storage.engine.dispose()


def check_study_name(name: str) -> str:
    if not name or not _NAME.match(name):
        raise ConfigError(f"study.name: {name!r} must be letters, digits, '_', '.' or '-'")
    return name


def open_study(
    storage: optuna.storages.BaseStorage,
    name: str,
    directions: list[str],
    fingerprint: Mapping[str, Any],
    sampler: optuna.samplers.BaseSampler,
    pruner: optuna.pruners.BasePruner,
    where: str = "",
) -> optuna.Study:
    """Create the study, or load it to resume, after checking that it was created for the same
    search space, objectives and data (``fingerprint``); a mismatch is a ``ConfigError``."""
    study = optuna.create_study(
        study_name=check_study_name(name), storage=storage, sampler=sampler, pruner=pruner,
        directions=directions, load_if_exists=True,
    )
    stored = study.user_attrs.get(FINGERPRINT_ATTR)
    stored_dirs = [d.name.lower() for d in study.directions]
    if stored_dirs != list(directions):
        raise ConfigError(
            f"study.name: study '{name}'{where} has objectives {stored_dirs}, not {list(directions)}; "
            "use another study.name"
        )
    if stored is None:
        study.set_user_attr(FINGERPRINT_ATTR, dict(fingerprint))
        return study
    diffs = fingerprint_differences(stored, fingerprint)
    if diffs:
        shown = "; ".join(diffs[:4]) + ("; ..." if len(diffs) > 4 else "")
        raise ConfigError(
            f"study.name: study '{name}'{where} was created with a different setup ({shown}); "
            "use another study.name or the stored settings"
        )
    return study


def fingerprint_differences(stored: Mapping[str, Any], requested: Mapping[str, Any]) -> list[str]:
    """Differences between two study fingerprints (the space compared parameter by parameter)."""
    diffs = space_differences(stored.get("space", {}), requested.get("space", {}))
    diffs = [f"search space: {d}" for d in diffs]
    for key in sorted((set(stored) | set(requested)) - {"space"}):
        a, b = stored.get(key), requested.get(key)
        if a != b:
            if isinstance(a, Mapping) and isinstance(b, Mapping):
                diffs += [f"{key}.{k}: {a.get(k)!r} -> {b.get(k)!r}" for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
            else:
                diffs.append(f"{key}: {a!r} -> {b!r}")
    return diffs


def study_parent_run(uri: str, experiment: str, study: str, storage_label: str, tags: Mapping[str, Any]) -> str:
    """The MLflow parent run of a study, created on first use and found again on resume.

    Workers starting together may each create one; all then agree on the oldest (by start
    time, then run id) and the others delete their own, so a study keeps exactly one parent.
    """
    filt = f"tags.`sdrl.kind` = 'study' and tags.`sdrl.study` = '{study}' and tags.`sdrl.storage` = '{storage_label}'"
    runs = tracking.find_runs(uri, experiment, filt)
    if runs:
        return runs[0]["run_id"]
    all_tags = {**tags, "sdrl.kind": "study", "sdrl.study": study, "sdrl.storage": storage_label}
    mine = tracking.create_parent_run(uri, experiment, f"study-{study}", all_tags)
    winner = tracking.find_runs(uri, experiment, filt)[0]["run_id"]
    if winner != mine:
        tracking.delete_run(uri, mine)
    return winner
