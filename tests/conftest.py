"""Shared fixtures: a real SQLite MLflow store in a temp dir. Helpers live in ``helpers.py``."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def made_store_file(tmp_path_factory) -> Path:
    """One empty MLflow store per test process, its tables made by MLflow itself and put in WAL
    mode by the harness (``tracking.mlflow_client``), then checkpointed so that the one file holds
    all of it. Making a store's tables costs 2-4 s on this machine (MLflow runs its ~60 schema
    migrations on every new store); a copy of this file costs a millisecond."""
    from sdrl_bench import tracking

    path = tmp_path_factory.mktemp("store-template") / "mlflow.db"
    tracking.mlflow_client(f"sqlite:///{path}")
    with contextlib.closing(sqlite3.connect(path)) as con:
        assert con.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    return path


@pytest.fixture
def store(tmp_path, monkeypatch, made_store_file) -> str:
    """A SQLite tracking URI in a temp dir holding an empty MLflow store, as a user's is after
    their first run (and MLFLOW_TRACKING_URI unset). The making of a new store, and first use by
    parallel processes, are tested with ``new_store`` and in ``e2e/test_faults.py``."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    db = tmp_path / "mlruns" / "mlflow.db"
    db.parent.mkdir(parents=True)
    shutil.copyfile(made_store_file, db)
    return f"sqlite:///{db}"


@pytest.fixture
def new_store(tmp_path, monkeypatch) -> str:
    """A SQLite tracking URI in a temp dir where no store exists yet (and MLFLOW_TRACKING_URI
    unset): the first run makes it, or, on bad input, nothing does."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    return f"sqlite:///{tmp_path / 'mlruns' / 'mlflow.db'}"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="session")
def mlflow_server(tmp_path_factory):
    """A real ``mlflow server`` on a free loopback port (SQLite backend and artifacts in a temp
    dir), started once per test process (it takes 15-25 s here) for the tests that need one, and
    stopped with its process group afterwards. Each test writes to an experiment of its own."""
    tmp = tmp_path_factory.mktemp("server")
    port = _free_port()
    with open(tmp / "server.log", "w") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "mlflow", "server", "--host", "127.0.0.1", "--port", str(port), "--workers", "1",
             "--backend-store-uri", f"sqlite:///{tmp / 'mlflow.db'}", "--artifacts-destination", str(tmp / "artifacts")],
            cwd=tmp, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
            env={**os.environ, "MLFLOW_TRACKING_URI": "", "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"},
        )
        url = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 180
        while True:
            try:
                with urllib.request.urlopen(f"{url}/health", timeout=2) as r:
                    if r.status == 200:
                        break
            except OSError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                with contextlib.suppress(ProcessLookupError):  # a server that exited left no group
                    os.killpg(proc.pid, signal.SIGKILL)
                pytest.fail(f"mlflow server did not start: {(tmp / 'server.log').read_text()[-2000:]}")
            time.sleep(0.5)
        yield url
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
