"""Optuna search over SINDy hyperparameters, every trial tracked.

The data are collected once per study (same seed, same data for every trial and every worker;
its hash is part of the study). A trial samples parameters from the search space, builds the
fit they describe (``build_job(params)``: the ``sdrl-bench`` config with those overrides) and
scores it by k-fold validation on the collected data (``validation``); the env's fixed test
set is only used to score the best trial at the end (``search.summary.summarize``).

``run_study`` is one worker: any number of them, in one process, several processes or several
machines, can share a study through its storage. ``n_trials`` is the study's budget (finished
trials over all workers and reruns), so a rerun after a crash completes the study.

About 320 lines: the settings, the data, the objective and the worker loop (with heartbeats and
stale-trial repair) are one unit that a reader follows top to bottom.
"""

from __future__ import annotations

import contextlib
import dataclasses
import warnings
from collections import Counter
from dataclasses import dataclass, field
from typing import Any
from collections.abc import Callable, Mapping

import numpy as np
import optuna

from sdrl_bench import ConfigError, raise_pending_stop, redact, stop_signal_received, stop_signals_held, seeds, tracking
from sdrl_bench.data import Transitions, collect, random_policy
from sdrl_bench.envs.base import EnvSpec
from sdrl_bench.models.libraries import build_library
from sdrl_bench.pipeline import FitJob, build_model, check
from sdrl_bench.fidelity import DATA_METRICS, POLICY_METRICS
from sdrl_bench.search.space import (GROUP_PARAMS, NN_PARAMS, PARAM_KEYS, Conditions, SearchSpace, describe_space,
                                     grid_values, suggest)
from sdrl_bench.search.location import resolve_storage
from sdrl_bench.search.storage import open_storage, open_study, study_parent_run
from sdrl_bench.search.validation import Fold, aggregate, cross_validate, fit_model, make_folds, resolution_floor

warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)
optuna.logging.set_verbosity(optuna.logging.WARNING)

OBJECTIVES = ("error", "n_terms")
ERROR_METRICS = DATA_METRICS
"""What the ``error`` objective measures on each validation fold (``search.objective``): today's
one-step error, or an open-loop error of the fidelity study (``fidelity.rollout_error`` /
``episode_error``: k steps, or whole validation episodes; a diverged rollout counts as its cap)."""
SAMPLERS = ("tpe", "random", "grid", "nsga2")
OBJECTIVE_VERSION = "geomean over folds of (mean normalized one-step MSE + float floor), v1"
TRIAL_ERRORS: tuple[type[BaseException], ...] = (ConfigError, ValueError, ArithmeticError, np.linalg.LinAlgError)
"""Errors that fail one trial (a candidate that cannot be fitted) without stopping the study."""

BuildJob = Callable[[Mapping[str, Any]], FitJob]


@dataclass(frozen=True)
class StudySettings:
    """What a study searches and how; validated by ``check_settings`` before any work."""

    name: str
    """Study name: rerunning with the same name (and storage) resumes the study."""
    space: SearchSpace
    """Parameters and distributions (``search.space.parse_space``)."""
    storage: str | None = None
    """Optuna storage URL; None: ``sqlite:///mlruns/optuna.db``; ``journal:<file>`` for a journal."""
    objectives: tuple[str, ...] = ("error",)
    """``("error",)`` or ``("error", "n_terms")`` (multi-objective: the Pareto front)."""
    objective: str = "one_step"
    """What ``error`` measures: on each validation fold (``ERROR_METRICS``), or with a policy on a
    fit to all the data (``POLICY_METRICS``, scored by ``policy``)."""
    policy: Any = None
    """A policy objective's ``rl.fidelity_study.PolicyProbe`` (agent, budget, real episodes)."""
    sampler: str = "tpe"
    """``tpe``, ``random``, ``grid`` (every grid point once) or ``nsga2``."""
    n_trials: int = 100
    """Budget of the study: finished trials over every worker and rerun (grid: its size)."""
    k_folds: int = 5
    """Validation folds over episodes (or time blocks of a single episode)."""
    pruner: str = "median"
    """``median`` (stop a trial whose running fold error is worse than the median) or ``none``."""
    seed: int = 0
    """Sampler seed; each worker adds its worker id."""
    worker: int = 0
    """Worker id (a label on its trials, and a sampler-seed offset)."""
    heartbeat_interval: int = 1
    """Seconds between heartbeats of a running trial (RDB storages)."""
    heartbeat_grace: int = 10
    """Seconds without a heartbeat after which a running trial counts as dead (FAIL)."""
    tracking_uri: str | None = None
    """MLflow tracking URI (None: ``tracking.resolve_uri`` default)."""
    experiment: str = "sdrl-bench-search"
    """MLflow experiment of the parent and trial runs."""
    context: Mapping[str, Any] = field(default_factory=dict)
    """Fixed settings the objective depends on (group choices, config values): recorded with
    the study and compared on resume, and written into the exported best config."""
    when: Conditions = field(default_factory=dict)
    """Values sampled only under some group choices (``search.space.conditions``: alpha only
    in the trials whose optimizer reads it)."""


@dataclass(frozen=True)
class StudyData:
    """The data every trial of a study is validated on."""

    spec: EnvSpec
    data: Transitions
    folds: list[Fold]
    floor: float
    exclude_bound: bool
    sha256: str
    objective: str = "one_step"


@dataclass(frozen=True)
class TrialOutcome:
    """What evaluating one parameter set gave."""

    error: float
    fold_errors: list[float]
    pruned: bool = False
    n_terms: int | None = None
    n_fits: int = 0
    equations: str = ""
    real_steps: dict[str, float] = field(default_factory=dict)
    """Real steps the objective took (a policy objective's episodes), by purpose."""


@dataclass
class WorkerResult:
    """What one ``run_study`` call did."""

    study: optuna.Study
    settings: StudySettings
    data: StudyData
    parent_run_id: str
    tracking_uri: str
    storage: str
    trials: list[int] = field(default_factory=list)
    """Numbers of the trials this worker ran (any final state)."""


def check_settings(s: StudySettings) -> None:
    """One-line ``ConfigError``s for settings that cannot work."""
    if not s.objectives or s.objectives[0] != "error" or len(set(s.objectives)) != len(s.objectives) \
            or any(o not in OBJECTIVES for o in s.objectives):
        raise ConfigError(f"search.objectives: use [error] or [error, n_terms], got {list(s.objectives)}")
    if s.objective not in ERROR_METRICS + POLICY_METRICS:
        raise ConfigError(f"search.objective: one of {list(ERROR_METRICS + POLICY_METRICS)}, got {s.objective!r}")
    if s.objective in POLICY_METRICS and s.policy is None:
        raise ConfigError(f"search.objective={s.objective} needs a policy: set search.policy (train_steps, episodes, reference)")
    if s.sampler not in SAMPLERS:
        raise ConfigError(f"search.sampler: one of {list(SAMPLERS)}, got {s.sampler!r}")
    if s.sampler == "grid":
        grid = grid_values(s.space)
        for name, conds in s.when.items():
            if len(grid[name]) < 2:
                continue  # one value: each point of the other choices is fitted once anyway
            group, options = conds[0]
            raise ConfigError(f"search.space.{name}: only {group}={','.join(sorted(options))} reads it, so the grid "
                              f"would fit the other {group} choices once per {name} value; use search.sampler=tpe "
                              f"or random, or one grid study per {group}")
    if s.pruner not in ("median", "none"):
        raise ConfigError(f"search.pruner: 'median' or 'none', got {s.pruner!r}")
    if s.pruner != "none" and len(s.objectives) > 1:
        raise ConfigError("search.pruner: pruning needs a single objective; set search.pruner=none")
    if s.n_trials < 0:
        raise ConfigError(f"search.n_trials must be >= 0, got {s.n_trials}")
    if s.k_folds < 2:
        raise ConfigError(f"search.k_folds must be >= 2, got {s.k_folds}")
    if s.heartbeat_interval < 1 or s.heartbeat_grace < 1:
        raise ConfigError("study.heartbeat_interval and study.heartbeat_grace must be >= 1 second")


def check_space(space: SearchSpace, build_job: BuildJob, env: str, key: str = "search.space") -> None:
    """Every value a study can give a parameter, checked once against the run's env and the
    values' domains before any data are collected: each categorical choice and each numeric
    bound (with the other settings the run's own) builds the fit ``sdrl-bench`` would run and
    passes ``pipeline.check``, else a one-line ``ConfigError`` naming the ``search.space`` key
    (instead of every trial failing with the same error). The collector, which no searched
    parameter changes, is the run's own and checked with it (``run_study``), not per value."""
    for p in space:
        if p.kind == "categorical":
            values = [("choices", c) for c in p.choices or ()]
        else:
            values = [("low", p.low), ("high", p.high)]
        for field_name, value in values:
            try:
                check(dataclasses.replace(build_job({p.name: value}), policy=None))
            except TRIAL_ERRORS as exc:
                reason = " ".join(str(exc).split()) or type(exc).__name__
                if not isinstance(exc, ConfigError):
                    reason = f"{type(exc).__name__}: {reason}"
                raise ConfigError(f"{key}.{p.name}.{field_name}: {value!r} cannot be fitted on env '{env}': "
                                  f"{reason}") from None


def study_data(job: FitJob, k_folds: int, objective: str = "one_step",
               checked: tuple[Any, Transitions | None] | None = None) -> StudyData:
    """Collect (or load) the study's data once, as ``pipeline.fit_dynamics`` would (the same
    reset seeds: the data of ``sdrl-bench seed=<study seed>``). A k-step objective needs a
    validation episode of k transitions in every fold (checked here, before any trial).
    ``checked``: what ``check(job)`` returned, when the caller checked the job already."""
    _, loaded = checked if checked is not None else check(job)
    data = loaded if loaded is not None else collect(
        job.spec, job.policy or random_policy, job.n_transitions, job.epsilon, seeds.reset_seed(job.seed, "collect"),
        max_steps_per_episode=job.max_steps_per_episode,
    )
    folds = make_folds(data, k_folds)
    k = int(objective[len("rollout"):]) if objective[len("rollout"):].isdigit() else 0
    for i, fold in enumerate(folds):
        valid = data.subset(fold.valid)
        if k and max(np.bincount(valid.episode - valid.episode.min())) < k:
            raise ConfigError(f"search.objective={objective}: validation fold {i} holds no episode of {k} transitions; "
                              "use rollout10, rollout_episode or more data")
    return StudyData(
        spec=job.spec, data=data, folds=folds, floor=resolution_floor(job.spec, data),
        exclude_bound=job.exclude_bound_transitions, sha256=data.content_hash(), objective=objective,
    )


def evaluate_params(
    params: Mapping[str, Any],
    build_job: BuildJob,
    sd: StudyData,
    report: Callable[[int, float], bool] | None = None,
    policy: Any = None,
    trial: int = 0,
) -> TrialOutcome:
    """k-fold error of the fit ``build_job(params)`` describes, then a fit on all the data for
    its number of active terms. ``report(fold, running error)`` returning True stops early.
    A policy objective (``policy``, a ``PolicyProbe``) scores the fit on all the data instead."""
    with warnings.catch_warnings():
        # pysindy warns when a threshold removes every term: that candidate simply scores badly
        warnings.simplefilter("ignore", UserWarning)
        return _evaluate(build_job(params), sd, report, policy, trial)


def _evaluate(job: FitJob, sd: StudyData, report: Callable[[int, float], bool] | None, policy: Any = None,
              trial: int = 0) -> TrialOutcome:
    spec = sd.spec
    library = build_library(job.library_parts, spec.target_names, spec.control_names)

    def make():
        return build_model(job, library)

    if sd.objective in POLICY_METRICS:
        model, counts = fit_model(make, spec, sd.data, sd.exclude_bound), Counter()
        value = float(policy.score(model, spec, sd.data, trial, counts))
        active = model.summary_metrics().get("n_active_terms")
        value += sd.floor if sd.objective == "onpolicy_one_step" else 0.0  # a one-step error: float noise does not rank
        return TrialOutcome(value, [value], False, None if active is None else int(active), 1, model.describe(),
                            {"selection": float(counts["onpolicy"] + counts["reference"]),
                             "resets/reset_pool": float(counts["resets/reset_pool"])})

    errors: list[float] = []
    folds = cross_validate(make, spec, sd.data, sd.folds, sd.exclude_bound, sd.objective)
    for i, err in enumerate(folds):
        errors.append(err)
        if report is not None and report(i, aggregate(errors, sd.floor)):
            return TrialOutcome(aggregate(errors, sd.floor), errors, pruned=True, n_fits=len(errors))
    model = fit_model(make, spec, sd.data, sd.exclude_bound)
    active = model.summary_metrics().get("n_active_terms")  # None: a model without terms (an NN)
    n_terms = None if active is None else int(active)
    return TrialOutcome(aggregate(errors, sd.floor), errors, False, n_terms, len(errors) + 1, model.describe())


def make_sampler(s: StudySettings, resumed_at: int = 0) -> optuna.samplers.BaseSampler:
    """The study's sampler: each worker its own stream, and a study resumed with ``resumed_at``
    trials in it a stream of its own too. A sampler seeded as at the start would draw the
    start's random points again (TPE's first ten, a random search's every one): a rerun of a
    3-trial TPE study ran its trial 0's parameters as trial 3. A new study (0) keeps the
    stream it always had."""
    sub = (s.worker, resumed_at) if resumed_at else (s.worker,)
    seed = int(seeds.generator(s.seed, "search", *sub).integers(2**31))
    if s.sampler == "grid":
        return optuna.samplers.GridSampler(grid_values(s.space), seed=seed)
    if s.sampler == "random":
        return optuna.samplers.RandomSampler(seed=seed)
    if s.sampler == "nsga2":
        return optuna.samplers.NSGAIISampler(seed=seed)
    # multivariate + group: one model over the joint space (the library choice and the
    # thresholds interact), a value sampled only under some choices (alpha) modelled over the
    # trials that have it; constant_liar keeps parallel workers from sampling the same point
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        return optuna.samplers.TPESampler(seed=seed, multivariate=True, group=True, constant_liar=True)


def make_pruner(s: StudySettings) -> optuna.pruners.BasePruner:
    if s.pruner == "median":
        return optuna.pruners.MedianPruner(n_startup_trials=10, n_warmup_steps=1)
    return optuna.pruners.NopPruner()


def counted(trial: optuna.trial.FrozenTrial) -> bool:
    """A trial that uses up budget: complete, pruned, or failed by its own candidate (a trial
    failed because its process died is not counted: a rerun replaces it)."""
    S = optuna.trial.TrialState
    return trial.state in (S.COMPLETE, S.PRUNED) or (trial.state == S.FAIL and "error" in trial.user_attrs)


def n_counted(study: optuna.Study) -> int:
    return sum(counted(t) for t in study.get_trials(deepcopy=False))


def fingerprint(s: StudySettings, sd: StudyData) -> dict[str, Any]:
    """What a study's trials are comparable under: checked when the study is resumed."""
    return {
        "space": describe_space(s.space),
        "objectives": list(s.objectives),
        "objective": OBJECTIVE_VERSION if s.objective == "one_step" else f"{s.objective}: {OBJECTIVE_VERSION}",
        "k_folds": s.k_folds,
        "data": {"env": sd.spec.name, "n_transitions": len(sd.data), "sha256": sd.sha256},
        "context": {k: v for k, v in s.context.items()},
        **({"policy": s.policy.describe()} if s.policy is not None else {}),
    }


def check_study(settings: StudySettings, build_job: BuildJob) -> tuple[FitJob, Any]:
    """The settings, the run's own fit (``pipeline.check``), then each value of the space against
    it: (the base job, what its check returned). Nothing collected, no store opened."""
    check_settings(settings)
    base = build_job({})
    checked = check(base)  # the run's own fit first: a space's value is then the only change
    check_space(settings.space, build_job, base.spec.name)
    return base, checked


def run_study(
    settings: StudySettings,
    build_job: BuildJob,
    progress: Callable[[optuna.trial.FrozenTrial], None] | None = None,
) -> WorkerResult:
    """Run one worker of a study until the study holds ``n_trials`` counted trials.

    Everything is checked (settings, storage, tracking store, data, stored study setup) before
    the first trial starts. Each trial is an MLflow child run of the study's parent run.
    """
    base, checked = check_study(settings, build_job)
    storage_url = resolve_storage(settings.storage)
    uri = tracking.resolve_uri(settings.tracking_uri)

    def on_stale(study: optuna.Study, trial: optuna.trial.FrozenTrial) -> None:
        run_id = trial.user_attrs.get("mlflow_run_id")
        if run_id:  # also a run that ended FINISHED: its worker died before Optuna recorded the trial
            tracking.Run(uri, run_id).set_tags({"optuna.state": "FAIL", "error": "worker process died"})
            tracking.end_run(uri, run_id, "KILLED", also_ended=True)

    heartbeat = settings.heartbeat_interval if not storage_url.startswith("journal:") else None
    storage = open_storage(storage_url, heartbeat, settings.heartbeat_grace if heartbeat else None, on_stale)
    tracking.ensure_experiment(uri, settings.experiment)
    tracking.end_runs_of_dead_processes(uri, settings.experiment, "sdrl-bench-search")
    sd = study_data(base, settings.k_folds, settings.objective, checked)
    directions = ["minimize"] * len(settings.objectives)
    where = f" in {redact(storage_url)}"
    study = open_study(storage, settings.name, directions, fingerprint(settings, sd),
                       make_sampler(settings), make_pruner(settings), where)
    if resumed_at := len(study.get_trials(deepcopy=False)):
        study.sampler = make_sampler(settings, resumed_at)
    parent = study_parent_run(
        uri, settings.experiment, settings.name, redact(storage_url),
        {"env": sd.spec.name, "sampler": settings.sampler, "objectives": ",".join(settings.objectives),
         "search.objective": settings.objective,
         **tracking.standard_tags("sdrl-bench-search")},  # git_commit as every run's (the checkout's from elsewhere)
    )
    result = WorkerResult(study, settings, sd, parent, uri, storage_url)
    remaining = settings.n_trials - n_counted(study)
    if remaining <= 0:
        return result

    def budget(study: optuna.Study, trial: optuna.trial.FrozenTrial) -> None:
        result.trials.append(trial.number)
        if progress is not None:
            progress(trial)
        if n_counted(study) >= settings.n_trials:
            study.stop()
        raise_pending_stop()  # Optuna has stored the trial: a safe point to stop

    objective = _objective(settings, build_job, sd, uri, parent)
    try:
        with stop_signals_held():  # raised only inside a trial's work or between trials
            study.optimize(objective, n_trials=remaining, callbacks=[budget], catch=TRIAL_ERRORS,
                           gc_after_trial=False)
    except BaseException as exc:  # the parent shows it; a later summarize (resume) finishes it
        stopped = isinstance(exc, KeyboardInterrupt) or stop_signal_received()
        tracking.end_run(uri, parent, "KILLED" if stopped else "FAILED")
        raise
    return result


FIT_PARAM_NAMES = {"library": "library.name", "optimizer": "optimizer.name", "threshold": "optimizer.threshold",
                   "alpha": "optimizer.alpha", "normalize_columns": "optimizer.normalize_columns",
                   "poly_degree": "env.poly_degree",
                   **{k: PARAM_KEYS[k] for k in NN_PARAMS}}
"""A searched parameter -> the name a fit run logs it under (``tracking.used_params``)."""


def fit_params(context: Mapping[str, Any], params: Mapping[str, Any]) -> dict[str, Any]:
    """A trial's params under the names a fit run uses: the study's fixed values (seed,
    n_transitions, collector.epsilon, ...) and group choices, then the searched ones."""
    out: dict[str, Any] = {f"{g}.name": v for g, v in dict(context.get("choices", {})).items() if g != "env"}
    out.update(dict(context.get("values", {})))
    out.update({FIT_PARAM_NAMES.get(k, k): v for k, v in params.items()})
    return out


def _objective(s: StudySettings, build_job: BuildJob, sd: StudyData, uri: str, parent: str):
    prune = s.pruner != "none" and len(s.objectives) == 1

    def objective(trial: optuna.Trial) -> float | tuple[float, float]:
        params = suggest(trial, s.space, s.when)
        trial.set_user_attr("worker", s.worker)
        choices = {**dict(s.context.get("choices", {})), **{k: v for k, v in params.items() if k in GROUP_PARAMS}}
        tags = {"sdrl.study": s.name, "optuna.trial": trial.number, "sdrl.worker": s.worker, "env": sd.spec.name,
                **{k: str(v) for k, v in choices.items() if k in ("collector", "library", "optimizer")},
                "seed": dict(s.context.get("values", {})).get("seed", "")}

        def report(step: int, value: float) -> bool:
            with stop_signals_held():  # Optuna's storage
                trial.report(value, step)
                return trial.should_prune()

        # Stop signals pass in the trial's run (its work and its MLflow calls: a request to a server
        # that died mid-trial would otherwise retry for minutes before a held stop is raised) and
        # are held only while the objective tells Optuna's storage.
        run_id = None
        try:
            with stop_signals_held(False), tracking.tracked_run(uri, s.experiment, f"{s.name}-trial-{trial.number}", "trial",
                                                                tags, parent, source="sdrl-bench-search") as run:
                run_id = run.run_id
                with stop_signals_held():
                    trial.set_user_attr("mlflow_run_id", run.run_id)
                run.log_params(fit_params(s.context, params))
                try:
                    out = evaluate_params(params, build_job, sd, report if prune else None, s.policy, trial.number)
                except TRIAL_ERRORS as exc:
                    msg = f"{type(exc).__name__}: {str(exc).strip()}".splitlines()[0][:500]
                    with stop_signals_held():
                        trial.set_user_attr("error", msg)
                    run.set_tags({"optuna.state": "FAIL", "error": msg})
                    raise
                run.log_metrics({"error": out.error, "n_fits": out.n_fits, **{f"real_steps/{k}": v for k, v in out.real_steps.items()},
                                 **{f"fold_error/{i}": e for i, e in enumerate(out.fold_errors)},
                                 **({"n_terms": out.n_terms} if out.n_terms is not None else {})})
                run.set_tags({"optuna.state": "PRUNED" if out.pruned else "COMPLETE"})
                if out.equations:
                    run.log_text(out.equations, "model/equations.txt")
        except KeyboardInterrupt:  # a stop: the trial fails, so its run ends KILLED, also one that landed FINISHED
            if run_id is not None:  # as the stop came (the run's last request under way)
                with contextlib.suppress(Exception):
                    tracking.end_run(uri, run_id, "KILLED", also_ended=True)
            raise
        trial.set_user_attr("fold_errors", out.fold_errors)
        trial.set_user_attr("n_fits", out.n_fits)
        if out.pruned:
            raise optuna.TrialPruned()
        if out.n_terms is not None:
            trial.set_user_attr("n_terms", out.n_terms)
        trial.set_user_attr("equations", out.equations)
        if len(s.objectives) == 1:
            return out.error
        if out.n_terms is None:
            raise ConfigError("search.objectives: n_terms counts a model's active terms; this model has none: use [error]")
        return out.error, float(out.n_terms)

    return objective
