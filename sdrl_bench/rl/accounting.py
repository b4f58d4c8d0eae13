"""Every real step a run's result rests on, counted by purpose (the definitions: docs/accounting.md).

The counts come from the counting wrapper on every real env (``agents.StepCounter``), never from
arithmetic on budgets; this module only names their purposes and adds them up:

* ``model_data``: transitions collected for the model (a fit's collection, Dyna's collections);
* ``train``: a real arm's training steps;
* ``selection``: evaluations that stop training or choose (a learning curve with a stop rule,
  Dyna's screens and confirmations); a step that serves two purposes counts once, under its
  first (Dyna's screens that also join the model data count as selection; the reuse is
  reported as ``reused_as_model_data``);
* ``monitor``: learning-curve evaluations that stop nothing (reported apart);
* ``judge``: the final evaluation, on a seed stream nothing trained or stopped on (reported
  apart: it judges, it does not train);
* ``expert``: the training of a trained collector or of the expert behind a prior (once per
  expert);
* ``tuning``: a recipe's tuning on the real env, as its config declares it;
* ``priors``: the real steps behind the env's fitted priors (``EnvSpec.declared_priors``);
  replays from saved states (only a simulator gives them) and resets are counted apart.

Headlines: ``this_run`` = model_data + train + selection (the run's own data);
``all`` = this_run + priors + expert + tuning (every real step the result rests on).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from sdrl_bench.envs.task import Prior, expert_budget

OWN = ("model_data", "train", "selection")
PREFIXES = ("real_steps/", "real_resets/")
"""The prefixes of ``headline``'s metrics (a transfer run logs its fit's under ``fit/``)."""
APART = ("monitor", "judge")


def prior_steps(priors: Sequence[Prior], experts: Sequence[str | None] = ()) -> dict[str, float]:
    """The real steps behind ``priors`` and the experts (``<env>-<algo>-n<budget>``) a run used,
    each expert counted once: ``priors``, ``expert``, ``simulator``, and one metric per prior."""
    fitted = [p for p in priors if p.kind in ("fitted", "simulator")]
    names = {e for e in [*experts, *(p.expert for p in fitted)] if e}
    out: dict[str, float] = {f"prior/{p.name}": float(p.real_steps) for p in fitted}
    out["priors"] = float(sum(p.real_steps for p in fitted))
    out["expert"] = float(sum(expert_budget(e) for e in names))
    out["simulator"] = float(sum(p.simulator_steps for p in fitted))
    return out


def headline(counts: Mapping[str, float], priors: Sequence[Prior], experts: Sequence[str | None] = (),
             tuning: float = 0.0) -> dict[str, float]:
    """``real_steps/<purpose>`` metrics from per-purpose counts, and the two headlines."""
    m = {p: float(counts.get(p, 0)) for p in (*OWN, *APART)}
    m["reused_as_model_data"] = float(counts.get("reused_as_model_data", 0))
    m.update(prior_steps(priors, experts))
    m["tuning"] = float(tuning)
    m["this_run"] = sum(m[p] for p in OWN)
    m["all"] = m["this_run"] + m["priors"] + m["expert"] + m["tuning"]
    resets = {k: float(v) for k, v in counts.items() if k.startswith("resets/")}
    return {**{f"real_steps/{k}": v for k, v in m.items()}, **{f"real_{k}": v for k, v in resets.items()}}


def expert_of(policy: Any, env: str) -> str | None:
    """The ``<env>-<algo>-n<budget>`` name of a trained collector (None for a heuristic or random one)."""
    agent, budget = getattr(policy, "agent", None), getattr(policy, "budget", None)
    return f"{env}-{agent.name}-n{int(budget)}" if agent is not None and budget is not None else None
