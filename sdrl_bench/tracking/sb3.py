"""SB3's training metrics into a run: a ``KVWriter`` whose only output is MLflow."""

from __future__ import annotations

from sdrl_bench.tracking.client import Run


def sb3_logger(run: Run, prefix: str):
    """An SB3 Logger whose only output is this run: SB3's training metrics reach MLflow here."""
    from stable_baselines3.common.logger import KVWriter, Logger

    class MlflowKVWriter(KVWriter):
        def write(self, key_values, key_excluded, step=0):
            numeric = {f"{prefix}/{k}": v for k, v in key_values.items()
                       if isinstance(v, (int, float)) and not isinstance(v, bool)}
            run.log_metrics(numeric, step=int(step))

        def close(self):
            pass

    return Logger(folder=None, output_formats=[MlflowKVWriter()])
