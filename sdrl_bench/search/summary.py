"""The end of a study: the best trial, its score on the fixed test set, the figures, the
exported config, and comparisons between studies (grid vs TPE).

``summarize`` is idempotent: every worker calls it when it stops, and the last one to finish
leaves the final picture in the parent run (and in the study's ``sdrl.summary`` attribute).
"""

from __future__ import annotations

import contextlib
import json
import os
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any
from collections.abc import Callable, Mapping

import optuna

from sdrl_bench import ConfigError, nearest_existing, redact, stop_signal_received, tracking
from sdrl_bench.pipeline import fit_dynamics
from sdrl_bench.search.study import BuildJob, WorkerResult, counted, fit_params
from sdrl_bench.search.plots import history_figure, importance_figure, pareto_figure
from sdrl_bench.search.space import describe_space, experiment_pack, to_overrides
from sdrl_bench.search.location import resolve_storage
from sdrl_bench.search.storage import local_file, open_storage, summary_lock

SUMMARY_ATTR = "sdrl.summary"
REFITS_ATTR = "sdrl.refit_scores"
"""Study attribute: {trial number: the test score of its best-refit run}, so that a best trial
that is best again (after another was) is not refitted a second time."""
S = optuna.trial.TrialState


@dataclass
class StudySummary:
    """The state of a study, as recorded in its parent run and its ``sdrl.summary`` attribute."""

    name: str
    sampler: str
    n_trials: int
    n_complete: int
    n_pruned: int
    n_failed: int
    fits_total: int
    best_number: int | None = None
    best_params: dict[str, Any] = field(default_factory=dict)
    best_error: float | None = None
    best_n_terms: int | None = None
    fits_to_best: int | None = None
    best_equations: str = ""
    pareto: list[tuple[int, float, int]] = field(default_factory=list)
    """(trial number, error, active terms) of the non-dominated completed trials."""
    test_name: str | None = None
    test_error: float | None = None
    """``mse_norm/mean`` of the best params refitted on all the data, on the fixed test set."""
    test_metrics: dict[str, float] = field(default_factory=dict)
    overrides: list[str] = field(default_factory=list)
    experiment_yaml: str = ""


def pareto_front(points: list[tuple[int, float, int]]) -> list[tuple[int, float, int]]:
    """Non-dominated (number, error, terms) points: no other point is at least as good in both
    and better in one. Sorted by terms."""
    front = [p for p in points if not any(
        (q[1] <= p[1] and q[2] <= p[2]) and (q[1] < p[1] or q[2] < p[2]) for q in points)]
    return sorted(front, key=lambda p: (p[2], p[1], p[0]))


def pick_best(study: optuna.Study) -> optuna.trial.FrozenTrial | None:
    """Single objective: Optuna's best trial. Several: the Pareto trial with the lowest error
    (fewest terms on ties)."""
    complete = study.get_trials(deepcopy=False, states=(S.COMPLETE,))
    if not complete:
        return None
    if len(study.directions) == 1:
        return study.best_trial
    return min(study.best_trials, key=lambda t: (t.values[0], t.values[1], t.number))


def summarize(
    result: WorkerResult,
    build_job: BuildJob,
    final_score: bool = True,
    export_dir: str | Path | None = None,
    on_wait: Callable[[], None] | None = None,
) -> StudySummary:
    """Record the study's current state: best trial (refitted and scored on the fixed test set
    when ``final_score``), counts and fits, figures, and the best config (as ``sdrl-bench``
    overrides and an experiment pack, also written under ``export_dir/experiment/``). Workers of
    one study on one host summarize one at a time (``storage.summary_lock``; ``on_wait`` is called
    once if this one waits for another's)."""
    try:
        with summary_lock(result.storage, result.settings.name, on_wait):
            return _summarize(result, build_job, final_score, export_dir)
    except BaseException as exc:  # the parent shows it (a rerun summarizes again and finishes it)
        stopped = isinstance(exc, KeyboardInterrupt) or stop_signal_received()
        with contextlib.suppress(Exception):  # a store that is down must not hide why the summary failed
            tracking.end_run(result.tracking_uri, result.parent_run_id, "KILLED" if stopped else "FAILED")
        raise


EXPORT_MARK = "# Best trial "
"""The second line of a best config this harness exported (``experiment_pack``'s header)."""


def export_path(export_dir: str | Path, study: str) -> Path:
    """Where study ``study`` writes its best config under ``export_dir``."""
    return Path(export_dir) / "experiment" / f"{study}.yaml"


def check_export(export_dir: str | Path | None, study: str) -> None:
    """Before any data or trial: the best config can be written under ``export_dir`` (no file
    where a folder must be, a writable folder), and the file it would replace, if any, is a best
    config of this study exported before (a rerun refreshes it), never a file of the user's:
    that is a one-line ``ConfigError`` naming ``study.export_dir``."""
    if export_dir is None:
        return
    path = export_path(export_dir, study)
    there = nearest_existing(path.parent)
    if not there.is_dir():
        raise ConfigError(f"study.export_dir: {there} is a file, not a folder (the best config goes to {path})")
    if not os.access(there, os.W_OK):
        raise ConfigError(f"study.export_dir: {there} is not writable (the best config goes to {path})")
    if path.exists():
        try:
            second = (path.read_text(errors="replace").splitlines()[1:2] or [""])[0]
        except OSError as exc:  # a folder by that name, unreadable
            raise ConfigError(f"study.export_dir: {path} cannot be replaced ({type(exc).__name__})") from None
        if not (second.startswith(EXPORT_MARK) and f"of study '{study}'" in second):
            raise ConfigError(f"study.export_dir: {path} exists and is not a best config this study exported; "
                              "move it, or set study.export_dir to another folder")


def _summarize(result: WorkerResult, build_job: BuildJob, final_score: bool, export_dir: str | Path | None) -> StudySummary:
    s, study, uri, parent = result.settings, result.study, result.tracking_uri, result.parent_run_id
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        optuna.storages.fail_stale_trials(study)
    trials = study.get_trials(deepcopy=False)
    _close_orphan_runs(uri, s.experiment, parent, {t.number: t.state for t in trials})
    done = [t for t in trials if counted(t)]
    complete = [t for t in trials if t.state == S.COMPLETE]
    summary = StudySummary(
        name=s.name, sampler=s.sampler, n_trials=len(done), n_complete=len(complete),
        n_pruned=sum(t.state == S.PRUNED for t in trials), n_failed=sum(t.state == S.FAIL for t in done),
        fits_total=sum(int(t.user_attrs.get("n_fits", 0)) for t in done),
    )
    points = [(t.number, float(t.values[0]), int(t.user_attrs["n_terms"])) for t in complete if "n_terms" in t.user_attrs]
    summary.pareto = pareto_front(points)
    best = pick_best(study)
    parent_run = tracking.Run(uri, parent)
    if best is not None:
        _describe_best(summary, best, done, s.context)
        previous = study.user_attrs.get(SUMMARY_ATTR) or {}
        scores = dict(study.user_attrs.get(REFITS_ATTR) or {})  # {trial number: its refit's test score}
        if previous.get("best_number") == best.number and previous.get("test_metrics"):  # before REFITS_ATTR
            scores.setdefault(str(best.number), {k: previous.get(k) for k in ("test_name", "test_error", "test_metrics")})
        known = scores.get(str(best.number))
        if final_score and not (known and _refit_run(result, best.number)):
            _final_score(summary, result, build_job, best)
            scores[str(best.number)] = {"test_name": summary.test_name, "test_error": summary.test_error,
                                        "test_metrics": summary.test_metrics}
            study.set_user_attr(REFITS_ATTR, json.loads(json.dumps(scores, default=str)))
        elif known:  # its test score stands (and its refit run, when there is one: a rerun adds none)
            summary.test_name, summary.test_error = known.get("test_name"), known.get("test_error")
            summary.test_metrics = dict(known.get("test_metrics") or {})
        _log_figures(parent_run, study, complete, points, summary)
    _log_parent(parent_run, result, summary)
    if export_dir is not None and summary.experiment_yaml:
        path = export_path(export_dir, s.name)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(summary.experiment_yaml)
    study.set_user_attr(SUMMARY_ATTR, json.loads(json.dumps(asdict(summary), default=str)))
    parent_run.end("FINISHED")  # also after an earlier worker left it FAILED or KILLED
    return summary


def _close_orphan_runs(uri: str, experiment: str, parent: str, states: Mapping[int, Any]) -> None:
    """Trial runs left RUNNING by a worker that died before its trial was linked to the run:
    once Optuna no longer considers the trial running, the run ends KILLED."""
    filt = f"tags.`{tracking.PARENT_TAG}` = '{parent}' and attributes.status = 'RUNNING'"
    for r in tracking.find_runs(uri, experiment, filt):
        number = r["tags"].get("optuna.trial")
        if number is not None and states.get(int(number), S.FAIL) != S.RUNNING:
            tracking.Run(uri, r["run_id"]).set_tags({"optuna.state": "FAIL", "error": "worker process died"})
            tracking.end_run(uri, r["run_id"], "KILLED")


def _describe_best(summary: StudySummary, best, done, context: Mapping[str, Any]) -> None:
    summary.best_number = best.number
    summary.best_params = dict(best.params)
    summary.best_error = float(best.values[0])
    summary.best_n_terms = best.user_attrs.get("n_terms")
    summary.best_equations = best.user_attrs.get("equations", "")
    summary.fits_to_best = sum(int(t.user_attrs.get("n_fits", 0)) for t in done if t.number <= best.number)
    choices = {k: str(v) for k, v in context.get("choices", {}).items()}
    values = dict(context.get("values", {}))
    summary.overrides = to_overrides(best.params, choices) + [f"{k}={v}" for k, v in values.items()]
    header = (f"{EXPORT_MARK[2:]}{best.number} of study '{summary.name}' ({summary.sampler}): held-out "
              f"error {summary.best_error:.4g}" + ("" if summary.best_n_terms is None else
                                                   f", {summary.best_n_terms} active terms") + ".\n"
              f"Use: sdrl-bench 'hydra.searchpath=[file://<the folder holding experiment/>]' "
              f"experiment={summary.name}\n(or copy it into <your --config-dir>/experiment/ and run: sdrl-bench experiment={summary.name})")
    summary.experiment_yaml = experiment_pack(best.params, choices, values, header)


def _refit_run(result: WorkerResult, number: int) -> str | None:
    """The id of a FINISHED best-refit run of trial ``number`` under the study's parent, if any."""
    filt = (f"tags.`{tracking.PARENT_TAG}` = '{result.parent_run_id}' and tags.`sdrl.role` = 'best-refit' "
            f"and tags.`optuna.trial` = '{number}' and attributes.status = 'FINISHED'")
    found = tracking.find_runs(result.tracking_uri, result.settings.experiment, filt)
    return found[0]["run_id"] if found else None


def _final_score(summary: StudySummary, result: WorkerResult, build_job: BuildJob, best) -> None:
    s = result.settings
    fit = fit_dynamics(build_job(best.params))
    tags = {"sdrl.study": s.name, "optuna.trial": best.number, "sdrl.role": "best-refit", "env": fit.job.spec.name,
            "seed": fit.job.seed, **{k: v for k, v in fit.job.names.items() if k in ("collector", "library", "optimizer")}}
    with tracking.tracked_run(result.tracking_uri, s.experiment, f"{s.name}-best-refit", "fit", tags, result.parent_run_id,
                              source="sdrl-bench-search") as run:
        tracking.log_fit(run, fit, fit_params(s.context, best.params))
    summary.test_name = fit.test_name
    summary.test_metrics = {k: float(v) for k, v in fit.fidelity.metrics.items()}
    summary.test_error = summary.test_metrics.get("mse_norm/mean")


def _log_figures(run: tracking.Run, study, complete, points, summary: StudySummary) -> None:
    title = f"{summary.name} ({summary.sampler}, {summary.n_trials} trials)"
    run.log_figure(history_figure([t.number for t in complete], [t.values[0] for t in complete], title),
                   "figures/optimization_history.png")
    if points:
        front = {p[0] for p in summary.pareto}
        run.log_figure(pareto_figure([p[1] for p in points], [p[2] for p in points], [p[0] in front for p in points],
                                     title), "figures/pareto_front.png")
    # over the params every trial has (a value sampled only under some choices, alpha with STLSQ,
    # would restrict the importances to those trials and leave its choice no importance)
    names = list(dict.fromkeys(k for t in complete for k in t.params))
    shared = [k for k in names if all(k in t.params for t in complete)]
    searched = [k for k in shared if len({repr(t.params[k]) for t in complete}) > 1]
    if set(names) - set(shared):
        run.set_tags({"importance.left_out": ",".join(k for k in names if k not in shared)})
    if len(complete) >= 2 and searched:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # PED-ANOVA's note on the target's sign
                imp = optuna.importance.get_param_importances(study, params=searched, target=lambda t: t.values[0])
        except (ValueError, RuntimeError, ZeroDivisionError) as exc:
            run.set_tags({"importance.error": str(exc).splitlines()[0][:500]})
        else:
            run.log_figure(importance_figure(imp, title), "figures/param_importances.png")


def _log_parent(run: tracking.Run, result: WorkerResult, summary: StudySummary) -> None:
    s = result.settings
    run.log_params({"env": result.data.spec.name, "k_folds": s.k_folds, "objectives": ",".join(s.objectives),
                    "space": json.dumps(describe_space(s.space)), "dataset_sha256": result.data.sha256,
                    "n_transitions": len(result.data.data)})
    metrics = {"n_trials": summary.n_trials, "n_complete": summary.n_complete, "n_pruned": summary.n_pruned,
               "n_failed": summary.n_failed, "fits_total": summary.fits_total, "pareto_size": len(summary.pareto)}
    if summary.best_number is not None:
        metrics.update({"best_error": summary.best_error, "best_trial": summary.best_number,
                        "fits_to_best": summary.fits_to_best})
        if summary.best_n_terms is not None:
            metrics["best_n_terms"] = summary.best_n_terms
        metrics.update({f"test/{k}": v for k, v in summary.test_metrics.items()})
        run.set_tags({**{f"best.{k}": v for k, v in summary.best_params.items()},
                      "best.overrides": " ".join(summary.overrides), "sampler": s.sampler})
        run.log_text(summary.experiment_yaml, f"best/{s.name}.yaml")
        run.log_text(" ".join(summary.overrides) + "\n", "best/overrides.txt")
        run.log_text(summary.best_equations or "\n", "best/equations.txt")
    run.log_metrics(metrics, step=summary.n_trials)
    run.log_dict(json.loads(json.dumps(asdict(summary), default=str)), "best/summary.json")


def load_summaries(storage: str | None, names: list[str]) -> list[dict[str, Any]]:
    """The recorded summaries of finished studies (``summarize`` output), by name (a name the
    storage lacks, or a local storage file that does not exist, is a one-line ``ConfigError``:
    comparing creates nothing)."""
    from sdrl_bench import ConfigError

    url = resolve_storage(storage)
    local = local_file(url)
    if local is not None and not local.exists():
        raise ConfigError(f"study.storage: {redact(url)} does not exist (no study to compare in it)")
    st = open_storage(url)
    out = []
    for name in names:
        try:
            study = optuna.load_study(study_name=name, storage=st)
        except KeyError:
            known = sorted(optuna.get_all_study_names(storage=st))
            raise ConfigError(f"search.studies: no study named '{name}' in {redact(url)} (it holds {known})") from None
        out.append(study.user_attrs.get(SUMMARY_ATTR) or {"name": name})
    return out


def comparison_table(rows: list[Mapping[str, Any]]) -> str:
    """A plain-text table of studies (validation error, test error, trials, fits) and which
    found the better model (lower test error; equal within 10% counts as a tie)."""
    head = f"{'study':<28} {'sampler':<7} {'cv error':>10} {'test err':>10} {'terms':>5} {'trials':>6} {'fits->best':>10} {'fits':>6}"
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(
            f"{r['name']:<28} {r.get('sampler', '?'):<7} {_g(r.get('best_error')):>10} {_g(r.get('test_error')):>10} "
            f"{r.get('best_n_terms') or '-':>5} {r.get('n_trials', 0):>6} {r.get('fits_to_best') or '-':>10} {r.get('fits_total', 0):>6}"
        )
    scored = [r for r in rows if r.get("test_error") is not None]
    if len(scored) >= 2:
        a, b = sorted(scored, key=lambda r: r["test_error"])[:2]
        if a["test_error"] >= 0.9 * b["test_error"]:
            fewer = min(scored, key=lambda r: r.get("fits_to_best") or 0)
            lines.append(f"verdict: equal test error within 10%; '{fewer['name']}' got there with fewer fits "
                         f"({fewer.get('fits_to_best')})")
        else:
            lines.append(f"verdict: '{a['name']}' finds the better model (test error {_g(a['test_error'])} vs "
                         f"{_g(b['test_error'])}) after {a.get('fits_to_best')} fits ({a.get('fits_total')} in all)")
    return "\n".join(lines)


def _g(v: Any) -> str:
    return "-" if v is None else f"{float(v):.3e}"
