"""The ``task=train`` half of the CLI: an RL-transfer run inside one MLflow run per seed.

Kept apart from ``cli.py`` so each file holds one job; ``cli.main`` dispatches here. Like
``cli.py`` it is an edge module: it instantiates configs and calls ``tracking``.
"""

from __future__ import annotations

import tempfile
from typing import Any

import pandas as pd
from omegaconf import DictConfig, OmegaConf

from sdrl_bench import tracking
from sdrl_bench.cli.build import build_transfer_job, real_arm_key
from sdrl_bench.rl.policy_maps import agreement, compute_maps, figure
from sdrl_bench.plots import learning_curves
from sdrl_bench.rl.transfer import TransferJob, run_arm


def run_train(cfg: DictConfig, fit_job, parent: str | None) -> dict[str, float]:
    """Validate, then run the arms of one seed inside one MLflow run; returns its metrics."""
    import torch

    torch.set_num_threads(int(cfg.torch_threads))
    job = build_transfer_job(cfg, fit_job)
    checked = job.check()
    uri = tracking.resolve_uri(cfg.tracking.uri)
    tracking.check_writable(uri)
    spec, names = job.fit.spec, job.fit.names
    key = real_arm_key(cfg)
    tags = {
        "sdrl.kind": "transfer", "env": spec.name, "agent": job.agent.name, "surrogate": names["surrogate"],
        "library": names["library"], "optimizer": names["optimizer"], "collector": names["collector"],
        "seed": job.seed, "arms": ",".join(job.arms), "real_arm_key": key, "git_commit": tracking.git_commit(),
        "solved_threshold": spec.solved_threshold,
    }
    run_name = f"train-{spec.name}-{job.agent.name}-{names['surrogate']}-s{job.seed}"
    summary: dict[str, float] = {}
    with tracking.start_run(uri, cfg.tracking.experiment, run_name, tags, parent) as run, \
            tempfile.TemporaryDirectory() as tmp:
        run.log_params(tracking.flatten(OmegaConf.to_container(cfg, resolve=True)))
        maps: dict[str, Any] = {}
        curves: dict[str, tuple] = {}
        model_text = ""
        for arm in job.arms:
            found = tracking.find_real_arm(uri, cfg.tracking.experiment, key) if (
                arm == "real" and cfg.rl.reuse_real_arm) else None
            if found is not None:
                algo_cls = getattr(job.agent.algo, "func", job.agent.algo)
                agent_zip, curve_csv = tracking.reuse_real_arm(run, found, tmp)
                model = algo_cls.load(agent_zip, device="cpu")
                maps["real"] = compute_maps(model, spec)
                curve = pd.read_csv(curve_csv)
                curves["real"] = (curve["train_steps"].tolist(), curve["return_mean"].tolist(), curve["return_std"].tolist())
                summary.update(found["metrics"])
                continue
            result = run_arm(
                job, arm, checked if arm == "surrogate" else None,
                logger_factory=lambda a: tracking.sb3_logger(run, f"{a}/sb3"),
                on_point=lambda a, s, m, sd: tracking.log_curve_point(run, a, s, m, sd),
            )
            steps = job.surrogate_steps if arm == "surrogate" else job.real_steps
            metrics = result.metrics(spec, steps)
            tracking.log_arm(run, result, metrics)
            if result.fit is not None:
                tracking.log_fit(run, result.fit, None, prefix="fit/")
                model_text = result.fit.model.describe()
            summary.update({f"{arm}/{k}": v for k, v in metrics.items()})
            maps[arm] = result.maps
            curves[arm] = (result.curve.steps, result.curve.means, result.curve.stds)
        if curves:
            run.log_figure(learning_curves(curves, spec.solved_threshold, f"{spec.name}: {job.agent.name}, seed {job.seed}"),
                           "figures/learning_curves.png")
        if len(maps) == 2:
            score = agreement(maps["surrogate"], maps["real"], discrete=bool(spec.n_discrete_actions))
            summary["policy_map_agreement"] = score
            run.log_metrics({"policy_map_agreement": score})
            label = "fraction of equal actions" if spec.n_discrete_actions else "mean |action difference|"
            fig = figure({"trained in the real env": maps["real"], f"trained in the {names['surrogate']} surrogate": maps["surrogate"]},
                         spec, f"{spec.name} policy maps ({label}: {score:.3f})")
            run.log_figure(fig, "figures/policy_maps.png")
        elif maps:
            arm = next(iter(maps))
            run.log_figure(figure({arm: maps[arm]}, spec, f"{spec.name} policy map ({arm} arm)"), "figures/policy_maps.png")
    _print(summary, uri, run.run_id, job, model_text)
    return summary


def _print(summary: dict[str, float], uri: str, run_id: str, job: TransferJob, model_text: str) -> None:
    from rich.console import Console
    from rich.table import Table

    keys = ("real_transitions_model", "real_transitions_train", "surrogate_steps", "total_steps",
            "final_return_mean", "final_return_std", "success_rate", "solved_real_steps", "solved_wall_seconds",
            "train_wall_seconds")
    table = Table(title=f"{job.fit.spec.name}: {job.agent.name}, seed {job.seed} (judged in the real env)")
    table.add_column("metric")
    for arm in job.arms:
        table.add_column(f"{arm} arm", justify="right")
    for k in keys:
        table.add_row(k, *[f"{summary[f'{a}/{k}']:.6g}" if f"{a}/{k}" in summary else "-" for a in job.arms])
    console = Console(width=120)
    if model_text:
        console.print(f"surrogate model ({job.fit.names['surrogate']}, {job.fit.n_transitions} real transitions):\n  "
                      + "\n  ".join(model_text.strip().splitlines()), highlight=False, markup=False)
    console.print(table)
    if "policy_map_agreement" in summary:
        console.print(f"policy-map agreement: {summary['policy_map_agreement']:.3f}")
    console.print(f"MLflow run {run_id} in {uri}", highlight=False)
    console.print("browse: mlflow ui --backend-store-uri " + tracking.display_uri(uri) + "  (then open http://127.0.0.1:5000)",
                  highlight=False)
