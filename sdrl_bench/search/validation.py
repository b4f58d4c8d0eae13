"""Held-out validation on the *collected* data: k folds over episodes, or over time blocks.

The search and the library refinement choose hyperparameters with these errors; the env's fixed
test set (``data.held_out_test_set``) stays untouched for the final score.

The error of a fold is the one-step MSE of each regressed state on the fold's rows (stepped as
the surrogate steps: bounds applied), divided by that state's variance in the training rows,
then averaged over states: the same normalization as ``fidelity``'s ``mse_norm/mean``, so no
state dominates because of its units.
"""

from __future__ import annotations

from dataclasses import dataclass
from collections.abc import Callable, Iterator

import numpy as np

from sdrl_bench import ConfigError
from sdrl_bench.data import Transitions
from sdrl_bench.envs.base import EnvSpec
from sdrl_bench.fidelity import step
from sdrl_bench.models.base import DynamicsModel


@dataclass(frozen=True)
class Fold:
    """Row indices of one train / validation split of a dataset."""

    train: np.ndarray
    valid: np.ndarray


def make_folds(data: Transitions, k: int) -> list[Fold]:
    """``k`` folds: whole episodes when the data has at least ``k`` episodes (episodes dealt
    round-robin in id order), else ``k`` contiguous time blocks of the row order. Deterministic.
    """
    if k < 2:
        raise ConfigError(f"search.k_folds must be >= 2, got {k}")
    n = len(data)
    if n < 2 * k:
        raise ConfigError(f"search.k_folds={k}: too few transitions ({n}) for {k} folds")
    episodes = np.unique(data.episode)
    if len(episodes) >= k:
        group = {int(e): i % k for i, e in enumerate(episodes)}
        label = np.array([group[int(e)] for e in data.episode])
    else:
        label = np.minimum((np.arange(n) * k) // n, k - 1)
    idx = np.arange(n)
    return [Fold(train=idx[label != f], valid=idx[label == f]) for f in range(k)]


def fit_rows(spec: EnvSpec, data: Transitions, exclude_bound: bool) -> np.ndarray:
    """Boolean mask of the rows a fit uses (rows whose next state lies on a bound dropped)."""
    if not exclude_bound:
        return np.ones(len(data), dtype=bool)
    return ~spec.at_bound(data.next_states)


def fit_model(
    make_model: Callable[[], DynamicsModel], spec: EnvSpec, data: Transitions, exclude_bound: bool = True
) -> DynamicsModel:
    """Fit a fresh model on ``data`` (bound rows excluded as in ``pipeline.fit_dynamics``)."""
    keep = fit_rows(spec, data, exclude_bound)
    if keep.sum() == 0:
        raise ConfigError("dataset: every transition lies on a state bound; nothing to fit")
    x, u = spec.model_inputs(data.states[keep], data.actions[keep])
    x_next = data.next_states[keep][:, spec.target_index]
    return make_model().fit(x, u, x_next, state_names=spec.target_names, control_names=spec.control_names,
                            bounds=spec.target_bounds())


def normalized_errors(
    model: DynamicsModel, spec: EnvSpec, valid: Transitions, reference: Transitions
) -> np.ndarray:
    """Per regressed state: one-step MSE on ``valid`` / variance of that state in ``reference``.
    Non-finite predictions give ``inf``."""
    true = valid.next_states[:, spec.target_index]
    pred = step(model, spec, valid.states, valid.actions)
    stats = reference.normalization(spec)
    var = np.array([stats[n]["std"] ** 2 for n in spec.target_names])
    if not np.all(np.isfinite(pred)):
        return np.full(len(var), np.inf)
    with np.errstate(over="ignore"):
        return np.mean((pred - true) ** 2, axis=0) / var


def cross_validate(
    make_model: Callable[[], DynamicsModel],
    spec: EnvSpec,
    data: Transitions,
    folds: list[Fold],
    exclude_bound: bool = True,
    objective: str = "one_step",
) -> Iterator[float]:
    """Yield each fold's error, fold by fold, so a caller can report running means to a pruner
    and stop early. ``one_step``: the mean normalized one-step MSE over states; ``rollout<k>`` and
    ``rollout_episode``: the fidelity study's open-loop errors on the fold's episodes
    (``rl.fidelity_study.rollout_error`` / ``episode_error``), normalized by the training rows' std."""
    from sdrl_bench.fidelity import episode_error, rollout_error

    for _, model, train, valid in _fold_fits(make_model, spec, data, folds, exclude_bound):
        if objective == "one_step":
            yield float(np.mean(normalized_errors(model, spec, valid, train)))
            continue
        stats = train.normalization(spec)
        std = np.array([stats[n]["std"] for n in spec.target_names])
        if objective == "rollout_episode":
            yield episode_error(model, spec, valid, std)
        else:
            yield rollout_error(model, spec, valid, int(objective[len("rollout"):]), std)


def fold_residuals(
    make_model: Callable[[], DynamicsModel],
    spec: EnvSpec,
    data: Transitions,
    folds: list[Fold],
    exclude_bound: bool = True,
) -> tuple[list[float], np.ndarray, np.ndarray]:
    """Fold errors, and the held-out residuals (true - predicted next state, each state divided
    by its training std) stacked over folds with their row indices: what the model misses."""
    errors, rows, residuals = [], [], []
    for fold, model, train, valid in _fold_fits(make_model, spec, data, folds, exclude_bound):
        errors.append(float(np.mean(normalized_errors(model, spec, valid, train))))
        stats = train.normalization(spec)
        std = np.array([stats[n]["std"] for n in spec.target_names])
        pred = step(model, spec, valid.states, valid.actions)
        residuals.append((valid.next_states[:, spec.target_index] - pred) / std)
        rows.append(fold.valid)
    return errors, np.concatenate(rows), np.concatenate(residuals)


def _fold_fits(make_model, spec, data, folds, exclude_bound):
    for fold in folds:
        train, valid = data.subset(fold.train), data.subset(fold.valid)
        yield fold, fit_model(make_model, spec, train, exclude_bound), train, valid


def resolution_floor(spec: EnvSpec, data: Transitions) -> float:
    """The normalized one-step error that rounding the true next states to the observation
    dtype alone produces (mean over regressed states of ``mean(ulp^2 / 12) / variance``).

    Errors below it are float noise: an exact law and the same law with a negligible spurious
    term both sit there, so the objective adds it before comparing models.
    """
    true = data.next_states[:, spec.target_index].astype(spec.obs_dtype)
    ulp = np.spacing(np.abs(true)).astype(float)
    stats = data.normalization(spec)
    var = np.array([stats[n]["std"] ** 2 for n in spec.target_names])
    return float(np.mean(np.mean(ulp**2 / 12.0, axis=0) / var))


def aggregate(fold_errors: list[float] | np.ndarray, floor: float) -> float:
    """The held-out error of a configuration: geometric mean over folds of (fold error +
    ``floor``). A geometric mean lets one hard fold (an extrapolation block) count without
    drowning the others; the floor keeps float-noise differences out of the ranking."""
    e = np.asarray(fold_errors, dtype=float) + floor
    if not np.all(np.isfinite(e)):
        return float("inf")
    with np.errstate(divide="ignore"):
        return float(np.exp(np.mean(np.log(e))))
