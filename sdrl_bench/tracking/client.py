"""The tracking store and its runs: where the store is, creating it, one run's writes.

Default store: ``sqlite:///<cwd>/mlruns/mlflow.db`` with artifacts under ``mlruns/artifacts``.
``MLFLOW_TRACKING_URI`` (e.g. an ``mlflow server``) or an explicit URI takes precedence.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import platform
import re
import socket
import subprocess
import tempfile
from pathlib import Path
from typing import Any
from collections.abc import Callable, Iterator, Mapping

from sdrl_bench import ConfigError, file_in_the_way, on_stop_signal, redact, stop_signal_received, stop_signals_held

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


def uri_key(given: str | None, key: str = "tracking.uri") -> str:
    """What named the store ``resolve_uri(given)`` finds, for messages: ``key`` (where the user gave
    a URI), else ``MLFLOW_TRACKING_URI`` when that set it, else ``tracking.uri`` (the default)."""
    if given or not os.environ.get("MLFLOW_TRACKING_URI"):
        return key if given else "tracking.uri"
    return "MLFLOW_TRACKING_URI"


def display_uri(uri: str) -> str:
    """The URI as a user would type it (a SQLite store under the current folder, relative), its
    password hidden (``redact``): what messages and reports show."""
    local = sqlite_path(uri)
    if local is None:
        return redact(uri)
    try:
        return f"sqlite:///{local.relative_to(Path.cwd())}"
    except ValueError:
        return uri


def sqlite_path(uri: str) -> Path | None:
    return Path(uri[len("sqlite:///"):]) if uri.startswith("sqlite:///") else None


def check_writable(uri: str) -> None:
    """Fail fast, naming the location, when a local store cannot be written."""
    local = sqlite_path(uri)
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
        blocker = file_in_the_way(folder)
        if blocker is not None:  # mkdir's "File exists" names no file
            reason = f"{blocker} is a file, not a folder"
        raise ConfigError(f"tracking.uri: cannot write the tracking store at {folder} ({reason})") from None


STOP_SERVER_WAITS = {"MLFLOW_HTTP_REQUEST_MAX_RETRIES": 1, "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR": 1,
                     "MLFLOW_HTTP_REQUEST_TIMEOUT": 5}
"""MLflow's waits on a tracking server once a stop signal has arrived (caps: a user's lower
setting stays). Its defaults (7 retries, backoff factor 2, 120 s a request) made a stopped
command whose server had died retry each of its last requests for minutes before it exited."""


def _short_server_waits() -> None:
    """After a stop signal, each of the process's remaining requests to a tracking server (ending
    its runs KILLED, the last word's query) gives up within seconds (``STOP_SERVER_WAITS``; MLflow
    reads these variables on every request). Hand-written: MLflow has no call for it."""
    for name, cap in STOP_SERVER_WAITS.items():
        try:
            current = float(os.environ.get(name, "inf"))
        except ValueError:
            current = float("inf")
        if not current <= cap:
            os.environ[name] = str(cap)


on_stop_signal(_short_server_waits)

_READY: set[str] = set()


def mlflow_client(uri: str):
    """An ``MlflowClient`` on ``uri`` (mlflow imported on first use).

    A local SQLite store is checked and opened once per process under a file lock
    (``store_lock``): its integrity is checked (a damaged file is named in one line, before any
    work), and a new store's tables are created, or an old one's migrated, by one process at a
    time (processes racing to create the tables crash and can leave the store unusable).

    On a server, MLflow prints two lines with the run's and the experiment's addresses each time
    a run ends, credentials in the URI included; the commands print the address of the run that
    matters, without them (``meta.browse_hint``), so MLflow's lines are off unless the user has
    set ``MLFLOW_SUPPRESS_PRINTING_URL_TO_STDOUT`` to another value.
    """
    from mlflow.tracking import MlflowClient

    logging.getLogger("mlflow").setLevel(logging.WARNING)  # its INFO chatter (table creation, monitors)
    os.environ.setdefault("MLFLOW_SUPPRESS_PRINTING_URL_TO_STDOUT", "true")
    local = sqlite_path(uri)
    if local is None:
        return MlflowClient(tracking_uri=uri)
    if uri in _READY:
        return _StopsHeld(MlflowClient(tracking_uri=uri))
    with store_lock(local):
        check_integrity(local)
        try:
            client = MlflowClient(tracking_uri=uri)
            client.search_experiments(max_results=1)  # creates or migrates the tables
        except Exception as exc:
            detail = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise ConfigError(f"tracking.uri: cannot open the tracking store {local} ({detail[:200]})") from None
        use_wal(local)
    _READY.add(uri)
    return _StopsHeld(client)


class _StopsHeld:
    """An ``MlflowClient`` on a local SQLite store whose every call holds stop signals
    (``stop_signals_held``): a stop that lands inside SQLAlchemy's session or pool bookkeeping can
    leave the process's store connection unusable, and the stop's own last word (ending the
    process's runs KILLED) then failed; seen once in about ten CI runs of a search stopped
    mid-trial, which said its store "did not answer". A held stop is raised when the call
    returns, milliseconds later. A server's calls are not held: a stop must cut their retries
    short (``STOP_SERVER_WAITS``). Hand-written: MLflow has no hook around its store calls."""

    def __init__(self, client):
        self._client = client

    def __getattr__(self, name: str):
        attr = getattr(self._client, name)
        if not callable(attr):
            return attr

        @functools.wraps(attr)
        def held(*args, **kwargs):
            with stop_signals_held():
                return attr(*args, **kwargs)

        return held


@contextlib.contextmanager
def store_lock(db: Path, on_wait: Callable[[], None] | None = None) -> Iterator[None]:
    """An exclusive lock across processes (``flock`` on ``<db>.lock`` beside the store);
    ``on_wait`` is called once when another process holds it, before waiting for it."""
    import fcntl

    db.parent.mkdir(parents=True, exist_ok=True)
    with open(db.with_name(db.name + ".lock"), "a+") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            if on_wait is not None:
                on_wait()
            fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


_INTACT: dict[tuple[Path, str], tuple[int, int]] = {}

_MLFLOW_SCHEMES = re.compile(r"^(sqlite|https?|file|databricks|databricks-uc|uc|postgresql|mysql|mssql)(\+[\w-]+)?$")
_OTHER_KIND = {  # tables that mark a SQLite file as the other tool's: MLflow's store, an Optuna study's
    "mlflow": ({"studies", "trials"}, {"experiments", "runs"}, "an Optuna study storage, not an MLflow store"),
    "optuna": ({"experiments", "runs"}, {"studies"}, "an MLflow tracking store, not an Optuna study storage"),
}


def check_store(uri: str, key: str = "tracking.uri", kind: str = "mlflow", reach: bool = False) -> None:
    """What can be told of the store at ``uri`` before a job's libraries load, each failure a
    ConfigError naming ``key`` (where the user gave the URI): a folder (a path or ``file://``: MLflow
    3 refuses its file store unless ``MLFLOW_ALLOW_FILE_STORE`` is set), a local SQLite file that is a folder,
    damaged, or the other tool's (``kind``: ``mlflow`` or ``optuna``; each would add its tables to
    the other's file), an in-memory SQLite URI (its runs would be lost when the process ends), a
    scheme MLflow has no store for, and with ``reach`` a tracking server that does not answer
    (MLflow's client would retry it for minutes)."""
    if uri in ("sqlite://", "sqlite:///:memory:") or uri.startswith("sqlite:///:memory:"):
        raise ConfigError(f"{key}: {uri} is an in-memory store, lost when the process ends; give a file "
                          "(sqlite:///<file>)")
    local = sqlite_path(uri)
    if local is not None:
        if local.is_dir():
            raise ConfigError(f"{key}: {local} is a folder, not an SQLite file")
        check_integrity(local, key, kind)
        return
    scheme = uri.split("://", 1)[0] if "://" in uri else ""
    if kind == "mlflow" and scheme in ("", "file") and os.environ.get("MLFLOW_ALLOW_FILE_STORE", "").lower() not in (
            "true", "1"):
        raise ConfigError(f"{key}: {uri} is a folder store, which MLflow 3 refuses (its file store is in maintenance "
                          f"mode); give sqlite:///<file> (sqlite:///mlruns/mlflow.db is the default) or "
                          "http://<host>:<port>, or set MLFLOW_ALLOW_FILE_STORE=true")
    if kind == "mlflow" and scheme and not _MLFLOW_SCHEMES.match(scheme) and scheme not in _plugin_schemes():
        raise ConfigError(f"{key}: MLflow has no store for '{scheme}://' (sqlite:///<file>, http://<host>:<port>, "
                          "or a database URL)")
    if kind == "mlflow" and reach and scheme in ("http", "https"):
        _check_reachable(uri, key)


def _check_reachable(uri: str, key: str, timeout: float = 10.0) -> None:
    """A tracking server's ``/health`` asked once: any HTTP answer (an error status included: a
    proxy or a hosted server may answer other paths only) and any TLS failure (MLflow's own TLS
    settings, ``MLFLOW_TRACKING_INSECURE_TLS`` and the like, may accept what urllib does not)
    count as reached; a refused connection, an unknown host or no answer within ``timeout``
    seconds is a ConfigError (the URI's password hidden). Credentials in the URI are sent as
    Basic auth, as MLflow sends them. Hand-written with urllib because MLflow's client retries a
    dead server with backoff for minutes."""
    import base64
    import ssl
    import urllib.error
    import urllib.parse
    import urllib.request

    parts = urllib.parse.urlsplit(uri)
    host = parts.hostname or ""
    netloc = f"[{host}]" if ":" in host else host
    netloc += f":{parts.port}" if parts.port else ""
    request = urllib.request.Request(urllib.parse.urlunsplit(parts._replace(netloc=netloc)).rstrip("/") + "/health")
    if parts.username is not None:
        token = f"{urllib.parse.unquote(parts.username)}:{urllib.parse.unquote(parts.password or '')}"
        request.add_header("Authorization", "Basic " + base64.b64encode(token.encode()).decode())
    shown = redact(uri)
    try:
        with urllib.request.urlopen(request, timeout=timeout):
            return
    except urllib.error.HTTPError:
        return
    except (urllib.error.URLError, OSError, ValueError) as exc:
        reason = getattr(exc, "reason", None) or exc
        if isinstance(reason, ssl.SSLError) or isinstance(exc, ssl.SSLError):
            return
        raise ConfigError(f"{key}: the tracking server at {shown} does not answer ({reason}); start it, or fix "
                          "the URI") from None


def _plugin_schemes() -> set[str]:
    """The URI schemes MLflow's plugins register for tracking stores (entry points, no import)."""
    from importlib.metadata import entry_points

    return {ep.name for ep in entry_points(group="mlflow.tracking_store")}


def check_integrity(db: Path, key: str = "tracking.uri", kind: str = "mlflow") -> None:
    """SQLite's own integrity check on an existing store (milliseconds at these sizes), and its
    tables read to tell an MLflow store from an Optuna study storage (``kind``, what ``key``
    should hold); a file that is not a database, a damaged one, or the other tool's, is a
    ConfigError naming it (after ``key``, where the user gave it). A file found good is not read
    again in this process while its size and modification time stay the same (the command
    line's check, then the run's)."""
    import sqlite3

    if not db.is_file():
        return
    st = db.stat()
    if st.st_size == 0 or _INTACT.get((db, kind)) == (st.st_size, st.st_mtime_ns):
        return
    try:
        with contextlib.closing(sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=30.0)) as con:
            rows = [r[0] for r in con.execute("PRAGMA integrity_check").fetchall()]
            tables = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    except sqlite3.Error as exc:
        raise ConfigError(f"{key}: {db} is not a usable SQLite store ({exc}); move it aside or restore it") from None
    if rows != ["ok"]:
        raise ConfigError(f"{key}: {db} is damaged (SQLite integrity check: {rows[0][:160]}); "
                          "move it aside or restore it")
    other, own, what = _OTHER_KIND[kind]
    if other <= tables and not own & tables:
        raise ConfigError(f"{key}: {db} is {what}; give another file")
    _INTACT[(db, kind)] = (st.st_size, st.st_mtime_ns)


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

    Safe from parallel processes: a local store is created under a file lock
    (``mlflow_client``), and an experiment created meanwhile by another process is found.
    """
    check_writable(uri)
    client = mlflow_client(uri)  # creates or migrates a local store, under a lock
    exp = client.get_experiment_by_name(name)
    local = sqlite_path(uri)
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
        """Log ``params``; logging a value the run already has is a no-op, as in MLflow, also
        when another process logs the same params at the same moment (``_log_param_batch``)."""
        from mlflow.entities import Param

        items = [Param(k[:250], str(v)[:6000]) for k, v in params.items()]
        for i in range(0, len(items), 100):
            self._log_param_batch(items[i : i + 100])

    def _log_param_batch(self, items: list, tries: int = 5) -> None:
        """One ``log_batch`` of params. MLflow skips a param the run already holds with the same
        value, but checks before it inserts: two processes logging the same params to one run at
        once (the workers of a study summarizing its parent run together) both pass the check and
        the second insert fails, seen as ``UNIQUE constraint failed: params.key`` on SQLite. Then
        the run's params are read again and only the missing ones are logged; a param the run holds
        with another value is MLflow's error, raised as it is. Hand-written: MLflow has no upsert
        of params."""
        from mlflow.exceptions import MlflowException

        for attempt in range(tries):
            try:
                self._client.log_batch(self.run_id, params=items)
                return
            except MlflowException:
                have = self._client.get_run(self.run_id).data.params
                if attempt == tries - 1 or any(p.key in have and have[p.key] != p.value for p in items):
                    raise
                items = [p for p in items if p.key not in have]
                if not items:
                    return

    def log_metrics(self, metrics: Mapping[str, float], step: int = 0) -> None:
        self.log_metric_rows([(metrics, step)])

    def log_metric_rows(self, rows: list[tuple[Mapping[str, float], int]]) -> None:
        """Several steps' metrics ((metrics, step) pairs) in as few batches as MLflow allows."""
        import math
        import time

        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        items = [Metric(k, float(v), now, step) for metrics, step in rows for k, v in metrics.items()
                 if v is not None and not math.isnan(float(v))]
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


def process_tags() -> dict[str, str]:
    """Which process owns a run, so that a later process can tell a run whose owner died (still
    RUNNING) from one still at work (``read.owner_alive``): ``sdrl.host`` and ``sdrl.pid``, and
    where Linux's ``/proc`` says them, the machine (``sdrl.machine``: ``/etc/machine-id``), its
    boot (``sdrl.boot``: the kernel's boot id), the process's start in clock ticks since that
    boot (``sdrl.pid_start``: a pid the system has reused is not the owner) and its pid namespace
    (``sdrl.pid_ns``: containers that share a host name do not share pids). None of these moves
    when the system clock is stepped, as a start time in seconds since the epoch would."""
    tags = {"sdrl.host": socket.gethostname(), "sdrl.pid": str(os.getpid())}
    names = ("sdrl.machine", "sdrl.boot", "sdrl.pid_ns")
    tags.update({k: v for k, v in zip(names, system_identity(), strict=True) if v})
    if start := process_start(os.getpid()):
        tags["sdrl.pid_start"] = start
    return tags


@functools.cache
def system_identity() -> tuple[str, str, str]:
    """(machine, boot id, pid namespace) of this process's system, each "" where it cannot be
    read (no ``/proc``, as on macOS; no machine id in some containers). The machine is a keyed
    hash of ``/etc/machine-id``, not the id itself, which systemd asks applications not to
    expose (machine-id(5)). Read once: none of them changes while the process lives (a
    ``setns`` of the pid namespace moves only its children)."""
    import hashlib  # noqa: PLC0415
    import hmac  # noqa: PLC0415

    def read(path: str, link: bool = False) -> str:
        try:
            return os.readlink(path) if link else Path(path).read_text().strip()
        except OSError:
            return ""

    machine = read("/etc/machine-id")
    if machine:
        machine = hmac.new(b"sdrl-bench", machine.encode(), hashlib.sha256).hexdigest()[:16]
    return machine, read("/proc/sys/kernel/random/boot_id"), read("/proc/self/ns/pid", link=True)


def process_start(pid: int) -> str:
    """When process ``pid`` (of this pid namespace) started, in clock ticks since boot (field 22
    of ``/proc/<pid>/stat``, an integer the clock does not move); "" where it cannot be read."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return ""
    fields = stat[stat.rindex(")") + 2:].split()  # after the command name, which may hold spaces
    return fields[19] if len(fields) > 19 else ""


VECTOR_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512_bf16", "avx512_fp16", "avx_vnni", "amx_tile")
"""The CPU's vector extensions a run records (``cpu_tags``): the ones the numeric libraries pick
their kernels by."""


def cpu_tags() -> dict[str, str]:
    """The machine's CPU, recorded on every run: ``sdrl.cpu`` (its model name, family and model)
    and ``sdrl.cpu_vectors`` (which of ``VECTOR_FLAGS`` it has). torch, MKL, OpenBLAS and XLA
    choose their kernels by these extensions, and kernels round differently, so runs of one seed
    agree bit for bit only on machines alike in them (docs/seeds.md, "On another machine")."""
    return dict(_cpu_tags())


def machine_label(tags: Mapping[str, Any]) -> str | None:
    """A run's machine in one phrase, ``<sdrl.cpu> [<sdrl.cpu_vectors>]`` from its tags (or from
    ``cpu_tags()``); None for a run from before the tags."""
    cpu = tags.get("sdrl.cpu")
    return f"{cpu} [{tags.get('sdrl.cpu_vectors', '?')}]" if cpu else None


@functools.lru_cache(maxsize=1)
def _cpu_tags() -> tuple[tuple[str, str], ...]:
    """Read once from Linux's ``/proc/cpuinfo`` (its first processor); elsewhere the platform's
    processor string and no vector list."""
    first: dict[str, str] = {}
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            first.setdefault(key.strip(), value.strip())
    except OSError:
        pass
    flags = set(first.get("flags", "").split())
    name = first.get("model name") or platform.processor() or platform.machine() or "unknown"
    if "cpu family" in first and "model" in first:  # a vendor's name alone may cover several generations
        name = f"{name} (family {first['cpu family']}, model {first['model']})"
    return (("sdrl.cpu", name), ("sdrl.cpu_vectors", " ".join(f for f in VECTOR_FLAGS if f in flags) or "unknown"))


@contextlib.contextmanager
def start_run(
    uri: str,
    experiment: str,
    run_name: str,
    tags: Mapping[str, Any] | None = None,
    parent_run_id: str | None = None,
) -> Iterator[Run]:
    """Create a run; it ends FINISHED, or FAILED (KILLED on Ctrl-C) if the body raises. A run that
    fails carries its reason in one line (tag ``sdrl.error``: the exception's type and message)."""
    exp_id = ensure_experiment(uri, experiment)
    all_tags = {RUN_NAME_TAG: run_name, **process_tags(), **cpu_tags(), **(tags or {})}
    if parent_run_id:
        all_tags[PARENT_TAG] = parent_run_id
    run_info = mlflow_client(uri).create_run(exp_id, tags={k: str(v) for k, v in all_tags.items()}, run_name=run_name)
    run = Run(uri, run_info.info.run_id)
    try:
        yield run
    except BaseException as exc:
        killed = isinstance(exc, KeyboardInterrupt) or stop_signal_received()
        if not killed:
            with contextlib.suppress(Exception):  # the reason is a courtesy; the status is what counts
                run.set_tags({ERROR_TAG: hide_password(_one_line(exc), uri)})
        run.end("KILLED" if killed else "FAILED")
        raise
    run.end("FINISHED")


ERROR_TAG = "sdrl.error"
"""Why a run ended FAILED: one line."""


def hide_password(text: str, uri: str) -> str:
    """``text`` with the password of ``uri`` hidden wherever it appears (MLflow's messages quote
    the request's URL, login included: ``API request to http://user:password@host/... failed``)."""
    from urllib.parse import unquote, urlsplit

    try:
        password = urlsplit(uri).password
    except ValueError:
        return text
    for secret in {password, unquote(password or "")} - {None, ""}:
        text = text.replace(secret, "***")
    return text


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return (f"{type(exc).__name__}: {text}" if text else type(exc).__name__)[:500]


def create_parent_run(uri: str, experiment: str, run_name: str, tags: Mapping[str, Any]) -> str:
    """Create a sweep's parent run (left RUNNING; end it with ``end_run``)."""
    exp_id = ensure_experiment(uri, experiment)
    all_tags = {RUN_NAME_TAG: run_name, **process_tags(), **cpu_tags(), **tags}
    info = mlflow_client(uri).create_run(exp_id, tags={k: str(v) for k, v in all_tags.items()}, run_name=run_name)
    return info.info.run_id


def end_run(uri: str, run_id: str, status: str, *, also_ended: bool = False) -> None:
    """End a RUNNING run with ``status``; ``also_ended``: a run that ended already gets it too
    (a search trial whose worker died after its run ended, before Optuna recorded the trial:
    the study counts it FAIL, and its run says so)."""
    client = mlflow_client(uri)
    if also_ended or client.get_run(run_id).info.status == "RUNNING":
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
