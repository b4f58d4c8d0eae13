"""Shared fixtures: a real SQLite MLflow store in a temp dir. Helpers live in ``helpers.py``."""

from __future__ import annotations

import contextlib
import shutil
import sqlite3
from pathlib import Path

import pytest

from helpers import start_mlflow_server, stop_mlflow_server


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


@pytest.fixture(scope="session")
def mlflow_server(tmp_path_factory):
    """A real ``mlflow server`` (``start_mlflow_server``), started once per test process for the
    tests that need one, and stopped with its process group afterwards. Each test writes to an
    experiment of its own."""
    proc, url = start_mlflow_server(tmp_path_factory.mktemp("server"))
    yield url
    stop_mlflow_server(proc)
