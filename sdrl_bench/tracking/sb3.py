"""SB3's training metrics into a run: a ``KVWriter`` whose only output is MLflow."""

from __future__ import annotations

import time

from sdrl_bench.tracking.client import Run

FLUSH_SECONDS = 2.0
"""The writer keeps SB3's rows and writes them in one batch at most every this many seconds (and
when the logger is closed): one SQLite write costs ~10-30 ms here, more than a compiled PPO
iteration (``rl.jax_agent``), and SB3 dumps a row every PPO iteration."""


def sb3_logger(run: Run, prefix: str, flush_seconds: float = FLUSH_SECONDS):
    """An SB3 Logger whose only output is this run: SB3's training metrics reach MLflow here,
    batched (``FLUSH_SECONDS``); ``logger.close()`` writes what is left (``rl.agents.train``
    closes it after ``learn``)."""
    from stable_baselines3.common.logger import KVWriter, Logger

    class MlflowKVWriter(KVWriter):
        def __init__(self):
            self.rows: list[tuple[dict[str, float], int]] = []
            self.last = time.monotonic()

        def write(self, key_values, key_excluded, step=0):
            numeric = {f"{prefix}/{k}": v for k, v in key_values.items()
                       if isinstance(v, (int, float)) and not isinstance(v, bool)}
            self.rows.append((numeric, int(step)))
            if time.monotonic() - self.last >= flush_seconds:
                self.close()

        def close(self):
            if self.rows:
                rows, self.rows = self.rows, []
                run.log_metric_rows(rows)
            self.last = time.monotonic()

    return Logger(folder=None, output_formats=[MlflowKVWriter()])
