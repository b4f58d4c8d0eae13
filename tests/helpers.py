"""Helpers shared by the tests (imported as ``helpers``: ``pythonpath = ["tests"]`` in pyproject)."""

from __future__ import annotations

import contextlib
import importlib.util
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

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


def held_sde_noise(model, ob, mean, copies: int | None = None) -> None:
    """Checks a compiled agent's stochastic ``predict`` under gSDE against SB3's semantics: one
    matrix held across calls until ``reset_noise`` (an episode follows one perturbed policy), one
    per row for a batch of the copies' count, one for every row of a batch of another size; drawn
    from a stream of its own, so that sampling moves nothing training draws next. ``mean``: the
    deterministic action at ``ob``; ``copies``: draw for that many copies first (else the first
    stochastic call draws for the config's)."""
    import numpy as np  # noqa: PLC0415

    state, key = model._host_rng.bit_generator.state, getattr(model, "_key", None)
    if copies is not None:
        model.reset_noise(copies)
    n = copies or model.cfg.n_envs
    first, _ = model.predict(ob, deterministic=False)
    assert np.array_equal(first, model.predict(ob, deterministic=False)[0]) and not np.array_equal(first, mean)
    rows = np.repeat(ob[None], n, axis=0)
    per_row, _ = model.predict(rows, deterministic=False)
    assert len({float(x) for x in per_row[:, 0]}) > n // 2  # a matrix per copy (a clipped few may tie)
    shared, _ = model.predict(rows[:3], deterministic=False)
    # the single matrix for every row (a batch of one and of three round apart)
    assert np.allclose(shared, first[None], rtol=0, atol=1e-6) and np.abs(per_row - first[None]).max() > 1e-3
    model.reset_noise()
    assert not np.array_equal(first, model.predict(ob, deterministic=False)[0])
    assert state == model._host_rng.bit_generator.state  # training's streams untouched (a split replaces the key)
    assert getattr(model, "_key", None) is key


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_mlflow_server(tmp: Path) -> tuple[subprocess.Popen, str]:
    """A real ``mlflow server`` on a free loopback port (SQLite backend and artifacts in ``tmp``),
    in a process group of its own; returns it once ``/health`` answers (15-25 s here) and its URL."""
    port = free_port()
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
                    return proc, url
        except OSError:
            pass
        if proc.poll() is not None or time.monotonic() > deadline:
            stop_mlflow_server(proc, signal.SIGKILL)
            pytest.fail(f"mlflow server did not start: {(tmp / 'server.log').read_text()[-2000:]}")
        time.sleep(0.5)


def stop_mlflow_server(proc: subprocess.Popen, sig: int = signal.SIGTERM) -> None:
    """Stop a ``start_mlflow_server`` process group with ``sig`` (SIGKILL after 15 s)."""
    with contextlib.suppress(ProcessLookupError):  # a server that exited left no group
        os.killpg(proc.pid, sig)
    try:
        proc.wait(timeout=15)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
