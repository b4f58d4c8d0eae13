"""SINDy vs NN: compute and accuracy ratios from finished fit runs (pure functions, no MLflow).

A fit run's metrics (``tracking.fit_metrics``) carry ``fit_wall_seconds``, ``fit_cpu_seconds``,
``n_parameters`` (SINDy: its active terms; NN: its weights and biases) and the one-step MSE per
state (``mse/<state>``) on the env's fixed test set. ``surrogate_ratios`` turns two such dicts
into SINDy / NN ratios; ``pair_fit_runs`` finds the pairs to compare among many runs: a SINDy
and an NN fit of the same env on the same dataset (hash) scored on the same test set (hash).
"""

from __future__ import annotations

import math
from typing import Any
from collections.abc import Mapping, Sequence

PREFIX = "sindy_over_nn"
COST_KEYS = ("fit_wall_seconds", "fit_cpu_seconds", "n_parameters")


def _ratio(a: float, b: float) -> float:
    a, b = float(a), float(b)
    if b == 0 or math.isnan(a) or math.isnan(b):
        return float("nan")
    return a / b


def surrogate_ratios(sindy: Mapping[str, float], nn: Mapping[str, float]) -> dict[str, float]:
    """SINDy / NN ratios of two fit runs' metrics, keyed ``sindy_over_nn/<metric>``.

    Cost: ``fit_wall_seconds``, ``fit_cpu_seconds``, ``n_parameters`` (below 1: SINDy is
    cheaper). Accuracy: every ``mse/<state>``, ``mse_norm/mean`` and ``rollout<k>_mse/<state>``
    both runs have (below 1: SINDy is more accurate). Also ``nn_over_sindy/fit_wall_seconds``,
    the "x times cheaper" figure. A zero denominator gives NaN. Missing cost keys raise KeyError.
    """
    for which, m in (("sindy", sindy), ("nn", nn)):
        missing = [k for k in COST_KEYS if k not in m]
        if missing:
            raise KeyError(f"{which} run metrics lack {missing}")
    out = {f"{PREFIX}/{k}": _ratio(sindy[k], nn[k]) for k in COST_KEYS}
    accuracy = sorted(k for k in set(sindy) & set(nn)
                      if k.startswith("mse/") or k == "mse_norm/mean" or
                      (k.startswith("rollout") and "_mse/" in k))
    out.update({f"{PREFIX}/{k}": _ratio(sindy[k], nn[k]) for k in accuracy})
    out["nn_over_sindy/fit_wall_seconds"] = _ratio(nn["fit_wall_seconds"], sindy["fit_wall_seconds"])
    return out


def pair_fit_runs(runs: Sequence[Mapping[str, Any]]) -> list[tuple[Mapping[str, Any], Mapping[str, Any]]]:
    """(SINDy run, NN run) pairs of finished fit runs on identical data and test set.

    ``runs`` are plain dicts with ``tags`` and ``metrics`` mappings (``tracking.find_runs``).
    Runs match on tags ``env``, ``dataset_sha256``, ``test_set_sha256`` and ``seed``; when a key
    has several finished runs of a kind, the newest (latest ``start_time``) is used.
    """
    by_key: dict[tuple, dict[str, Mapping[str, Any]]] = {}
    for run in sorted(runs, key=lambda r: r.get("start_time") or 0, reverse=True):
        tags = run["tags"]
        if tags.get("sdrl.kind") != "fit" or run.get("status", "FINISHED") != "FINISHED":
            continue
        kind = tags.get("surrogate")
        if kind not in ("sindy", "nn"):
            continue
        key = tuple(tags.get(k) for k in ("env", "dataset_sha256", "test_set_sha256", "seed"))
        by_key.setdefault(key, {}).setdefault(kind, run)
    return [(pair["sindy"], pair["nn"]) for _, pair in sorted(by_key.items(), key=lambda kv: str(kv[0]))
            if "sindy" in pair and "nn" in pair]


def comparison_rows(runs: Sequence[Mapping[str, Any]], states: Sequence[str] | None = None) -> list[dict[str, Any]]:
    """One row per (SINDy, NN) pair: env, seed, dataset hash, per-state one-step MSE of both,
    both fits' wall seconds and parameters, and the ratios (``surrogate_ratios``)."""
    rows = []
    for s, n in pair_fit_runs(runs):
        sm, nm = s["metrics"], n["metrics"]
        names = states or sorted(k[4:] for k in set(sm) & set(nm) if k.startswith("mse/") and k != "mse/mean")
        row: dict[str, Any] = {"env": s["tags"].get("env"), "seed": s["tags"].get("seed"),
                               "dataset_sha256": s["tags"].get("dataset_sha256"),
                               "sindy_run": s.get("run_id"), "nn_run": n.get("run_id")}
        for name in names:
            row[f"sindy mse/{name}"], row[f"nn mse/{name}"] = sm.get(f"mse/{name}"), nm.get(f"mse/{name}")
        for k in ("fit_wall_seconds", "n_parameters"):
            row[f"sindy {k}"], row[f"nn {k}"] = sm.get(k), nm.get(k)
        row.update(surrogate_ratios(sm, nm))
        rows.append(row)
    return rows
