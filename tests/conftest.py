"""Shared fixtures: a real SQLite MLflow store in a temp dir. Helpers live in ``helpers.py``."""

from __future__ import annotations

import pytest


@pytest.fixture
def store(tmp_path, monkeypatch) -> str:
    """A fresh SQLite tracking URI in a temp dir (and MLFLOW_TRACKING_URI unset)."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    return f"sqlite:///{tmp_path / 'mlruns' / 'mlflow.db'}"
