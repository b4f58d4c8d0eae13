"""Command-line entry points (Hydra). The only module that composes configs and instantiates.

``sdrl-bench`` runs a tracked SINDy fit: collect -> fit -> fidelity -> MLflow.
"""

from __future__ import annotations

import os

# SB3's small matrices run fastest single-threaded; BLAS reads this once, at numpy's import
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import signal
import sys
from typing import TYPE_CHECKING

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from sdrl_bench import ConfigError, Terminated, raise_on_stop_signals, stop_signal_received, tracking
from sdrl_bench.cli import CONFIG_PATH
from sdrl_bench.cli.callbacks import CONFIG_KEY_TAG, SWEEP_KEY_TAG, job_label, sweep_context

if TYPE_CHECKING:
    from sdrl_bench.pipeline import FitResult

# The config's builders (cli.build) and the pipeline import pysindy, torch and SB3 (about 3 s):
# they are imported where a job runs, so that a bad command line is answered (cli.precheck) in
# well under a second, before any of them loads.


def _sweep() -> tuple[str | None, str | None]:
    """(parent run id, sweep key) inside a ``-m`` sweep, else (None, None)."""
    if not HydraConfig.initialized():
        return None, None
    hc = HydraConfig.get()
    return sweep_context(hc.sweep.dir) if hc.mode == RunMode.MULTIRUN else (None, None)


def adopt_finished_job(cfg: DictConfig, parent: str, tags: dict[str, str]) -> float | None:
    """A FINISHED run of this very job (same config key) from an earlier run of the same sweep
    (same sweep key): moved under the new parent and its result returned, instead of a rerun."""
    uri = tracking.resolve_uri(cfg.tracking.uri)
    filt = (f"tags.`{SWEEP_KEY_TAG}` = '{tags[SWEEP_KEY_TAG]}' and tags.`{CONFIG_KEY_TAG}` = '{tags[CONFIG_KEY_TAG]}' "
            "and attributes.status = 'FINISHED'")
    done = tracking.find_runs(uri, cfg.tracking.experiment, filt)
    if not done:
        return None
    run = done[-1]  # the newest
    before = run["tags"].get(tracking.PARENT_TAG)
    if before != parent:
        tracking.Run(uri, run["run_id"]).set_tags({tracking.PARENT_TAG: parent, tracking.ADOPTED_BY_TAG: parent,
                                                   tracking.ADOPTED_FROM_TAG: before or ""})
    print(f"sdrl-bench: this job FINISHED in run {run['run_id']} of an earlier run of this sweep: adopted, not "
          "rerun (resume=false reruns it)", file=sys.stderr)
    m = run["metrics"]
    value = m.get("mse_norm/mean", m.get("surrogate/final_return_mean", m.get("real/final_return_mean", m.get("audit_return_mean", m.get("real_return_mean", 0.0)))))
    return float(value)


def run_fit(cfg: DictConfig, parent: str | None = None, extra_tags: dict[str, str] | None = None) -> FitResult:
    """Validate, then fit inside one MLflow run (FAILED if anything raises)."""
    from sdrl_bench.cli.build import build_fit_job, run_label  # noqa: PLC0415  (see the imports above)
    from sdrl_bench.pipeline import check, fit_dynamics  # noqa: PLC0415

    job = build_fit_job(cfg)
    checked = check(job)
    uri = tracking.resolve_uri(cfg.tracking.uri)
    tracking.check_writable(uri)
    names = job.names
    tags = {
        "env": names["env"], "library": names["library"], "optimizer": names["optimizer"],
        "collector": names["collector"], "surrogate": names["surrogate"], "seed": job.seed, **(extra_tags or {}),
    }
    model_name = f"{names['library']}-{names['optimizer']}" if names["surrogate"] == "sindy" else names["surrogate"]
    run_name = run_label(f"fit-{names['env']}-{model_name}-s{job.seed}", tags)
    with tracking.tracked_run(uri, cfg.tracking.experiment, run_name, "fit", tags, parent,
                              config=OmegaConf.to_container(cfg, resolve=True)) as run:
        result = fit_dynamics(job, checked)
        tracking.log_fit(run, result)
    _print_summary(result, uri, run.run_id, tracking.ensure_experiment(uri, cfg.tracking.experiment))
    return result


def _print_summary(result: FitResult, uri: str, run_id: str, experiment_id: str = "0") -> None:
    from rich.console import Console
    from rich.table import Table

    m = result.fidelity.metrics
    spec = result.job.spec
    table = Table(title=f"{spec.name}: {len(result.data)} transitions -> held-out '{result.test_name}' "
                        f"({len(result.test)} transitions)")
    for col in ("state", "MSE (raw)", "MSE (normalized)", "corr", "R^2", "10-step MSE", "50-step MSE"):
        table.add_column(col, justify="right")
    for n in spec.target_names:
        table.add_row(n, f"{m[f'mse/{n}']:.3e}", f"{m.get(f'mse_norm/{n}', float('nan')):.3e}",
                      f"{m[f'corr/{n}']:.6f}", f"{m[f'r2/{n}']:.6f}",
                      f"{m[f'rollout10_mse/{n}']:.3e}", f"{m[f'rollout50_mse/{n}']:.3e}")
    console = Console(width=120)
    console.print(table)
    console.print(f"diverged rollouts: 10-step {m['rollout10/diverged_fraction']:.1%}, "
                  f"50-step {m['rollout50/diverged_fraction']:.1%}; "
                  f"parameters {int(result.model.summary_metrics()['n_parameters'])}; "
                  f"fit {result.seconds['fit_wall']:.3f} s")
    lines = result.model.describe().strip().splitlines()
    console.print(f"{result.model.summary_file[:-4]}:\n  " + "\n  ".join(lines), highlight=False, markup=False)
    console.print(f"MLflow run {run_id} in {tracking.display_uri(uri)}", highlight=False)
    console.print(tracking.browse_hint(uri, experiment_id, run_id, tracking.display_uri(uri)), highlight=False, soft_wrap=True)


def main() -> None:
    """Entry point of ``sdrl-bench``: the command line checked first (``cli.precheck``: one line and
    exit 2 for a bad override, key, group option, YAML file or damaged store), then the Hydra app (``app``)."""
    from sdrl_bench.cli.precheck import run_checked

    run_checked(app, "config", "sdrl-bench", check_job="sdrl_bench.cli.build:check_job")


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="config")
def app(cfg: DictConfig) -> float:
    """Entry point of ``sdrl-bench``. ``task=fit`` returns the mean normalized one-step MSE,
    ``task=train`` the surrogate arm's final real return, ``task=dyna`` the final agent's
    audit return, ``task=fidelity`` its surrogates' mean real return (values for sweepers)."""
    # SIGTERM (a cluster scheduler, kill) and SIGINT unwind like an exception: the open MLflow
    # run ends KILLED instead of staying RUNNING. A sweep driver running jobs in-process keeps
    # its own handler (cli.callbacks), which also ends the parent run.
    from sdrl_bench.cli.build import JOB_TAG, build_fit_job, check_task, config_key, exit_after_stop_signal  # noqa: PLC0415

    if signal.getsignal(signal.SIGTERM) in (signal.SIG_DFL, None):
        raise_on_stop_signals()
    try:
        parent, key = _sweep()
        tags: dict[str, str] = {}
        if parent is not None:  # no progress bars inside multiruns
            OmegaConf.update(cfg, "progress_bar", False)
            tags = {SWEEP_KEY_TAG: key or "", CONFIG_KEY_TAG: config_key(cfg),
                    JOB_TAG: job_label(HydraConfig.get().sweep.dir, list(HydraConfig.get().overrides.task),
                                       list(HydraConfig.get().runtime.choices))}
        if HydraConfig.initialized():  # the experiment pack the run came from (rows of the report keep packs apart)
            pack = HydraConfig.get().runtime.choices.get("experiment")
            if pack and pack != "null":
                tags["sdrl.experiment"] = str(pack)
        check_task(cfg)
        fit_job = build_fit_job(cfg)  # validates the config before anything else
        if parent is not None and key and cfg.get("resume", True) is True:
            done = adopt_finished_job(cfg, parent, tags)
            if done is not None:
                return done
        if cfg.task == "fit":
            return float(run_fit(cfg, parent=parent, extra_tags=tags).fidelity.metrics["mse_norm/mean"])
        if cfg.task == "fidelity":
            from sdrl_bench.cli.fidelity_task import run_fidelity_task

            returns = run_fidelity_task(cfg, parent, extra_tags=tags)
            return float(sum(returns.values()) / len(returns))
        if cfg.task == "dyna":
            from sdrl_bench.cli.dyna_task import run_dyna_task

            summary = run_dyna_task(cfg, fit_job, parent, extra_tags=tags)
            return float(summary.get("audit_return_mean", summary.get("final_return_mean", 0.0)))
        from sdrl_bench.cli.train import run_train

        summary = run_train(cfg, fit_job, parent, extra_tags=tags)
        return float(summary.get("surrogate/final_return_mean", summary.get("real/final_return_mean", 0.0)))
    except ConfigError as exc:
        print(f"sdrl-bench: error: {exc}", file=sys.stderr)
        sys.exit(2)
    except Terminated as exc:
        exit_after_stop_signal(cfg, exc.signum, "sdrl-bench", "the run ended KILLED")
    except Exception:
        if stop_signal_received() is None:
            raise
        exit_after_stop_signal(cfg, stop_signal_received(), "sdrl-bench", "the run ended KILLED")


if __name__ == "__main__":
    main()
