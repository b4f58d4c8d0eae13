"""Fidelity of a dynamics model on held-out real transitions, stepped as the surrogate steps it.

A step is: model inputs from (state, action) -> model prediction -> the spec's bounds. One-step
errors compare that with the real next state; k-step open-loop rollouts feed predictions back
for k steps with the real actions (and, for exogenous variables such as LunarLander's leg
contacts, the real recorded values: the rollout measures the regressed dynamics alone).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sdrl_bench.data import Transitions
from sdrl_bench.envs.base import EnvSpec, wrap_angle
from sdrl_bench.metrics import mse, pearson, r2, spearman
from sdrl_bench.models.base import DynamicsModel


def step(model: DynamicsModel, spec: EnvSpec, states: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """Next regressed states for full states (N, n_state) and raw actions, bounds applied."""
    x, u = spec.model_inputs(states, actions)
    with np.errstate(all="ignore"):
        return spec.apply_bounds(states, model.predict(x, u))


@dataclass
class FidelityReport:
    """Metrics keyed ``<name>/<state>`` plus the arrays behind them, for figures."""

    metrics: dict[str, float] = field(default_factory=dict)
    true_next: np.ndarray | None = None
    pred_next: np.ndarray | None = None
    rollout: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    pred_std: np.ndarray | None = None
    """Per test transition and regressed state: the model's own uncertainty (an ensemble's member
    spread), for models that have one."""


def evaluate(
    model: DynamicsModel,
    spec: EnvSpec,
    test: Transitions,
    norm_std: dict[str, float] | None = None,
    horizons: tuple[int, ...] = (10, 50),
    stride: int = 5,
    test_name: str | None = None,
) -> FidelityReport:
    """One-step MSE (raw units, and in units of ``norm_std``), correlation, R^2 per regressed
    state; one-step MSE on the smooth transitions alone (``mse_smooth``, see ``smooth_mask``);
    per regime of the spec (``mse_<regime>``, e.g. LunarLander's flight and contact) and, where
    the spec knows the replay noise floor of test set ``test_name``, the ratio to it
    (``floor_ratio_<regime>``: 1 is the best any deterministic model can do); and k-step
    open-loop rollout MSE with the fraction of diverged rollouts."""
    names = spec.target_names
    true = test.next_states[:, spec.target_index]
    pred = step(model, spec, test.states, test.actions)
    finite = np.all(np.isfinite(pred), axis=1)
    rep = FidelityReport(true_next=true, pred_next=pred)
    m = rep.metrics
    m["one_step/nonfinite_fraction"] = float(1 - finite.mean())
    err, cor, det = mse(true[finite], pred[finite]), pearson(true[finite], pred[finite]), r2(true[finite], pred[finite])
    for i, n in enumerate(names):
        m[f"mse/{n}"] = float(err[i])
        if norm_std is not None:
            m[f"mse_norm/{n}"] = float(err[i] / norm_std[n] ** 2)
        m[f"corr/{n}"] = float(cor[i])
        m[f"r2/{n}"] = float(det[i])
    m["mse/mean"] = float(np.mean(err))
    smooth = smooth_mask(spec, test) & finite
    m["one_step/smooth_fraction"] = float(smooth.mean())
    if smooth.any():
        err_s = mse(true[smooth], pred[smooth])
        for i, n in enumerate(names):
            m[f"mse_smooth/{n}"] = float(err_s[i])
    floors = spec.noise_floor(test_name) if test_name else None
    for regime, mask in spec.regimes(test.episode, test.states, test.rewards, test.next_states).items():
        mask = np.asarray(mask, bool) & finite
        m[f"{regime}_fraction"] = float(mask.mean())
        if not mask.any():
            continue
        err_r = mse(true[mask], pred[mask])
        for i, n in enumerate(names):
            m[f"mse_{regime}/{n}"] = float(err_r[i])
            if floors and regime in floors:
                m[f"floor_ratio_{regime}/{n}"] = float(err_r[i] / floors[regime][i])
        if floors and regime in floors:
            m[f"floor_ratio_{regime}/max"] = float(max(m[f"floor_ratio_{regime}/{n}"] for n in names))
    if norm_std is not None:
        m["mse_norm/mean"] = float(np.mean([m[f"mse_norm/{n}"] for n in names]))
    if _has_uncertainty(model):
        rep.pred_std = std = np.asarray(model.predict_std(*spec.model_inputs(test.states, test.actions)), dtype=float)
        m.update(uncertainty_metrics(names, np.abs(pred - true)[finite], std[finite]))
    for k in horizons:
        final_true, final_pred, diverged = rollouts(model, spec, test, k, stride)
        m[f"rollout{k}/n"] = float(len(diverged))
        m[f"rollout{k}/diverged_fraction"] = float(diverged.mean()) if len(diverged) else float("nan")
        ok = ~diverged
        e = mse(final_true[ok], final_pred[ok]) if ok.any() else np.full(len(names), np.nan)
        for i, n in enumerate(names):
            m[f"rollout{k}_mse/{n}"] = float(e[i])
        rep.rollout[k] = (final_true, final_pred)
    return rep


def _has_uncertainty(model) -> bool:
    return callable(getattr(model, "predict_std", None)) and getattr(model, "ensemble_size", 1) > 1


def uncertainty_metrics(names, abs_err: np.ndarray, std: np.ndarray) -> dict[str, float]:
    """Is the model's uncertainty informative? Per regressed state: the mean predicted std, the
    Spearman rank correlation of std with the absolute one-step error (does the spread rank the
    transitions by error?), and the share of errors within 2 std (0.95 for calibrated Gaussian
    errors; ensembles of few members are usually overconfident)."""
    m: dict[str, float] = {}
    rank = spearman(std, abs_err)
    for i, n in enumerate(names):
        m[f"uncertainty/mean_std/{n}"] = float(np.mean(std[:, i]))
        m[f"uncertainty/spearman/{n}"] = float(rank[i])
        m[f"uncertainty/within_2std/{n}"] = float(np.mean(abs_err[:, i] <= 2 * std[:, i]))
    return m


def smooth_mask(spec: EnvSpec, test: Transitions) -> np.ndarray:
    """Transitions with no non-smooth event: the next state is not on a known bound, the
    episode does not end there, and every exogenous variable (LunarLander's leg contacts) is
    zero before and after. Errors on the rest are contact and boundary physics."""
    mask = ~spec.at_bound(test.next_states) & ~test.terminated
    exo = spec.exogenous_index
    if len(exo):
        mask &= ~np.any(test.states[:, exo] != 0, axis=1) & ~np.any(test.next_states[:, exo] != 0, axis=1)
    return mask


def rollouts(
    model: DynamicsModel, spec: EnvSpec, test: Transitions, k: int, stride: int = 5
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Open-loop k-step rollouts from every ``stride``-th step of each test episode that has k
    more transitions. Returns the true and predicted regressed state after k steps, and a
    diverged flag (non-finite, or beyond the spec's divergence limit at any step)."""
    starts = []
    for ep in np.unique(test.episode):
        idx = np.flatnonzero(test.episode == ep)
        starts += [idx[j] for j in range(0, len(idx) - k + 1, stride)]
    starts = np.asarray(starts, dtype=int)
    tgt = spec.target_index
    if len(starts) == 0:
        empty = np.zeros((0, len(tgt)))
        return empty, empty, np.zeros(0, dtype=bool)
    state = test.states[starts].copy()
    diverged = np.zeros(len(starts), dtype=bool)
    limit = spec.divergence_limit()
    for j in range(k):
        nxt = step(model, spec, state, test.actions[starts + j])
        bad = ~np.all(np.isfinite(nxt), axis=1) | np.any(np.abs(nxt) > limit, axis=1)
        diverged |= bad
        nxt[diverged] = 0.0  # frozen; excluded from the error
        state = test.next_states[starts + j].copy()  # exogenous variables: the real values
        state[:, tgt] = nxt
    final_true = test.next_states[starts + k - 1][:, tgt]
    return final_true, align_angles(spec, final_true, state[:, tgt]), diverged


def align_angles(spec: EnvSpec, true: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """Predicted angles (``spec.angles``) moved by whole turns to within pi of the true ones: an
    angle's error is its wrapped difference."""
    cols = [i for i, n in enumerate(spec.target_names) if n in spec.angles]
    if cols:
        pred = pred.copy()
        with np.errstate(all="ignore"):
            pred[:, cols] = true[:, cols] + wrap_angle(pred[:, cols] - true[:, cols])
    return pred


DATA_METRICS = ("one_step", "rollout10", "rollout50", "rollout_episode")
"""The fidelity study's candidates a search can score on validation folds (``search.objective``)."""

POLICY_METRICS = ("onpolicy_one_step", "reference_gap")
"""The fidelity study's candidates a search can select on that need a policy (real steps per trial,
or per study): scored by ``rl.fidelity_study.PolicyProbe``."""

ROLLOUT_CAP = 1.0e4
"""Normalized squared error given to a diverged or non-finite prediction (about 100 standard
deviations off): the fidelity study's and the search's open-loop errors stay finite and rank a
diverging model below every model that does not diverge."""


def normalized_error(true: np.ndarray, pred: np.ndarray, std: np.ndarray) -> np.ndarray:
    """Per row: mean over states of ((pred - true) / std)^2; a non-finite row is ``ROLLOUT_CAP``."""
    with np.errstate(all="ignore"):
        e = np.mean(((pred - true) / std) ** 2, axis=1)
    return np.where(np.isfinite(e), np.minimum(e, ROLLOUT_CAP), ROLLOUT_CAP)


def rollout_error(model: DynamicsModel, spec: EnvSpec, test: Transitions, k: int, std: np.ndarray) -> float:
    """k-step open-loop error on the test set: mean over rollouts of the normalized error after k
    steps, a diverged rollout counting as ``ROLLOUT_CAP``."""
    true, pred, diverged = rollouts(model, spec, test, k)
    if not len(true):
        return float("nan")
    e = normalized_error(true, pred, std)
    return float(np.mean(np.where(diverged, ROLLOUT_CAP, e)))


def episode_error(model: DynamicsModel, spec: EnvSpec, test: Transitions, std: np.ndarray) -> float:
    """Open loop over each whole test episode from its first state with its recorded actions
    (exogenous variables from the record), all episodes stepped together: the normalized error
    averaged over time, then over episodes; after a divergence every step counts as the cap."""
    tgt, limit = spec.target_index, spec.divergence_limit()
    eps = [np.flatnonzero(test.episode == e) for e in np.unique(test.episode)]
    state = test.states[[ix[0] for ix in eps]].copy()
    sums, dead = np.zeros(len(eps)), np.zeros(len(eps), dtype=bool)
    for t in range(max(len(ix) for ix in eps)):
        live = np.flatnonzero([t < len(ix) for ix in eps])
        rows = np.array([eps[i][t] for i in live])
        nxt = step(model, spec, state[live], test.actions[rows])
        bad = ~np.all(np.isfinite(nxt), axis=1) | np.any(np.abs(nxt) > limit, axis=1)
        dead[live] |= bad
        err = normalized_error(test.next_states[rows][:, tgt], align_angles(spec, test.next_states[rows][:, tgt], nxt), std)
        sums[live] += np.where(dead[live], ROLLOUT_CAP, err)
        new = test.next_states[rows].copy()
        new[:, tgt] = np.where(dead[live][:, None], test.next_states[rows][:, tgt], nxt)
        state[live] = new
    return float(np.mean(sums / np.array([len(ix) for ix in eps])))


def open_loop_episode(
    model: DynamicsModel, spec: EnvSpec, test: Transitions, episode: int, max_steps: int = 300
) -> tuple[np.ndarray, np.ndarray]:
    """(true, predicted) regressed-state trajectories of one test episode, open loop from its
    first state with its recorded actions (exogenous variables from the record)."""
    idx = np.flatnonzero(test.episode == episode)[:max_steps]
    state = test.states[idx[:1]].copy()
    pred = []
    for i in idx:
        nxt = step(model, spec, state, test.actions[i : i + 1])
        state = test.next_states[i : i + 1].copy()
        state[:, spec.target_index] = nxt
        pred.append(nxt[0])
    true = test.next_states[idx][:, spec.target_index]
    return true, align_angles(spec, true, np.asarray(pred))


def replay_noise_floor(spec: EnvSpec, test: Transitions, episode_seeds: dict[int, int], rows_per_episode: int = 400,
                       k: int = 2, seed: int = 0) -> dict[str, list[float] | float]:
    """The replay noise floor of one-step prediction per regime: for a sample of rows, reset the
    real env with the episode's seed, replay its recorded actions to the row, give the env a
    fresh random generator and step the row's action again, ``k`` times. For envs whose only
    randomness after ``reset`` is ``env.np_random`` (LunarLander's engine dispersion), this
    redraws that step's noise alone: same state, terrain and contacts. With the recorded s',
    that is k + 1 draws of s' | (s, a); their unbiased variance, averaged over the rows of a
    regime, is the MSE of the best deterministic predictor (the floor). Returns
    {regime: per regressed state variance} (plus ``"all"``), ``n_<regime>`` row counts and
    ``replay_max_abs_diff`` (the replay with the original generator must reproduce the record: 0).
    Cost: O(episode length) env steps per draw."""
    rng = np.random.default_rng(seed)
    tgt = spec.target_index
    env = spec.make_env().unwrapped
    rows, draws, worst = [], [], 0.0
    try:
        for ep in np.unique(test.episode):
            idx = np.flatnonzero(test.episode == ep)
            env.reset(seed=int(episode_seeds[int(ep)]))
            for r in idx:  # the replay check: bit-exact
                worst = max(worst, float(np.max(np.abs(np.asarray(env.step(_raw(spec, test.actions[r]))[0]) - test.next_states[r]))))
            pick = np.sort(rng.choice(idx, size=min(len(idx), rows_per_episode), replace=False))
            for r in pick:
                out = []
                for _ in range(k):
                    env.reset(seed=int(episode_seeds[int(ep)]))
                    for q in idx[: np.searchsorted(idx, r)]:
                        env.step(_raw(spec, test.actions[q]))
                    env.np_random = np.random.default_rng(int(rng.integers(2**63)))
                    out.append(np.asarray(env.step(_raw(spec, test.actions[r]))[0], dtype=float)[tgt])
                rows.append(r)
                draws.append(out)
    finally:
        env.close()
    rows_a = np.asarray(rows)
    allv = np.concatenate([test.next_states[rows_a][:, tgt][:, None, :], np.asarray(draws)], axis=1)
    var = allv.var(axis=1, ddof=1)
    masks = {"all": np.ones(len(test), bool), **spec.regimes(test.episode, test.states, test.rewards, test.next_states)}
    res: dict[str, list[float] | float] = {"replay_max_abs_diff": worst}
    for name, mask in masks.items():
        sel = np.asarray(mask, bool)[rows_a]
        res[name] = var[sel].mean(axis=0).tolist() if sel.any() else [float("nan")] * len(tgt)
        res[f"n_{name}"] = float(sel.sum())
    return res


def _raw(spec: EnvSpec, action: np.ndarray):
    return int(action[0]) if spec.n_discrete_actions else np.asarray(action, dtype=np.float32)
