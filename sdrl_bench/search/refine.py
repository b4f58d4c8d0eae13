"""Residual-guided library refinement (the paper's stage 2).

Start from a simple library. At each stage, score every remaining candidate term family
(trigonometric, rational, ...) twice: by how much of the current model's held-out residuals
its features explain (the residual score: what the misfit looks like), and by the held-out
error of the library with the family added. The family with the lowest error is added when it
lowers the error by at least the relative ``margin``; otherwise refinement stops. Every
library is scored with the best of several optimizers (e.g. STLSQ thresholds) on the same k
folds as the search, and every stage lists its candidates in residual-score order.
"""

from __future__ import annotations

import copy
import dataclasses
import warnings
from dataclasses import dataclass, field
from typing import Any
from collections.abc import Callable, Mapping, Sequence

import numpy as np

from sdrl_bench import ConfigError, tracking
from sdrl_bench.models.base import DynamicsModel
from sdrl_bench.models.libraries import LibraryPart, build_library
from sdrl_bench.models.sindy import SindyModel
from sdrl_bench.pipeline import FitJob, FitResult, fit_dynamics
from sdrl_bench.search.study import StudyData, study_data
from sdrl_bench.search.validation import aggregate, fit_model, fold_residuals


@dataclass(frozen=True)
class Candidate:
    """One library scored during refinement."""

    families: tuple[str, ...]
    """Families added to the base library (empty: the base alone)."""
    error: float
    """Held-out error with the best optimizer (``validation.aggregate`` over folds)."""
    optimizer: str
    """Label of that optimizer."""
    n_terms: int
    """Active terms of that library and optimizer fitted on all the data."""
    residual_score: float | None = None
    """Share of the previous model's held-out residual variance the added family explains."""
    accepted: bool = False


@dataclass
class Refinement:
    """Stages of a refinement: ``stages[0]`` is the base library, each later stage lists the
    candidates tried (best residual score first) and whether one was accepted."""

    margin: float
    stages: list[list[Candidate]] = field(default_factory=list)
    n_fits: int = 0

    @property
    def final(self) -> Candidate:
        """The last accepted library (the base if none was)."""
        accepted = [c for stage in self.stages for c in stage if c.accepted]
        return accepted[-1] if accepted else self.stages[0][0]


def residual_scores(
    sd: StudyData, rows: np.ndarray, residuals: np.ndarray, families: Mapping[str, Sequence[LibraryPart]]
) -> dict[str, float]:
    """For each family: mean over states of the R^2 of a least-squares fit of the normalized
    held-out residuals on [1, the family's features] at the same rows."""
    spec = sd.spec
    x, u = spec.model_inputs(sd.data.states[rows], sd.data.actions[rows])
    z = np.concatenate([x, u], axis=1)
    centered = residuals - residuals.mean(axis=0)
    total = np.sum(centered**2, axis=0)
    scores = {}
    for name, parts in families.items():
        lib = copy.deepcopy(build_library(parts, spec.target_names, spec.control_names))
        phi = np.column_stack([np.ones(len(z)), np.asarray(lib.fit_transform(z))])
        coef, *_ = np.linalg.lstsq(phi, residuals, rcond=None)
        explained = 1.0 - np.sum((residuals - phi @ coef) ** 2, axis=0) / np.where(total > 0, total, 1.0)
        scores[name] = float(np.mean(np.clip(explained, 0.0, 1.0)))
    return scores


def refine(
    sd: StudyData,
    base: Sequence[LibraryPart],
    families: Mapping[str, Sequence[LibraryPart]],
    optimizers: Sequence[tuple[str, Any]],
    margin: float = 0.1,
    seed: int = 0,
    on_stage: Callable[[int, list[Candidate]], None] | None = None,
) -> Refinement:
    """Grow ``base`` with ``families`` while the held-out error drops by ``margin`` (relative)."""
    if not 0.0 <= margin < 1.0:
        raise ConfigError(f"search.margin must be in [0, 1), got {margin}")
    if not optimizers:
        raise ConfigError("search.thresholds: at least one optimizer setting is needed")
    out = Refinement(margin)
    chosen: list[str] = []
    current, residual = _score(sd, list(base), (), optimizers, seed, out)
    current = Candidate(**{**current.__dict__, "accepted": True})
    out.stages.append([current])
    if on_stage:
        on_stage(0, out.stages[0])
    remaining = dict(families)
    while remaining:
        scores = residual_scores(sd, residual[0], residual[1], remaining)
        scored = []
        for name in sorted(remaining, key=lambda n: -scores[n]):
            parts = list(base) + [p for f in (*chosen, name) for p in families[f]]
            cand, cand_residual = _score(sd, parts, (*chosen, name), optimizers, seed, out)
            scored.append((Candidate(**{**cand.__dict__, "residual_score": scores[name]}), cand_residual))
        best, best_residual = min(scored, key=lambda c: c[0].error)
        ok = best.error <= (1.0 - margin) * current.error
        tried = [Candidate(**{**c.__dict__, "accepted": ok and c is best}) for c, _ in scored]
        out.stages.append(tried)
        if on_stage:
            on_stage(len(out.stages) - 1, tried)
        if not ok:
            break
        name = best.families[-1]
        chosen.append(name)
        current, residual = best, best_residual
        del remaining[name]
    return out


def _score(sd, parts, families, optimizers, seed, out: Refinement):
    spec = sd.spec
    library = build_library(parts, spec.target_names, spec.control_names)
    best = None
    for label, optimizer in optimizers:
        def make(opt=optimizer) -> DynamicsModel:
            return SindyModel(library, opt, seed)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # pysindy: a threshold removed every term
                errors, rows, res = fold_residuals(make, spec, sd.data, sd.folds, sd.exclude_bound)
        except (ConfigError, ValueError, np.linalg.LinAlgError):
            continue
        out.n_fits += len(sd.folds)
        err = aggregate(errors, sd.floor)
        if best is None or err < best[0]:
            best = (err, label, make, (rows, np.nan_to_num(res, nan=0.0, posinf=0.0, neginf=0.0)))
    if best is None:
        raise ConfigError(f"search: no optimizer setting could fit the library {list(families) or 'base'}")
    model = fit_model(best[2], spec, sd.data, sd.exclude_bound)
    out.n_fits += 1
    terms = int(model.summary_metrics().get("n_active_terms", 0))
    return Candidate(tuple(families), best[0], best[1], terms), best[3]


def log_refinement(uri: str, experiment: str, parent: str, name: str, stage: int, candidates: list[Candidate]) -> None:
    """One MLflow child run per stage: the candidates tried, their scores, what was accepted."""
    tags = {"sdrl.study": name, "stage": stage}
    with tracking.tracked_run(uri, experiment, f"{name}-stage-{stage}", "refine-stage", tags, parent,
                              source="sdrl-bench-search search=refine") as run:
        best = min(candidates, key=lambda c: c.error)
        chosen = next((c for c in candidates if c.accepted), None)
        run.log_params({"stage": stage, "tried": ",".join("+".join(c.families) or "base" for c in candidates)})
        run.log_metrics({"best_error": best.error, "best_n_terms": best.n_terms, "accepted": float(chosen is not None)})
        for i, c in enumerate(candidates):
            run.log_metrics({"candidate_error": c.error, "candidate_n_terms": c.n_terms,
                             **({"residual_score": c.residual_score} if c.residual_score is not None else {})}, step=i)
        run.log_dict({"candidates": [c.__dict__ for c in candidates]}, "stage.json")
        run.set_tags({"accepted": "+".join(chosen.families) or "base" if chosen else "none",
                      "best_candidate": "+".join(best.families) or "base", "optimizer": best.optimizer})


def run_refinement(
    base_job: FitJob, families: Mapping[str, tuple[LibraryPart, ...]], optimizers: Sequence[tuple[str, Any]], *,
    margin: float, seed: int, k_folds: int, uri: str, experiment: str, name: str, library_label: str,
    export_library: Callable[[Sequence[str]], str],
) -> tuple[Refinement, FitResult]:
    """Refinement as one tracked job: a parent run with a child run per candidate, then the
    final library fitted and scored on the env's fixed test set (a child "fit" run); the
    parent carries the figure, the final error, and the library as YAML
    (``export_library(chosen families)``). The parent ends FAILED if anything raises."""
    from sdrl_bench.search.plots import refinement_figure

    sd = study_data(base_job, k_folds)
    parent = tracking.create_parent_run(uri, experiment, f"refine-{name}",
                                        {"sdrl.kind": "refine", "sdrl.study": name, "env": sd.spec.name})
    try:
        out = refine(sd, base_job.library_parts, families, optimizers, margin, seed,
                     on_stage=lambda i, c: log_refinement(uri, experiment, parent, name, i, c))
        final = out.final
        opt = dict(optimizers)[final.optimizer]
        parts = tuple(base_job.library_parts) + tuple(p for f in final.families for p in families[f])
        fit = fit_dynamics(dataclasses.replace(base_job, library_parts=parts, optimizer=opt))
        with tracking.tracked_run(uri, experiment, f"{name}-final", "fit", {"sdrl.study": name}, parent,
                                  source="sdrl-bench-search search=refine") as run:
            tracking.log_fit(run, fit, {"library": "+".join((library_label, *final.families)), "optimizer": final.optimizer})
        run = tracking.Run(uri, parent)
        tried = [c for stage in out.stages for c in stage]
        run.log_figure(refinement_figure(["+".join(("base", *c.families)) for c in tried], [c.error for c in tried],
                                         [c.accepted for c in tried], f"{name}: refinement (margin {out.margin:g})"),
                       "figures/refinement.png")
        run.log_text(export_library(final.families), f"best/library_{name}.yaml")
        run.log_metrics({"final_error": final.error, "final_n_terms": final.n_terms, "n_fits": out.n_fits,
                         "test/mse_norm/mean": fit.fidelity.metrics["mse_norm/mean"], "n_stages": len(out.stages)})
        run.set_tags({"final.library": "+".join(("base", *final.families)), "final.optimizer": final.optimizer})
    except BaseException:
        tracking.end_run(uri, parent, "FAILED")
        raise
    tracking.end_run(uri, parent, "FINISHED")
    return out, fit
