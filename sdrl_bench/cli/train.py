"""The ``task=train`` half of ``sdrl-bench``: one RL-transfer run per seed, inside one MLflow run.

Builds the typed job (``cli.build``), hands ``rl.transfer.run_transfer`` a recorder that writes
the MLflow run, and prints the accounting. ``cli.main`` dispatches here.
"""

from __future__ import annotations

import tempfile

from omegaconf import DictConfig, OmegaConf

from sdrl_bench import ConfigError, tracking
from sdrl_bench.cli.build import bool_key, build_transfer_job, check_run_keys, real_arm_key, run_label
from sdrl_bench.rl.transfer import TransferJob, run_transfer
from sdrl_bench.tracking.transfer import RunRecorder


def run_train(cfg: DictConfig, fit_job, parent: str | None, extra_tags: dict[str, str] | None = None) -> dict[str, float]:
    """Validate, then run the arms of one seed inside one MLflow run; returns its metrics."""
    job, checked, uri = prepare(cfg, build_transfer_job(cfg, fit_job))
    spec, names = job.fit.spec, job.fit.names
    key = real_arm_key(cfg)
    tags = {
        "env": spec.name, "agent": job.agent.name, "surrogate": names["surrogate"],
        "library": names["library"], "optimizer": names["optimizer"], "collector": names["collector"],
        "seed": job.seed, "arms": ",".join(job.arms), "real_arm_key": key,
        "solved_threshold": spec.solved_threshold, **(extra_tags or {}),
    }
    run_name = run_label(f"train-{spec.name}-{job.agent.name}-{names['surrogate']}-s{job.seed}", extra_tags)
    intro = (f"**{spec.name}**: {job.agent.name.upper()} trained in the {names['surrogate']} surrogate and/or the real "
             f"env (arms: {', '.join(job.arms)}), seed {job.seed}.")
    with tracking.tracked_run(uri, cfg.tracking.experiment, run_name, "transfer", tags, parent, task="train",
                              config=OmegaConf.to_container(cfg, resolve=True), description=intro, system=True) as run, \
            tempfile.TemporaryDirectory() as tmp:
        exp_id = tracking.ensure_experiment(uri, cfg.tracking.experiment)
        _start_banner(run_name, run.run_id, uri, exp_id, job)
        recorder = RunRecorder(run, cfg.tracking.experiment, key, tmp)
        outcome = run_transfer(job, checked, recorder, reuse_real_arm=bool_key(cfg, "rl.reuse_real_arm"))
        tracking.set_description(run, _description(outcome.summary, job, outcome.model_text))
    _print(outcome.summary, uri, run.run_id, job, outcome.model_text, exp_id, recorder.reused_from)
    return outcome.summary


def prepare(cfg: DictConfig, job):
    """(job, what its check returned, store URI): torch's threads set, the job validated and the
    store checked writable, before any env step or run (task=train and task=dyna)."""
    import torch

    torch_threads, jax_threads = check_run_keys(cfg)  # checked whatever the agent
    torch.set_num_threads(torch_threads)
    algo = getattr(job.agent.algo, "func", None)
    compiled = bool(getattr(algo, "USES_JAX", False))  # the compiled agents (rl.jax_agent.CompiledAgent)
    if compiled:  # before anything creates JAX's backend (the job's check may)
        from sdrl_bench.rl.jax_compile import size_cpu_pool

        try:
            size_cpu_pool(jax_threads, getattr(algo, "LABEL", getattr(algo, "__qualname__", "the agent")))
        except ImportError as exc:  # the [jax] extra missing: the agent's check would say the same
            raise ConfigError(f"agent.algo: {exc}") from None
    checked = job.check()
    if cfg.get("jax_cache_dir") and compiled:
        from sdrl_bench.rl.jax_compile import use_compilation_cache

        use_compilation_cache(cfg.jax_cache_dir)
    uri = tracking.resolve_uri(cfg.tracking.uri)
    tracking.check_writable(uri)
    return job, checked, uri


def _start_banner(run_name: str, run_id: str, uri: str, exp_id: str, job: TransferJob) -> None:
    """Printed as soon as the run exists, so the live run can be opened while it trains."""
    budgets = {"surrogate": job.surrogate_steps, "real": job.real_steps}
    arms = ", ".join(f"{a} arm {budgets[a]:,} steps" for a in job.arms)
    print(f"sdrl-bench: {run_name}: {job.agent.name.upper()} on {job.fit.spec.name}, {arms}", flush=True)
    print(f"MLflow run {run_id} in {tracking.display_uri(uri)}; "
          f"{tracking.browse_hint(uri, exp_id, run_id, tracking.display_uri(uri))}", flush=True)


def _description(summary: dict[str, float], job: TransferJob, model_text: str) -> str:
    """The run's description once it ends: each arm's real return and steps, and the equations."""
    spec = job.fit.spec
    lines = [f"**{spec.name}**: {job.agent.name.upper()}, seed {job.seed}, judged in the real env."]
    for arm in job.arms:
        if f"{arm}/final_return_mean" in summary:
            lines.append(f"- {arm} arm: real return {summary[f'{arm}/final_return_mean']:.1f} "
                         f"(success {summary.get(f'{arm}/success_rate', float('nan')):.0%}), "
                         f"{summary.get(f'{arm}/total_steps', float('nan')):,.0f} total steps")
    if model_text:
        lines.append(f"\nSurrogate ({job.fit.names['surrogate']}, {job.fit.n_transitions} real transitions):\n\n"
                     f"```\n{model_text.strip()}\n```")
    return "\n".join(lines) + "\n"


def _notes(summary: dict[str, float], job: TransferJob, reused_from: str | None) -> list[str]:
    """What the table alone would not say: a real arm reused from an earlier run, and an arm that
    trained past its budget (an agent rounds a budget up to whole rollouts: 2,000 steps of
    ``ppo_fast``'s 128 envs x 32 steps are 4,096)."""
    notes = []
    if reused_from and "real" in job.arms:
        notes.append(f"the real arm is reused from run {reused_from} (the same env, agent, budgets and seed), not "
                     "trained again; rl.reuse_real_arm=false trains it")
    budgets = (("surrogate", "surrogate_steps", job.surrogate_steps, "rl.surrogate_steps"),
               ("real", "real_transitions_train", job.real_steps, "rl.real_steps"))
    for arm, metric, budget, key in budgets:
        took = summary.get(f"{arm}/{metric}")
        if arm in job.arms and took is not None and took > budget and not (arm == "real" and reused_from):
            notes.append(f"the {arm} arm trained {took:,.0f} steps for {key}={budget:,}: the agent rounds a budget up "
                         "to whole rollouts or training intervals, and every step is counted above")
    return notes


def _print(summary: dict[str, float], uri: str, run_id: str, job: TransferJob, model_text: str, exp_id: str = "0",
           reused_from: str | None = None) -> None:
    from rich.console import Console
    from rich.table import Table

    keys = ("real_transitions_model", "real_transitions_train", "surrogate_steps", "total_steps",
            "real_steps/this_run", "real_steps/all", "final_return_mean", "final_return_std", "success_rate",
            "judged_solved", "solved_real_steps", "solved_wall_seconds", "train_wall_seconds")
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
    for note in _notes(summary, job, reused_from):
        console.print(f"note: {note}", highlight=False)
    if "policy_map_agreement" in summary:
        console.print(f"policy-map agreement: {summary['policy_map_agreement']:.3f}")
    console.print(f"MLflow run {run_id} in {tracking.display_uri(uri)}", highlight=False)
    console.print(tracking.browse_hint(uri, exp_id, run_id, tracking.display_uri(uri)), highlight=False, soft_wrap=True)
