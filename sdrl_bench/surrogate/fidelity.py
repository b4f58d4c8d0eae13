"""How well a surrogate's task matches the real env, measured on held-out real transitions.

The surrogate's reward, termination and exogenous variables come from the env's task (its rules:
some are approximations, e.g. contact). This module measures them on real transitions, as plain
numbers for the tracking layer to log.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sdrl_bench.data import Transitions
from sdrl_bench.envs import EnvSpec
from sdrl_bench.surrogate.model_env import ModelEnv


def _precision_recall(pred: np.ndarray, true: np.ndarray) -> tuple[float, float]:
    tp = float(np.sum(pred & true))
    return (tp / float(pred.sum()) if pred.any() else float("nan"), tp / float(true.sum()) if true.any() else float("nan"))


def surrogate_fidelity(model: Any, spec: EnvSpec | str, test: Transitions) -> dict[str, float]:
    """How well the surrogate's task approximations match held-out real transitions.

    ``surrogate/...`` applies the spec's reward, termination and exogenous rules to the *real*
    next states (the approximations alone; exogenous variables derived, not copied);
    ``surrogate/one_step/...`` runs the full surrogate step from the real state and action (the
    model's prediction included). Reward MSE, termination precision / recall (nan when there is
    nothing to divide by; per cause too, for specs with ``termination_causes``), accuracy per
    exogenous variable, and counts.
    """
    sur = ModelEnv(model, spec, noise=False, penalty=False)  # the deterministic step and the task's own reward
    spec, task = sur.spec, sur.task
    s, a, real = test.states, test.actions, test.next_states
    true_term = np.asarray(test.terminated, dtype=bool)
    ns = real.copy()
    if spec.exogenous_names:
        ns[:, spec.exogenous_index] = task.exogenous(s, a, ns)
    one, r_one, term_one, div = sur.step(s, a)
    rules_reward, rules_term = task.reward_terminated(s, a, ns)
    regimes = spec.regimes(test.episode, s, test.rewards, real)
    m: dict[str, float] = {"surrogate/n_transitions": float(len(test)), "surrogate/n_terminated": float(true_term.sum())}
    for prefix, nxt, rew, term in (
        ("surrogate/", ns, rules_reward, rules_term),
        ("surrogate/one_step/", one, r_one, term_one),
    ):
        err2 = (np.asarray(rew) - test.rewards) ** 2
        m[prefix + "reward_mse"] = float(np.mean(err2))
        running = ~true_term & ~np.asarray(term, bool)  # shaping and costs, without terminal rewards
        m[prefix + "reward_mse_running"] = float(np.mean(err2[running])) if running.any() else float("nan")
        for regime, mask in regimes.items():  # per regime of the spec
            sel = running & np.asarray(mask, bool)
            m[f"{prefix}reward_mse_running_{regime}"] = float(np.mean(err2[sel])) if sel.any() else float("nan")
        m[prefix + "terminated_precision"], m[prefix + "terminated_recall"] = _precision_recall(np.asarray(term, bool), true_term)
        m[prefix + "n_terminated_pred"] = float(np.sum(term))
        for name, i in zip(spec.exogenous_names, spec.exogenous_index, strict=True):
            m[f"{prefix}{name}_accuracy"] = float(np.mean(nxt[:, i] == real[:, i]))
        if task.termination_causes is None or task.observed_causes is None:
            continue
        observed = task.observed_causes(test.rewards, true_term)
        for cause, pred in task.termination_causes(s, a, nxt).items():  # where the task tells causes apart
            p, r = _precision_recall(np.asarray(pred, bool) & np.asarray(term, bool), observed[cause])
            m[f"{prefix}{cause}_precision"], m[f"{prefix}{cause}_recall"] = p, r
    if spec.exogenous_names:
        m["surrogate/reward_mse_real_exogenous"] = float(np.mean((task.reward_terminated(s, a, real)[0] - test.rewards) ** 2))
    m["surrogate/one_step/diverged_fraction"] = float(div.mean())
    m.update({f"surrogate/{k}": float(v) for k, v in spec.task_fidelity(test).items()})
    return m
