"""The report's tables, built from plain run dicts (``tracking.find_runs``): pure functions.

Every table is a ``pandas.DataFrame`` with numeric values (NaN where the store holds nothing:
the renderer prints "not run") and a ``runs`` column listing the run ids behind the row, so
each number can link to its run. The paper's numbers (Table 1, the step counts, the NN
comparison) come from the env's ``reference/<env>.yaml`` and sit in their own columns beside ours.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from typing import Any
from collections.abc import Callable, Iterable, Mapping, Sequence
from functools import cache

import numpy as np
import pandas as pd
from scipy import stats

from sdrl_bench.envs import functional

Run = Mapping[str, Any]

ABLATION_LIBRARIES = ("polynomial", "poly_trig", "rational")
ARMS = ("surrogate", "real")


@cache
def references() -> dict[str, dict]:
    """What the report knows of each env beyond its runs: ``reference/<env>.yaml`` of the config
    tree (``envs.functional.references``): the paper's figures, the paper pack's choices, notes."""
    return functional.references()


def paper(env: str, key: str) -> dict:
    """The paper's figures of ``env`` (``fidelity``: {state: [MSE, corr]}, ``ablation``:
    {library: MSE}, ``total_steps``: {arm: steps}); empty where the paper has none."""
    return dict((references().get(env, {}).get("paper") or {}).get(key) or {})


def pack(env: str, key: str) -> str | None:
    """The paper pack's ``library``, ``agent`` or ``optimizer`` for ``env`` (preferred for the fidelity table)."""
    return (references().get(env, {}).get("pack") or {}).get(key)


def note(env: str, section: str) -> str | None:
    """What only ``env`` explains about a section's numbers (``notes.<section>``)."""
    return (references().get(env, {}).get("notes") or {}).get(section)


def paper_envs() -> list[str]:
    return [e for e, ref in references().items() if ref.get("paper")]


#: Open-loop rollout horizon of the fidelity tables (fits log ``rollout<k>_mse/<state>``).
HORIZON = 50


# ---------------------------------------------------------------------- run selection
def finished(runs: Iterable[Run], kind: str | None = None) -> list[Run]:
    """FINISHED runs (RUNNING, FAILED and KILLED runs are not results), of one ``sdrl.kind``."""
    return [r for r in runs if r.get("status") == "FINISHED" and (kind is None or r["tags"].get("sdrl.kind") == kind)]


def fit_records(runs: Iterable[Run]) -> list[dict[str, Any]]:
    """Every finished fit as one record: fit runs, and the fit inside each transfer run
    (its fit metrics). Keys: run_id, source ("fit"/"transfer"), env, library, surrogate,
    collector, optimizer, n_transitions, seed, test_set, metrics (unprefixed)."""
    out = []
    for r in finished(runs):
        kind, tags = r["tags"].get("sdrl.kind"), r["tags"]
        if tags.get("sdrl.study"):  # a study's refit of its best trial: the study's section reports it
            continue
        if kind == "fit":
            metrics = dict(r["metrics"])
        elif kind == "transfer":  # the fit under the names fit runs use, its accounting under ``fit/``
            metrics = {k: v for k, v in r["metrics"].items()  # (older runs: every fit metric under ``fit/``)
                       if not k.startswith(("surrogate/", "real/", "fit/")) and k != "policy_map_agreement"}
            metrics.update({k[4:]: v for k, v in r["metrics"].items() if k.startswith("fit/")})
            if "surrogate" not in tags.get("arms", "surrogate") or not any(k.startswith("mse/") for k in metrics):
                continue  # a real arm trained alone fits nothing
        else:
            continue
        out.append({"run_id": r["run_id"], "source": kind, "env": tags.get("env"), "library": tags.get("library"),
                    "surrogate": tags.get("surrogate", "sindy"), "collector": tags.get("collector"),
                    "optimizer": tags.get("optimizer"), "n_transitions": (r.get("params") or {}).get("n_transitions"),
                    "seed": tags.get("seed"), "test_set": tags.get("test_set", "?"), "agent": tags.get("agent"),
                    "fit_regime": tags.get("fit_regime"), "start_time": r.get("start_time") or 0, "metrics": metrics,
                    "fit_params": {k: v for k, v in (r.get("params") or {}).items() if k.startswith(FIT_PARAMS)}})
    return out


FIT_PARAMS = ("optimizer.", "library.", "collector.", "surrogate.", "dataset.", "n_transitions")
"""The params (as runs log them) that shape a fit: two fits that differ in any of them (a sweep
over thresholds) never share a row or a seed's place."""


def setup_of(fit: Mapping[str, Any]) -> str:
    """What a fit was made with besides its library: "optimizer, collector, real transitions"."""
    return ", ".join(str(fit.get(k) or "?") for k in ("optimizer", "collector", "n_transitions"))


def setup_key(fit: Mapping[str, Any]) -> tuple[str, str]:
    """A fit's whole setup: ``setup_of`` and every param that shapes the fit (``FIT_PARAMS``)."""
    return setup_of(fit), json.dumps(dict(fit.get("fit_params") or {}), sort_keys=True, default=str)


def setup(fits: Sequence[Mapping[str, Any]], others: Sequence[Sequence[Mapping[str, Any]]] = ()) -> str:
    """The setup a row's fits were made with: ``setup_of`` ("stlsq, heuristic, 75"), then the
    params in which it differs from ``others`` (the rows beside it of the same setup_of, e.g.
    "; optimizer.threshold=0.0003"); "mixed: ... | ..." should a row ever hold fits of several."""
    found = sorted({setup_of(f) for f in fits})
    if len(found) != 1:
        return "mixed: " + " | ".join(found) if found else ""
    mine = dict(fits[0].get("fit_params") or {})
    differ = _differing(mine, [dict(g[0].get("fit_params") or {}) for g in others if g and setup_of(g[0]) == found[0]
                               and setup_key(g[0]) != setup_key(fits[0])])
    shown = [f"{k}={mine.get(k, '-')}" for k in differ if len(str(mine.get(k, "-"))) <= 40]
    return found[0] + ("; " + ", ".join(shown) if shown else "; other params" if differ else "")


def _differing(mine: Mapping[str, Any], others: Sequence[Mapping[str, Any]]) -> list[str]:
    """The keys (sorted) in which ``mine`` differs from any of ``others``, one lacking a key
    counting as a difference: what a row's label names to tell it from the rows beside it."""
    return sorted(k for k in set(mine).union(*others) if any(o.get(k) != mine.get(k) for o in others))


def one_per_seed(fits: Sequence[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    """The newest fit of each seed (fits without a seed tag are all kept): two sweeps of the same
    pack never count a seed twice, so the "seeds" column and the CIs are over distinct seeds."""
    newest: dict[Any, Mapping[str, Any]] = {}
    for f in fits:
        key = f["seed"] if f.get("seed") is not None else id(f)
        if key not in newest or f.get("start_time", 0) >= newest[key].get("start_time", 0):
            newest[key] = f
    return list(newest.values())


def newest_per_seed(runs: Iterable[Run]) -> list[Run]:
    """The newest run of each seed (runs without a seed tag all kept), in seed order: a job run
    twice (a sweep rerun that could not adopt it) counts once."""
    newest: dict[Any, Run] = {}
    for r in runs:
        seed = r["tags"].get("seed")
        key = seed if seed is not None else r["run_id"]
        if key not in newest or (r.get("start_time") or 0) >= (newest[key].get("start_time") or 0):
            newest[key] = r
    return sorted(newest.values(), key=lambda r: (str(r["tags"].get("seed")), r["run_id"]))


def states_of(records: Sequence[Mapping[str, Any]], env: str) -> list[str]:
    """State names of an env: the paper's order, then any others the records' metrics name."""
    found = {k[4:] for r in records if r["env"] == env for k in r["metrics"] if k.startswith("mse/") and k != "mse/mean"}
    known = list(paper(env, "fidelity"))
    return [s for s in known if s in found or not found] + sorted(found - set(known))


def envs_of(records: Iterable[Mapping[str, Any]]) -> list[str]:
    """The paper's envs first, then any others present."""
    found = {r["env"] for r in records if r.get("env")}
    return paper_envs() + sorted(found - set(paper_envs()))


def main_fits(records: Sequence[Mapping[str, Any]], env: str, surrogate: str = "sindy") -> list[Mapping[str, Any]]:
    """The fits that stand for an env's surrogate: those made inside transfer runs (the
    paper's pipeline) if any, else fit runs; of the paper pack's agent and library when present
    (SINDy) and the pack's optimizer when it names one, and of the (library, test set, setup:
    ``setup_key``) with the most seeds: fits of another optimizer, collector, number of
    transitions or threshold (a sweep over them) never share a seed's place."""
    mine = [r for r in records if r["env"] == env and r["surrogate"] == surrogate]
    mine = [r for r in mine if r["source"] == "transfer"] or mine
    # the paper packs' runs when there are any: a fast recipe's runs fit the same data again
    mine = [r for r in mine if r["agent"] in (None, pack(env, "agent"))] or mine
    if surrogate == "sindy":
        mine = [r for r in mine if r["library"] == pack(env, "library")] or mine
        mine = [r for r in mine if r["optimizer"] in (None, pack(env, "optimizer"))] or mine
    if not mine:
        return []
    groups: dict[tuple, list[Mapping[str, Any]]] = {}
    for r in mine:
        groups.setdefault((str(r["library"]), str(r["test_set"]), *setup_key(r)), []).append(r)
    return _most_seeds(groups)[0][1]


def _mean(values: Iterable[float | None]) -> float:
    vals = [float(v) for v in values if v is not None and not math.isnan(float(v))]
    return float(np.mean(vals)) if vals else float("nan")


# ---------------------------------------------------------------------- tables 1-3
def _values(fits: Sequence[Mapping[str, Any]], key: str) -> list[float]:
    """One metric of each fit, NaN where a fit lacks it (``bootstrap_ci`` and ``_mean`` skip NaN)."""
    return [float(f["metrics"].get(key, math.nan)) for f in fits]


def floor_regime(fits: Sequence[Mapping[str, Any]], state: str) -> str | None:
    """The regime whose replay noise floor the fits were scored against for ``state``
    (``floor_ratio_<regime>/<state>``): the regime the fits' model was fitted on (their
    ``fit_regime``: the dynamics the model regresses) when logged, else "all", else the first
    found; None when the env has no floor."""
    found = sorted({k.split("/")[0][len("floor_ratio_"):] for f in fits for k in f["metrics"]
                    if k.startswith("floor_ratio_") and k.endswith(f"/{state}")})
    fitted = [f.get("fit_regime") for f in fits if f.get("fit_regime")]
    for regime in ([Counter(fitted).most_common(1)[0][0]] if fitted else []) + ["all"]:
        if regime in found:
            return regime
    return found[0] if found else None


def fidelity_table(runs: Iterable[Run]) -> pd.DataFrame:
    """Paper Table 1 top, per env and state over the env's main fits (``main_fits``, one per
    seed): one-step MSE (raw units; IQM with a 95% bootstrap CI over seeds, the mean below 5
    seeds), normalized MSE and correlation (same statistic), the one-step MSE as a multiple of
    the replay noise floor where the env has one (``floor_ratio``, its regime in
    ``floor_regime``), the MSE of the state after ``HORIZON`` open-loop steps (``rollout``, over
    the rollouts that did not diverge) and the fraction that diverged; beside the paper's."""
    records = fit_records(runs)
    rows = []
    for env in envs_of(records):
        fits = main_fits(records, env)
        for state in states_of(records, env):
            ref = paper(env, "fidelity").get(state, (math.nan, math.nan))
            one = bootstrap_ci(_values(fits, f"mse/{state}"))
            rollouts = _values(fits, f"rollout{HORIZON}_mse/{state}")  # NaN: every rollout of that seed diverged
            roll = bootstrap_ci(rollouts)
            regime = floor_regime(fits, state)
            floor = bootstrap_ci(_values(fits, f"floor_ratio_{regime}/{state}")) if regime else (math.nan,) * 3
            rows.append({
                "env": env, "state": state,
                "library": fits[0]["library"] if fits else None,
                "test_set": fits[0]["test_set"] if fits else None, "setup": setup(fits),
                "n_fits": len(fits), "statistic": one[3],
                "mse": one[0], "mse_lo": one[1], "mse_hi": one[2],
                "mse_norm": bootstrap_ci(_values(fits, f"mse_norm/{state}"))[0],
                "corr": bootstrap_ci(_values(fits, f"corr/{state}"))[0],
                "floor_ratio": floor[0], "floor_ratio_lo": floor[1], "floor_ratio_hi": floor[2], "floor_regime": regime,
                "rollout": roll[0], "rollout_lo": roll[1], "rollout_hi": roll[2],
                "rollout_n": int(np.isfinite(rollouts).sum()),
                "diverged": _mean(_values(fits, f"rollout{HORIZON}/diverged_fraction")),
                "paper_mse": ref[0], "paper_corr": ref[1],
                "runs": [f["run_id"] for f in fits],
            })
    return pd.DataFrame(rows, columns=["env", "state", "library", "test_set", "setup", "n_fits", "statistic", "mse", "mse_lo",
                                       "mse_hi", "mse_norm", "corr", "floor_ratio", "floor_ratio_lo", "floor_ratio_hi",
                                       "floor_regime", "rollout", "rollout_lo", "rollout_hi", "rollout_n", "diverged",
                                       "paper_mse", "paper_corr", "runs"])


def _state_mean(metrics: Mapping[str, float], prefix: str) -> float:
    """The mean over states of ``<prefix>/<state>`` (e.g. the 50-step rollout MSE of one fit)."""
    vals = [v for k, v in metrics.items() if k.startswith(prefix + "/") and not k.endswith(("/mean", "/max", "/n"))]
    return _mean(vals)


def ablation_table(runs: Iterable[Run]) -> pd.DataFrame:
    """Paper Table 1 bottom: per env, library and setup (``setup_key``: a sweep over optimizers,
    collectors, transitions or thresholds gives a row each, ``setup`` names it), over the SINDy
    fit runs (one per seed): the
    one-step MSE averaged over states (``mse/mean``, raw units; IQM with a 95% bootstrap CI
    over seeds, the mean below 5), the normalized one, the ``HORIZON``-step rollout MSE
    averaged over states, the fraction of rollouts that diverged and the active terms
    (``n_parameters``); beside the paper's."""
    records = [r for r in fit_records(runs) if r["surrogate"] == "sindy" and r["source"] == "fit"]
    rows = []
    for env in envs_of(records):
        # the paper's libraries ("not run" where missing) for the paper's envs; others: what was fitted
        paper_libs = list(ABLATION_LIBRARIES) if paper(env, "ablation") else []
        libraries = paper_libs + sorted({r["library"] for r in records if r["env"] == env and r["library"]} - set(paper_libs))
        for lib, fits, beside in ((name, group, groups) for name in libraries
                                  for groups in [_by_setup(records, env, name)] for group in groups):
            one = bootstrap_ci(_values(fits, "mse/mean"))
            rows.append({"env": env, "library": lib, "n_fits": len(fits), "setup": setup(fits, beside),
                         "test_set": fits[0]["test_set"] if fits else None, "statistic": one[3],
                         "mse_mean": one[0], "mse_mean_lo": one[1], "mse_mean_hi": one[2],
                         "mse_norm_mean": bootstrap_ci(_values(fits, "mse_norm/mean"))[0],
                         "rollout_mean": bootstrap_ci([_state_mean(f["metrics"], f"rollout{HORIZON}_mse") for f in fits])[0],
                         "diverged": _mean(_values(fits, f"rollout{HORIZON}/diverged_fraction")),
                         "n_terms": _mean(_values(fits, "n_parameters")),
                         "paper_mse": paper(env, "ablation").get(lib, math.nan),
                         "runs": [f["run_id"] for f in fits]})
    return pd.DataFrame(rows, columns=["env", "library", "n_fits", "setup", "test_set", "statistic", "mse_mean", "mse_mean_lo",
                                       "mse_mean_hi", "mse_norm_mean", "rollout_mean", "diverged", "n_terms", "paper_mse",
                                       "runs"])


def _by_setup(records: Sequence[Mapping[str, Any]], env: str, library: str) -> list[list[Mapping[str, Any]]]:
    """An env's fits of one library, one group per setup (``setup_key``; the most seeds first,
    then by key), each its newest fit per seed; [[]] when there are none (a "not run" row)."""
    groups: dict[tuple, list[Mapping[str, Any]]] = {}
    for r in records:
        if r["env"] == env and r["library"] == library:
            groups.setdefault(setup_key(r), []).append(r)
    return [group for _, group in _most_seeds(groups)] or [[]]


def _most_seeds(groups: Mapping[Any, Sequence[Mapping[str, Any]]],
                per_seed: Callable[[Sequence[Mapping[str, Any]]], list] = one_per_seed) -> list[tuple[Any, list]]:
    """[(key, the group's newest fit or run per seed)], the groups with the most seeds first
    (then by key): a setup fitted five times on two seeds does not outrank one fitted once on
    each of five. ``per_seed``: ``one_per_seed`` for fit records, ``newest_per_seed`` for runs."""
    kept = {k: per_seed(g) for k, g in groups.items()}
    return [(k, kept[k]) for k in sorted(kept, key=lambda k: (-len(kept[k]), k))]


def _ratio(a: float, b: float) -> float:
    return a / b if b and not (math.isnan(a) or math.isnan(b)) else math.nan


def nn_kinds(runs: Iterable[Run]) -> list[str]:
    """The NN kinds the fit runs of ``runs`` compare against SINDy: the MLP (``nn``, its row
    "not run" when absent), then any other kind with fit runs (``pe``), in name order."""
    records = [r for r in fit_records(runs) if r["source"] == "fit"]
    return ["nn", *sorted({r["surrogate"] for r in records} - {"sindy", "nn"})]


def sindy_vs_nn_table(runs: Iterable[Run]) -> pd.DataFrame:
    """SINDy vs each NN kind (``nn_kinds``: the MLP, and the probabilistic ensemble when it has
    fit runs) per env: per-state one-step and ``HORIZON``-step rollout MSE, fit wall and CPU
    seconds, parameters (SINDy: active terms) and the SINDy/NN ratios; each value the IQM over
    the kind's fit runs (one per seed; the mean below 5) with its 95% bootstrap CI
    (``<kind>_lo``, ``<kind>_hi``), ``sindy_over_<kind>``, ``n_<kind>``; ``runs_<kind>``
    name the runs, so each number links to its own runs."""
    runs = list(runs)
    records = [r for r in fit_records(runs) if r["source"] == "fit"]
    kinds = nn_kinds(runs)
    rows = []
    for env in envs_of(records):
        fits = {k: main_fits(records, env, k) for k in ("sindy", *kinds)}
        ids = [f["run_id"] for group in fits.values() for f in group]
        states = states_of(records, env)
        quantities = ([f"mse/{s}" for s in states] + [f"rollout{HORIZON}_mse/{s}" for s in states]
                      + [f"rollout{HORIZON}/diverged_fraction", "fit_wall_seconds", "fit_cpu_seconds", "n_parameters"])
        for q in quantities:
            row: dict[str, Any] = {"env": env, "quantity": q, "runs": ids}
            for k, group in fits.items():
                point, lo, hi, _ = bootstrap_ci(_values(group, q))
                row.update({k: point, f"{k}_lo": lo, f"{k}_hi": hi, f"n_{k}": len(group),
                            f"runs_{k}": [f["run_id"] for f in group]})
            row.update({f"sindy_over_{k}": _ratio(row["sindy"], row[k]) for k in kinds})
            rows.append(row)
    columns = ["env", "quantity", *(c for k in ("sindy", *kinds) for c in (k, f"{k}_lo", f"{k}_hi")),
               *(f"sindy_over_{k}" for k in kinds), *(f"n_{k}" for k in ("sindy", *kinds)), "runs",
               *(f"runs_{k}" for k in ("sindy", *kinds))]
    return pd.DataFrame(rows, columns=columns)


# ---------------------------------------------------------------------- RL transfer
def iqm(x: np.ndarray, axis: int = -1) -> np.ndarray:
    """Interquartile mean: the mean of the middle 50% (25% trimmed from each end)."""
    return stats.trim_mean(x, 0.25, axis=axis)


def bootstrap_ci(values: Sequence[float], confidence: float = 0.95, n_resamples: int = 2000,
                 seed: int = 0) -> tuple[float, float, float, str]:
    """(point, low, high, statistic name) over seeds: the IQM when there are >= 5 values, else
    the mean; a percentile bootstrap interval (``scipy.stats.bootstrap``, fixed seed). Fewer
    than two values: no interval (NaN bounds)."""
    # sorted: the interval depends on the values, not on the order the runs were read in
    x = np.sort(np.asarray([v for v in values if v is not None and not math.isnan(v)], dtype=float))
    if len(x) == 0:
        return math.nan, math.nan, math.nan, "mean"
    name, fn = ("IQM", iqm) if len(x) >= 5 else ("mean", np.mean)
    point = float(fn(x))
    if len(x) < 2:
        return point, math.nan, math.nan, name
    if np.all(x == x[0]):
        return point, point, point, name
    res = stats.bootstrap((x,), fn, confidence_level=confidence, n_resamples=n_resamples, method="percentile",
                          vectorized=True, axis=-1, rng=np.random.default_rng(seed))
    return point, float(res.confidence_interval.low), float(res.confidence_interval.high), name


TRANSFER_METRICS = ("real_transitions_model", "real_transitions_train", "surrogate_steps", "total_steps",
                    "success_rate", "train_wall_seconds", "solved_real_steps", "solved_wall_seconds")


KINDS = ("sindy", "nn")
"""The surrogate kinds every RL table shows (a row "not run" when absent); other kinds (``pe``,
a user's) get rows where they have runs."""


def surrogate_kinds(runs: Iterable[Run]) -> list[str]:
    """``KINDS`` then every other surrogate kind the runs carry, in name order."""
    seen = {r["tags"].get("surrogate", "sindy") for r in runs}
    return [*KINDS, *sorted(seen - set(KINDS))]


def transfer_table(runs: Iterable[Run], seed: int = 0) -> pd.DataFrame:
    """RL transfer per env, surrogate kind, agent and arm (seeds pooled): real transitions used
    (model + training), surrogate steps, total steps as the paper counts them, final real
    return (IQM or mean) with a 95% bootstrap CI over seeds, success rate, training wall
    seconds, real steps (and wall seconds) to first reach the solved threshold (mean over the
    seeds that reached it; ``n_solved`` says how many did)."""
    done = finished(runs, "transfer")
    rows = []
    for env in envs_of({"env": r["tags"].get("env")} for r in done):
        # the paper pack's agent first, then the others (a fast recipe)
        agents = sorted({r["tags"].get("agent", "?") for r in done if r["tags"].get("env") == env},
                        key=lambda a: (a != pack(env, "agent"), a)) or ["-"]
        kinds = surrogate_kinds(r for r in done if r["tags"].get("env") == env)
        for kind, agent in ((k, a) for k in kinds for a in agents):
            # one row group per agent: a store with the zoo recipe and a fast one keeps them apart
            group = newest_per_seed(r for r in done if r["tags"].get("env") == env
                                    and r["tags"].get("surrogate", "sindy") == kind and r["tags"].get("agent", "?") == agent)
            for arm in ARMS:
                have = [r for r in group if f"{arm}/final_return_mean" in r["metrics"]]
                returns = [r["metrics"][f"{arm}/final_return_mean"] for r in have]
                point, lo, hi, stat = bootstrap_ci(returns, seed=seed)
                row: dict[str, Any] = {"env": env, "surrogate": kind, "arm": arm, "agent": agent, "n_seeds": len(have),
                                       "return": point, "ci_low": lo, "ci_high": hi, "statistic": stat}
                for m in TRANSFER_METRICS:
                    row[m] = _mean(r["metrics"].get(f"{arm}/{m}") for r in have)
                row["real_transitions"] = row["real_transitions_model"] + row["real_transitions_train"]
                row["real_steps_this_run"] = _mean(r["metrics"].get(f"{arm}/real_steps/this_run") for r in have)
                row["real_steps_all"] = _mean(r["metrics"].get(f"{arm}/real_steps/all") for r in have)
                row["n_solved"] = sum(f"{arm}/solved_real_steps" in r["metrics"] for r in have)
                # the paper's step counts belong to its recipe: beside the paper pack's agent only
                row["paper_total_steps"] = (paper(env, "total_steps").get(arm, math.nan)
                                            if agent in (pack(env, "agent"), "?", "-") else math.nan)
                row["runs"] = [r["run_id"] for r in have]
                rows.append(row)
    cols = ["env", "surrogate", "arm", "agent", "n_seeds", "real_transitions", "real_steps_this_run", "real_steps_all",
            "surrogate_steps", "total_steps", "paper_total_steps",
            "return", "ci_low", "ci_high", "statistic", "success_rate", "train_wall_seconds", "solved_real_steps",
            "solved_wall_seconds", "n_solved", "real_transitions_model", "real_transitions_train", "runs"]
    return pd.DataFrame(rows, columns=cols)


def _median_cost(costs: Sequence[float]) -> float:
    """The median of per-seed costs where an unsolved seed costs infinity (NaN: no seeds)."""
    return float(np.median(costs)) if len(costs) else math.nan


def _real_arms(dyna: Sequence[Run], real: Sequence[Run]) -> list[Run]:
    """The real arms the Dyna runs compare with (same env, agent, budgets and seed), each once:
    the run a Dyna run was plotted beside (tag ``dyna.real_arm_run``), else the one with its
    ``dyna.real_arm_key`` (a real arm run after it), else, for runs older than those tags, the
    real arms of the same seed; with no Dyna run tagged at all, every real arm given."""
    by_id = {r["run_id"]: r for r in real}
    by_key = {r["tags"]["real_arm_key"]: r for r in real if r["tags"].get("real_arm_key")}
    tagged = [r for r in dyna if r["tags"].get("dyna.real_arm_run") or r["tags"].get("dyna.real_arm_key")]
    if not tagged:
        return list(real)
    out: dict[str, Run] = {}
    for r in dyna:
        tags = r["tags"]
        hit = by_id.get(tags.get("dyna.real_arm_run", "")) or by_key.get(tags.get("dyna.real_arm_key", ""))
        found = [hit] if hit is not None else [a for a in real if a["tags"].get("seed") == tags.get("seed")]
        out.update({a["run_id"]: a for a in found})
    return newest_per_seed(out.values())


def _by_loop_settings(runs: Sequence[Run]) -> list[tuple[list[Run], str]]:
    """Dyna runs split by their loop's settings (the ``rl.dyna.*`` params): [(newest run per seed,
    "" or "; <the settings in which this group differs>")], the most seeds first; [([], "")] for
    none. Two loops of other settings (rounds, screens, data from evaluations) are two rows."""
    if not runs:
        return [([], "")]
    groups: dict[str, list[Run]] = {}
    for r in runs:
        own = {k: v for k, v in (r.get("params") or {}).items() if k.startswith("rl.dyna.")}
        groups.setdefault(json.dumps(own, sort_keys=True), []).append(r)
    ordered = _most_seeds(groups, newest_per_seed)
    if len(ordered) == 1:
        return [(ordered[0][1], "")]
    settings = {k: json.loads(k) for k in groups}
    differ = sorted({p for k in groups for p in _differing(settings[k], [settings[o] for o in groups if o != k])})
    return [(group, "; " + ", ".join(f"{p.removeprefix('rl.dyna.')}={settings[k].get(p, '-')}" for p in differ))
            for k, group in ordered]


def dyna_table(runs: Iterable[Run], seed: int = 0) -> pd.DataFrame:
    """Dyna runs (``task=dyna``) per env, surrogate kind and agent, and beside them the real
    arm of the same agent (finished transfer runs that trained it, not those that reused it): seeds solved; the median real transitions to solve (an
    unsolved seed counts as infinitely many); per phase, the mean real steps (Dyna: collect,
    screens, confirmations; real arm: training to the first solved evaluation, and the
    evaluations); this run's real steps as IQM with a CI, an unsolved seed counted as what it
    spent (censored at its budget); the last 20-episode return and the Dyna audit, each as IQM (or mean) with a 95%
    bootstrap CI over seeds. Real arms of other agents on the same env that stopped at the
    threshold (``rl.stop_when_solved``) get rows too, and every row the ratio of its median real
    transitions to solve to the best real arm's on its env."""
    runs = list(runs)
    dyna = finished(runs, "dyna")
    # the real arm: every transfer run that trained one of the same agent (alone, as studies/dyna_real_steps.py
    # runs it, or beside a surrogate arm); a reused real arm is the same run's and is not counted twice
    real = [r for r in finished(runs, "transfer") if "real/final_return_mean" in r["metrics"]
            and not r["tags"].get("real_arm_reused_from")]
    rows = []
    for env in envs_of({"env": r["tags"].get("env")} for r in dyna):
        for agent in sorted({r["tags"].get("agent", "?") for r in dyna if r["tags"].get("env") == env}):
            # the env's own Dyna pack first, then other packs (a variant: other priors, other budgets)
            packs = sorted({r["tags"].get("sdrl.experiment") for r in dyna if r["tags"].get("env") == env
                            and r["tags"].get("agent") == agent}, key=lambda p: (p not in (None, f"dyna_{env}"), str(p)))
            kinds = surrogate_kinds(r for r in dyna if r["tags"].get("env") == env)
            for pack, kind in ((p, k) for p in packs for k in kinds):
                mine = [r for r in dyna if r["tags"].get("env") == env and r["tags"].get("agent") == agent
                        and r["tags"].get("surrogate", "sindy") == kind and r["tags"].get("sdrl.experiment") == pack]
                if not mine and (pack not in (None, f"dyna_{env}") or kind not in KINDS):
                    continue
                for group, variant in _by_loop_settings(mine):
                    label = f"Dyna, {kind}" + ("" if pack in (None, f"dyna_{env}") else f", {pack}") + variant
                    m = [r["metrics"] for r in group]
                    # solved as the independent judge says (the audit), where runs record it; else the loop's own stop
                    judged = [x.get("judged_solved", x.get("solved")) == 1.0 for x in m]
                    costs = [x["real_transitions_total"] if ok else math.inf for x, ok in zip(m, judged, strict=True)]
                    costs_all = [x.get("real_steps/all", math.nan) if ok else math.inf for x, ok in zip(m, judged, strict=True)]
                    final = bootstrap_ci([x.get("final_return_mean", math.nan) for x in m], seed=seed)
                    audit = bootstrap_ci([x.get("audit_return_mean", math.nan) for x in m], seed=seed)
                    # censored: an unsolved seed counts what it spent (its budget, or a round past it)
                    spent = bootstrap_ci([x.get("real_transitions_total", math.nan) for x in m], seed=seed)
                    rows.append({"env": env, "method": label, "agent": agent, "n_seeds": len(group),
                                 "n_solved": sum(judged), "n_stopped": sum(x.get("solved") == 1.0 for x in m),
                                 "median_to_solve": _median_cost(costs), "median_all": _median_cost(costs_all), "censored": spent,
                                 "model_data": _mean(x.get("real_transitions_model") for x in m),
                                 "phase_a": _mean(x.get("real_steps_collect") for x in m),
                                 "phase_b": _mean(x.get("real_steps_evaluate") for x in m),
                                 "phase_c": _mean(x.get("real_steps_final") for x in m),
                                 "surrogate_steps": _mean(x.get("surrogate_steps") for x in m),
                                 "wall_seconds": _mean(x.get("wall_seconds") for x in m),
                                 "final": final, "audit": audit, "runs": [r["run_id"] for r in group]})
            group = _real_arms([r for r in dyna if r["tags"].get("env") == env and r["tags"].get("agent") == agent],
                               [r for r in real if r["tags"].get("env") == env and r["tags"].get("agent") == agent])
            rows.append(_real_arm_row(env, agent, group, seed))
        # real-env learners of other agents on the same env, stopped at the threshold (a stronger real arm
        # than the loop's own recipe may be another algorithm or recipe)
        # (one row per agent and pack: two recipes of one algorithm are two arms)
        shown = {r["agent"] for r in rows if r["env"] == env and r["method"] == "real arm"}
        others = [r for r in real if r["tags"].get("env") == env and r["tags"].get("agent") not in shown
                  and r.get("params", {}).get("rl.stop_when_solved") == "True"]
        # a stop confirmed on fresh episodes (rl.confirm_episodes) is another procedure: rows of its own
        confirm = lambda r: r.get("params", {}).get("rl.confirm_episodes", "0")  # noqa: E731
        arms = sorted({(r["tags"].get("agent", "?"), r["tags"].get("sdrl.experiment") or "", confirm(r)) for r in others})
        for agent, pack, n in arms:
            group = newest_per_seed(r for r in others if r["tags"].get("agent") == agent
                                    and (r["tags"].get("sdrl.experiment") or "") == pack and confirm(r) == n)
            label = ", ".join(["real arm", *([pack] if pack else []), *([f"confirmed on {n}"] if n != "0" else [])])
            rows.append(_real_arm_row(env, agent, group, seed, label))
    for row in rows:  # each method's median real steps to solve over the best real arm's on its env
        best = [r["median_to_solve"] for r in rows if r["env"] == row["env"] and r["method"].startswith("real arm")
                and math.isfinite(r["median_to_solve"])]
        row["ratio_to_best_real"] = row["median_to_solve"] / min(best) if best else math.nan
    return pd.DataFrame(rows, columns=["env", "method", "agent", "n_seeds", "n_solved", "n_stopped", "median_to_solve",
                                       "median_all", "censored", "model_data",
                                       "phase_a", "phase_b", "phase_c", "surrogate_steps", "wall_seconds", "final",
                                       "audit", "ratio_to_best_real", "runs"])


def _real_arm_row(env: str, agent: str, group: Sequence[Run], seed: int, method: str = "real arm") -> dict[str, Any]:
    """One real arm's row of ``dyna_table``: its cost to solve is its training steps up to the
    first evaluation at the threshold plus every evaluation it ran."""
    m = [r["metrics"] for r in group]
    costs = [x["real/solved_real_steps"] + x.get("real/eval_steps", 0.0) if "real/solved_real_steps" in x
             else math.inf for x in m]
    costs_all = [c + x.get("real/real_steps/tuning", 0.0) for c, x in zip(costs, m, strict=True)]
    spent = bootstrap_ci([c if math.isfinite(c) else x.get("real/real_steps/this_run", math.nan)
                          for c, x in zip(costs, m, strict=True)], seed=seed)
    return {"env": env, "method": method, "agent": agent, "n_seeds": len(group),
            "n_solved": sum("real/solved_real_steps" in x for x in m),
            "n_stopped": sum("real/solved_real_steps" in x for x in m),
            "median_to_solve": _median_cost(costs), "median_all": _median_cost(costs_all), "censored": spent,
            "model_data": 0.0, "phase_a": _mean(x.get("real/solved_real_steps") for x in m),
            "phase_b": _mean(x.get("real/eval_steps") for x in m), "phase_c": math.nan,
            "surrogate_steps": 0.0, "wall_seconds": _mean(x.get("real/train_wall_seconds") for x in m),
            "final": bootstrap_ci([x.get("real/final_return_mean", math.nan) for x in m], seed=seed),
            "audit": (math.nan, math.nan, math.nan, "mean"), "runs": [r["run_id"] for r in group]}


RUN_TAGS = ("sdrl.kind", "mlflow.runName", "mlflow.parentRunId", "env", "agent", "surrogate", "library", "optimizer",
            "collector", "seed", "arms", "git_commit")
"""The tags ``runs_frame`` keeps (the rest are MLflow's bookkeeping or descriptions)."""


def runs_frame(runs: Iterable[Run]) -> pd.DataFrame:
    """Every run as one row: id, experiment, status, start time, the tags of ``RUN_TAGS``
    (``tag.<name>``), every param (``param.<name>``) and every metric's last value
    (``metric.<name>``): the runs a report read, so each of its numbers can be traced to a run id."""
    rows = []
    for r in runs:
        row: dict[str, Any] = {"run_id": r["run_id"], "experiment_id": r.get("experiment_id"), "status": r.get("status"),
                               "start_time": r.get("start_time")}
        row.update({f"tag.{k}": r["tags"][k] for k in RUN_TAGS if k in r["tags"]})
        row.update({f"param.{k}": v for k, v in sorted(r.get("params", {}).items())})
        row.update({f"metric.{k}": v for k, v in sorted(r.get("metrics", {}).items())})
        rows.append(row)
    df = pd.DataFrame(rows)
    if df.empty:
        return df
    head = [c for c in ("run_id", "experiment_id", "status", "start_time") if c in df.columns]
    rest = sorted(c for c in df.columns if c not in head)
    order = [c for c in rest if c.startswith("tag.")] + [c for c in rest if c.startswith("param.")] + \
        [c for c in rest if c.startswith("metric.")]
    return df[head + order]


def curve_band(curves: Sequence[pd.DataFrame]) -> pd.DataFrame:
    """Learning curves of several seeds (columns train_steps, return_mean) on their common
    steps: mean, min and max across seeds per step, and how many seeds have the step."""
    frames = [c[["train_steps", "return_mean"]].dropna() for c in curves if len(c)]
    if not frames:
        return pd.DataFrame(columns=["train_steps", "mean", "low", "high", "n"])
    joined = pd.concat(frames).groupby("train_steps")["return_mean"]
    out = pd.DataFrame({"mean": joined.mean(), "low": joined.min(), "high": joined.max(), "n": joined.count()})
    return out.reset_index()


def missing_metrics(runs: Iterable[Run]) -> list[str]:
    """Finished runs whose kind's key metrics are absent, as messages for the report."""
    needed = {"fit": ("mse/mean", "fit_wall_seconds"), "transfer": tuple(f"{a}/final_return_mean" for a in ARMS)}
    out = []
    for r in finished(runs):
        keys = needed.get(r["tags"].get("sdrl.kind", ""), ())
        if r["tags"].get("arms"):  # a transfer run that ran some arms only: ask for those
            keys = tuple(f"{a}/final_return_mean" for a in r["tags"]["arms"].split(","))
        lacking = [k for k in keys if k not in r["metrics"]]
        if lacking:
            out.append(f"run {r['run_id']} ({r['tags'].get('mlflow.runName', '?')}) lacks {', '.join(lacking)}")
    return out
