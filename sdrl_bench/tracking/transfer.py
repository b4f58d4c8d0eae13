"""Recording an RL-transfer run: curve points, each arm's accounting, curve and agent, and
finding (and copying) a finished real arm to reuse."""

from __future__ import annotations

import tempfile
from collections.abc import Mapping
from pathlib import Path

from sdrl_bench.tracking.client import Run, mlflow_client


def log_curve_point(run: Run, arm: str, step: int, mean: float, std: float) -> None:
    run.log_metrics({f"{arm}/curve_return_mean": mean, f"{arm}/curve_return_std": std}, step=step)


def log_arm(run: Run, arm_result, metrics: Mapping[str, float]) -> None:
    """An arm's accounting metrics (prefixed ``<arm>/``), its curve and its trained agent."""
    import pandas as pd

    arm = arm_result.arm
    run.log_metrics({f"{arm}/{k}": v for k, v in metrics.items()})
    if arm_result.surrogate_stats:
        run.log_metrics({f"{arm}/surrogate_{k}": v for k, v in arm_result.surrogate_stats.items()})
    c = arm_result.curve
    curve = pd.DataFrame({"train_steps": c.steps, "return_mean": c.means, "return_std": c.stds, "train_wall_seconds": c.wall})
    run.log_text(curve.to_csv(index=False), f"curves/{arm}.csv")
    run.log_text(pd.DataFrame({"return": arm_result.final_returns, "success": arm_result.final_successes}).to_csv(index=False),
                 f"final_eval/{arm}.csv")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"{arm}.zip"
        arm_result.model.save(path)
        run.log_artifact(path, "agents")


def find_real_arm(uri: str, experiment: str, key: str) -> dict | None:
    """A finished run whose real arm has the same key: its id, real/* metrics and curve."""
    client = mlflow_client(uri)
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        return None
    runs = client.search_runs([exp.experiment_id], filter_string=f"tags.real_arm_key = '{key}' and attributes.status = 'FINISHED'",
                              order_by=["attributes.start_time DESC"], max_results=5)
    for r in runs:
        if "real/final_return_mean" in r.data.metrics and r.data.tags.get("real_arm_reused_from") is None:
            return {"run_id": r.info.run_id, "metrics": {k: v for k, v in r.data.metrics.items() if k.startswith("real/")}}
    return None


def reuse_real_arm(run: Run, found: dict, local_dir: str | Path) -> tuple[Path, Path]:
    """Copy a reused real arm's metrics and curve into ``run``; returns (agent zip, curve CSV)."""
    run.log_metrics(found["metrics"])
    run.set_tags({"real_arm_reused_from": found["run_id"]})
    client = mlflow_client(run.uri)
    curve = client.download_artifacts(found["run_id"], "curves/real.csv", str(local_dir))
    run.log_artifact(curve, "curves")
    for m in client.get_metric_history(found["run_id"], "real/curve_return_mean"):
        run.log_metrics({"real/curve_return_mean": m.value}, step=m.step)
    return Path(client.download_artifacts(found["run_id"], "agents/real.zip", str(local_dir))), Path(curve)


class RunRecorder:
    """``rl.transfer.TransferRecorder`` into one MLflow run: the fit as soon as it exists
    (under the names fit runs use), curve points as they come, each arm's accounting, curve and agent, figures;
    a finished real arm with the same ``real_arm_key`` is found and copied for reuse."""

    def __init__(self, run: Run, experiment: str, real_arm_key: str, local_dir: str | Path):
        self.run, self.experiment, self.key, self.local_dir = run, experiment, real_arm_key, Path(local_dir)
        self.reused_from: str | None = None
        """The run whose real arm this run reused, once it has."""

    def reusable_real_arm(self):
        import pandas as pd

        from sdrl_bench.rl.agents import Curve
        from sdrl_bench.rl.transfer import ReusedArm

        found = find_real_arm(self.run.uri, self.experiment, self.key)
        if found is None:
            return None
        agent_zip, curve_csv = reuse_real_arm(self.run, found, self.local_dir)
        self.reused_from = found["run_id"]
        curve = pd.read_csv(curve_csv)
        return ReusedArm(agent_zip, Curve(steps=curve["train_steps"].tolist(), means=curve["return_mean"].tolist(),
                                          stds=curve["return_std"].tolist()), found["metrics"])

    def sb3_logger(self, arm: str):
        from sdrl_bench.tracking.sb3 import sb3_logger

        return sb3_logger(self.run, f"{arm}/sb3")

    def curve_point(self, arm: str, step: int, mean: float, std: float) -> None:
        log_curve_point(self.run, arm, step, mean, std)

    def fit_done(self, fit) -> None:
        from sdrl_bench.tracking.fit import log_fit

        # the fit's metrics under the names fit runs use (``mse/x``, not ``fit/mse/x``): one
        # column and one chart across fit and transfer runs; the arms keep their prefixes. Its
        # real-step accounting goes under fit/: the run's headlines (``<arm>/real_steps/this_run``)
        # are the arms', and an unprefixed ``real_steps/this_run`` of the fit alone beside them misled
        log_fit(self.run, fit, accounting_prefix="fit/")

    def arm_done(self, result, metrics: Mapping[str, float]) -> None:
        log_arm(self.run, result, metrics)

    def figure(self, fig, artifact_file: str) -> None:
        self.run.log_figure(fig, artifact_file)

    def metrics(self, metrics: Mapping[str, float]) -> None:
        self.run.log_metrics(metrics)
