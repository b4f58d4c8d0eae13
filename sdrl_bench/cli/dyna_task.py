"""The ``task=dyna`` half of ``sdrl-bench``: one Dyna run (``rl.dyna``) per seed, a parent MLflow
run with a child run per round (``tracking.dyna_runs``). ``cli.main`` dispatches here."""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

from sdrl_bench import tracking
from sdrl_bench.cli.build import build_dyna_job, real_arm_key, run_label
from sdrl_bench.cli.train import prepare
from sdrl_bench.rl.dyna import LOOP_PHASES, DynaOutcome, run_dyna
from sdrl_bench.tracking.dyna_runs import DynaRunRecorder


def run_dyna_task(cfg: DictConfig, fit_job, parent: str | None, extra_tags: dict[str, str] | None = None) -> dict[str, float]:
    """Validate, then run the loop inside one MLflow run; returns its summary metrics."""
    job, checked, uri = prepare(cfg, build_dyna_job(cfg, fit_job))
    spec, names = job.fit.spec, job.fit.names
    base = {"env": spec.name, "agent": job.agent.name, "surrogate": names["surrogate"], "library": names["library"],
            "optimizer": names["optimizer"], "collector": names["collector"], "seed": job.seed,
            "solved_threshold": spec.solved_threshold}
    standard = tracking.standard_tags("sdrl-bench task=dyna")
    run_name = run_label(f"dyna-{spec.name}-{job.agent.name}-{names['surrogate']}-s{job.seed}", extra_tags)
    with tracking.tracked_run(uri, cfg.tracking.experiment, run_name, "dyna", {**base, **(extra_tags or {})}, parent,
                              config=OmegaConf.to_container(cfg, resolve=True), system=True) as run:
        exp_id = tracking.ensure_experiment(uri, cfg.tracking.experiment)
        print(f"sdrl-bench: {run_name}: Dyna on {spec.name}, {names['surrogate']} surrogate, {job.agent.name.upper()}, "
              f"at most {job.dyna.max_real_transitions:,} real steps", flush=True)
        print(f"MLflow run {run.run_id} in {tracking.display_uri(uri)}; "
              f"{tracking.browse_hint(uri, exp_id, run.run_id, tracking.display_uri(uri))}", flush=True)
        recorder = DynaRunRecorder(run, cfg.tracking.experiment, run_name, {**base, **standard})
        outcome = run_dyna(job, checked, _Printing(recorder))
        recorder.finish(outcome, spec, real_arm_key(cfg), f"{spec.name}: Dyna ({names['surrogate']}) vs the real arm, seed {job.seed}")
        tracking.set_description(run, _description(outcome, job))
    _print(outcome, uri, run.run_id, exp_id, job.dyna.final_episodes)
    return outcome.summary


class _Printing:
    """Prints one line per round, then hands the round to the MLflow recorder."""

    def __init__(self, inner: DynaRunRecorder):
        self.inner = inner

    def sb3_logger(self):
        return self.inner.sb3_logger()

    def round_done(self, result, agent) -> None:
        m = result.metrics()
        parts = [f"round {result.round}: {m['real_transitions_total']:,.0f} real steps "
                 f"(model data {m['real_transitions_model']:,.0f}), {m['surrogate_steps']:,.0f} surrogate steps"]
        if result.screen is not None:
            parts.append(f"screen {result.screen.mean:.1f}")
        if result.final is not None:
            parts.append(f"confirmation {result.final.mean:.1f}")
        for name, model in (result.events or {}).items():
            if model is not None:
                seen = ", ".join(f"{n} {o}" for o, n in model.counts.items())
                parts.append(f"{name} model learned from {model.n_events} real events ({seen})")
        print("; ".join(parts) + (" -> solved" if result.solved else ""), flush=True)
        self.inner.round_done(result, agent)


def _description(outcome: DynaOutcome, job) -> str:
    s = outcome.summary
    head = (f"**{job.fit.spec.name}**: Dyna, {job.fit.names['surrogate']} surrogate, {job.agent.name.upper()}, seed {job.seed}: "
            + (f"solved in round {s['rounds']:.0f} after {s['real_transitions_total']:,.0f} real steps"
               if s["solved"] else f"not solved in {s['rounds']:.0f} rounds ({s['real_transitions_total']:,.0f} real steps)"))
    lines = [head, "", "| phase | real steps |", "|---|---:|"]
    lines += [f"| {p} | {s[f'real_steps_{p}']:,.0f} |" for p in LOOP_PHASES]
    if "audit_return_mean" in s:
        lines += ["", f"Audit (after the loop, {s['audit_episodes']:.0f} fresh real episodes, not counted above): "
                      f"{s['audit_return_mean']:.1f} +- {s['audit_return_std']:.1f}, success {s['audit_success_rate']:.0%}."]
    lines += ["", "```", outcome.rounds[-1].fit.model.describe().strip(), "```"]
    return "\n".join(lines) + "\n"


def _print(outcome: DynaOutcome, uri: str, run_id: str, exp_id: str, final_episodes: int) -> None:
    s = outcome.summary
    verdict = "solved" if s["solved"] else "not solved"
    print(f"Dyna: {verdict} after {s['rounds']:.0f} rounds; real steps {s['real_transitions_total']:,.0f} "
          f"(collect {s['real_steps_collect']:,.0f}, screens {s['real_steps_evaluate']:,.0f}, "
          f"confirmations {s['real_steps_final']:,.0f}); surrogate steps {s['surrogate_steps']:,.0f}; "
          f"wall {s['wall_seconds']:.1f} s")
    if "real_steps/all" in s:
        print(f"real steps: this run's data {s['real_steps/this_run']:,.0f}; all real steps {s['real_steps/all']:,.0f} "
              f"(+ priors {s['real_steps/priors']:,.0f}, expert training {s['real_steps/expert']:,.0f}, recipe tuning "
              f"{s['real_steps/tuning']:,.0f}; judging apart: {s['real_steps/judge']:,.0f})")
    if "final_return_mean" in s:
        print(f"last confirmation: {s['final_return_mean']:.1f} +- {s['final_return_std']:.1f} on {final_episodes} real episodes")
    if "audit_return_mean" in s:
        print(f"audit: {s['audit_return_mean']:.1f} +- {s['audit_return_std']:.1f} on {s['audit_episodes']:.0f} fresh real "
              f"episodes (success {s['audit_success_rate']:.0%}; not counted in the loop's real steps): "
              f"{'solved' if s.get('judged_solved') else 'not solved'} by this independent judge")
    print(f"MLflow run {run_id} in {tracking.display_uri(uri)}")
    print(tracking.browse_hint(uri, exp_id, run_id, tracking.display_uri(uri)))
