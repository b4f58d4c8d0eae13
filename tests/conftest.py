"""Shared fixtures: real envs, a real SQLite MLflow store in a temp dir, composed configs."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from sdrl_bench.cli import CONF_DIR

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def store(tmp_path, monkeypatch) -> str:
    """A fresh SQLite tracking URI in a temp dir (and MLFLOW_TRACKING_URI unset)."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    return f"sqlite:///{tmp_path / 'mlruns' / 'mlflow.db'}"


def compose_cfg(*overrides: str):
    """Compose the app's config as the CLI would (no Hydra run dir, no callbacks)."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def run_cli(*args: str, cwd: Path, env: dict | None = None, timeout: int = 300) -> subprocess.CompletedProcess:
    """Run the ``sdrl-bench`` app in a subprocess (real process, real exit code)."""
    full_env = {**os.environ, **(env or {})}
    full_env.pop("MLFLOW_TRACKING_URI", None)
    return subprocess.run(
        [sys.executable, "-m", "sdrl_bench.cli", *args],
        cwd=cwd, env=full_env, capture_output=True, text=True, timeout=timeout,
    )


def search(uri: str, experiment: str = "sdrl-bench", filter_string: str = ""):
    import mlflow

    mlflow.set_tracking_uri(uri)
    try:
        return mlflow.search_runs(experiment_names=[experiment], filter_string=filter_string)
    finally:
        mlflow.set_tracking_uri(None)
