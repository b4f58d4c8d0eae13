"""Writes to the SQLite tracking store from parallel jobs: rollback journal vs write-ahead log.

A sweep's jobs log to one SQLite file at once (Hydra's joblib launcher), and the MLflow UI or a
report may read it meanwhile. ``tracking.ensure_experiment`` puts the store in WAL mode; this
measures what that buys. Per journal mode, a fresh store; ``--jobs`` processes each log
``--runs`` runs shaped like a fit (40 params, 60 metrics, a 20-point curve, a tag batch, the
end of the run) through ``sdrl_bench.tracking.client.Run``; optionally a reader process polls
``search_runs`` meanwhile (``--reader``). Modes are interleaved over ``--repeats``; the table
shows median wall seconds and the ratio.

    .venv/bin/python benchmarks/tracking_writes.py [--jobs 2] [--runs 30] [--repeats 5] [--reader]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import sqlite3
import tempfile
import time
from pathlib import Path

import numpy as np

from sdrl_bench import tracking


def _as_mlflow_leaves_it(uri: str) -> None:
    """Keep the harness's client off the store's journal mode in this process: ``mlflow_client``
    switches a store to WAL the first time a process opens it, and skips stores it has opened
    already (a private set, reached into here so that the benchmark's rollback-journal side stays
    as MLflow alone leaves a store)."""
    from sdrl_bench.tracking import client

    client._READY.add(uri)


def _store(folder: Path, mode: str) -> str:
    """A fresh store: as sdrl-bench makes it (WAL), or as MLflow alone does (rollback journal)."""
    from mlflow.tracking import MlflowClient

    uri = f"sqlite:///{folder / 'mlflow.db'}"
    if mode == "wal":
        tracking.ensure_experiment(uri, "bench")
    else:
        MlflowClient(tracking_uri=uri).create_experiment("bench")
    with sqlite3.connect(folder / "mlflow.db") as con:
        got = con.execute("PRAGMA journal_mode").fetchone()[0]
    assert got == mode, f"journal mode {got}, wanted {mode}"
    return uri


def _writer(uri: str, mode: str, runs: int, start, out) -> None:
    if mode != "wal":
        _as_mlflow_leaves_it(uri)
    client = tracking.mlflow_client(uri)
    exp = client.get_experiment_by_name("bench").experiment_id
    start.wait()
    t0 = time.perf_counter()
    for i in range(runs):
        info = client.create_run(exp, run_name=f"r{i}")
        run = tracking.Run(uri, info.info.run_id)
        run.log_params({f"group.key{j}": j for j in range(40)})
        run.log_metrics({f"mse/state{j}": 1.0 / (j + 1) for j in range(60)})
        for step in range(20):
            run.log_metrics({"curve_return_mean": float(step)}, step=step)
        run.set_tags({"env": "bench", "seed": i})
        run.end()
    out.put(time.perf_counter() - t0)


def _reader(uri: str, stop, out) -> None:
    import mlflow

    mlflow.set_tracking_uri(uri)
    n = 0
    while not stop.is_set():
        mlflow.search_runs(experiment_names=["bench"], max_results=200)
        n += 1
    out.put(n)


def once(mode: str, jobs: int, runs: int, reader: bool) -> tuple[float, int]:
    ctx = mp.get_context("spawn")
    with tempfile.TemporaryDirectory() as tmp:
        uri = _store(Path(tmp), mode)
        start, stop, out, reads = ctx.Event(), ctx.Event(), ctx.Queue(), ctx.Queue()
        procs = [ctx.Process(target=_writer, args=(uri, mode, runs, start, out)) for _ in range(jobs)]
        readers = [ctx.Process(target=_reader, args=(uri, stop, reads))] if reader else []
        for p in procs + readers:
            p.start()
        time.sleep(2.0)  # imports done
        t0 = time.perf_counter()
        start.set()
        for p in procs:
            p.join()
        wall = time.perf_counter() - t0
        stop.set()
        for p in readers:
            p.join()
        n_reads = reads.get() if reader else 0
        if any(p.exitcode for p in procs):
            raise RuntimeError(f"a writer failed in {mode} mode")
        with sqlite3.connect(Path(tmp) / "mlflow.db") as con:
            got = con.execute("PRAGMA journal_mode").fetchone()[0]
        assert got == mode, f"journal mode {got} after the writes, wanted {mode}"
        return wall, n_reads


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--runs", type=int, default=30)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--reader", action="store_true", help="a process polling search_runs meanwhile")
    args = ap.parse_args()
    from sdrl_bench.cli.args import at_least

    at_least(ap, args, 1, "--jobs", "--runs", "--repeats")
    modes = ("delete", "wal")
    walls: dict[str, list[float]] = {m: [] for m in modes}
    reads: dict[str, list[int]] = {m: [] for m in modes}
    for _ in range(args.repeats):
        for m in modes:
            w, n = once(m, args.jobs, args.runs, args.reader)
            walls[m].append(w)
            reads[m].append(n)
    print(f"\n{args.jobs} writer processes x {args.runs} runs each"
          f"{', one reader polling search_runs' if args.reader else ''}; median of {args.repeats}")
    print(f"{'journal mode':<14} {'wall s':>8} {'runs/s':>8} {'reads':>6} {'ratio':>7}")
    base = float(np.median(walls["delete"]))
    for m in modes:
        med = float(np.median(walls[m]))
        print(f"{m:<14} {med:>8.2f} {args.jobs * args.runs / med:>8.1f} {int(np.median(reads[m])):>6} "
              f"{base / med:>6.2f}x")


if __name__ == "__main__":
    main()
