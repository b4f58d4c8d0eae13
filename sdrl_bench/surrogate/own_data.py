"""A surrogate's constants learned from the run's own transitions (``env.spec.own_data: true``).

Every fit (a transfer run's, each Dyna round's) hands its data to ``learn_from_run``, which
returns the spec the surrogate is built on:

* the env's own constants its data identify (``EnvSpec.learned_constants``; LunarLander: the
  contact rules, ``envs/lunar_lander/own_data.py``);
* the pessimism's ``scale``: per regressed state, the standard deviation of the model's
  residuals on the rows it was fitted on (in place of a replay noise floor, which only a
  resettable simulator gives), and its ``free`` band: the 99th percentile of the ensemble's
  disagreement on the same rows in those units (in place of a band set on other data);
* the declared priors, less those all of whose constants were learned (their real steps no
  longer count: ``rl.accounting``).

A constant the data do not identify keeps its prior value and its prior keeps counting.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from sdrl_bench.envs.base import EnvSpec
from sdrl_bench.surrogate.model_env import member_spread

FREE_QUANTILE = 99.0


def uncertainty_from_data(spec: EnvSpec, model: Any, data: Any, rows: np.ndarray) -> tuple[dict, dict[str, float]]:
    """(the ``uncertainty`` node with scale and free band from the fit's own rows, learned values)."""
    node = dict(spec.uncertainty or {})
    if not node or len(rows) < 2:
        return node, {}
    x, u = spec.model_inputs(data.states[rows], data.actions[rows])
    resid = data.next_states[rows][:, spec.target_index] - np.asarray(model.predict(x, u))
    scale = np.sqrt(np.mean(resid**2, axis=0))
    scale = np.where(scale > 0, scale, np.finfo(float).tiny)
    node["scale"] = scale.tolist()
    learned = {f"uncertainty.scale/{n}": float(v) for n, v in zip(spec.target_names, scale, strict=True)}
    learned["uncertainty.scale"] = float(len(scale))
    members = member_spread(model)
    if members is not None:
        spread = members(np.vstack([x.T, u.T])).std(axis=0) / scale[:, None]
        node["free"] = float(np.percentile(spread.max(axis=0), FREE_QUANTILE))
        learned["uncertainty.free"] = node["free"]
    return node, learned


def learn_from_run(spec: EnvSpec, data: Any, model: Any, rows: np.ndarray | None = None) -> tuple[EnvSpec, dict[str, float]]:
    """(the spec a surrogate of this fit is built on, {learned key: value}); ``rows``: the rows
    (mask or indices) the model was fitted on (None: all). Without ``spec.own_data``: (spec, {})."""
    if not spec.own_data:
        return spec, {}
    rows = np.arange(len(data)) if rows is None else (np.flatnonzero(rows) if np.asarray(rows).dtype == bool else np.asarray(rows))
    changes, learned = spec.learned_constants(data)
    node, unc = uncertainty_from_data(spec, model, data, rows)
    learned = {**learned, **unc}
    if node:
        changes["uncertainty"] = node
    keys = {k.split("/")[0] for k in learned}
    kept = tuple(node_ for node_, prior in zip(spec.priors, spec.declared_priors, strict=True)
                 if not set(prior.sets) <= keys)
    return replace(spec, **changes, priors=kept), learned
