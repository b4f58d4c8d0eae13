"""Helpers shared by the tests (imported as ``helpers``: ``pythonpath = ["tests"]`` in pyproject)."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

from sdrl_bench.cli.build import compose

ROOT = Path(__file__).resolve().parents[1]


def load_script(relpath: str):
    """A script of the repository that is not a package module (``benchmarks/``, ``studies/``,
    ``scripts/``), imported from its file: its functions tested without running its ``main``."""
    path = ROOT / relpath
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def compose_cfg(*overrides: str):
    """Compose the app's config as the CLI would (no Hydra run dir, no callbacks)."""
    return compose(list(overrides))


def run_cli(*args: str, cwd: Path, env: dict | None = None, timeout: int = 300,
            module: str = "sdrl_bench.cli.main") -> subprocess.CompletedProcess:
    """Run an entry point (default ``sdrl-bench``) in a subprocess: real process, real exit code."""
    full_env = {**os.environ, **(env or {})}
    full_env.pop("MLFLOW_TRACKING_URI", None)
    return subprocess.run(
        [sys.executable, "-m", module, *args],
        cwd=cwd, env=full_env, capture_output=True, text=True, timeout=timeout,
    )


def search(uri: str, experiment: str = "sdrl-bench", filter_string: str = ""):
    """``mlflow.search_runs`` on one store (the global tracking URI restored afterwards)."""
    import mlflow

    mlflow.set_tracking_uri(uri)
    try:
        return mlflow.search_runs(experiment_names=[experiment], filter_string=filter_string)
    finally:
        mlflow.set_tracking_uri(None)
