"""Tracking store -> reports/<name>/report.md and a self-contained report.html, our numbers
beside the paper's, also logged to MLflow as the artifacts of a "report" run.

Reads the store only through ``tracking``; the tables come from ``report.tables`` (pure
functions over run dicts); the figures are the runs' own artifacts plus learning curves
pooled across seeds. What the store does not hold prints as "not run". Bad input (an empty
store, an unknown experiment or parent run, a selection without runs) is a ConfigError: one
line, and nothing written or logged. Inside sweeps each job's config has a key
(``sdrl.config_key``): the newest FINISHED run per key is used, so a config is never counted twice.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from collections.abc import Mapping, Sequence

import pandas as pd

from sdrl_bench import ConfigError, tracking
from sdrl_bench.report import tables as rt
from sdrl_bench.report.figures import figure_blocks
from sdrl_bench.report.folder import clear_earlier_build, record_build, report_files
from sdrl_bench.report.fidelity_study import fidelity_blocks
from sdrl_bench.report.render import MISSING, NOT_RUN, Block, Cell, Heading, Para, Table, fmt, render_html, render_markdown


@dataclass
class ReportInput:
    """What the report reads: the store, a selection, and how to link runs."""

    uri: str
    experiment: str = "sdrl-bench"
    parent_run: str | None = None
    tags: dict[str, str] = field(default_factory=dict)
    ui_url: str | None = None


@dataclass
class ReportResult:
    folder: Path
    n_runs: int
    problems: list[str]
    report_run_id: str | None
    seconds: float


def select_runs(inp: ReportInput) -> tuple[list[dict[str, Any]], list[str]]:
    """The runs the report covers, and the problems met (unknown experiment or parent run,
    empty selection). Never raises for bad input: problems are returned as messages."""
    local = tracking.sqlite_path(inp.uri)
    if local is not None and not local.is_file():  # report, don't create
        return [], [f"no tracking store at {local}"]
    names = tracking.list_experiments(inp.uri)
    if inp.experiment not in names:
        known = ", ".join(repr(n) for n in names) or "none: the store is empty"
        return [], [f"no experiment {inp.experiment!r} in {tracking.display_uri(inp.uri)} (experiments: {known})"]
    filters = [f"tags.`{k}` = '{v}'" for k, v in inp.tags.items()]
    runs = tracking.find_runs(inp.uri, inp.experiment, " and ".join(filters), missing_ok=False, key="--experiment")
    runs = [r for r in runs if r["tags"].get("sdrl.kind") != "report"]
    if inp.parent_run:
        if not tracking.run_exists(inp.uri, inp.parent_run):
            return [], [f"no run {inp.parent_run!r} (--parent-run) in {tracking.display_uri(inp.uri)}"]
        keep = {inp.parent_run}
        for _ in range(3):  # children, grandchildren (a study's trials under a sweep), ...
            keep |= {r["run_id"] for r in runs if r["tags"].get(tracking.PARENT_TAG) in keep}
        runs = [r for r in runs if r["run_id"] in keep]
    if not runs:
        return [], [f"no runs match (experiment {inp.experiment!r}, parent run {inp.parent_run or 'any'}, tags {inp.tags or 'any'})"]
    return runs, []


def latest_per_config(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One FINISHED run per job config (tag ``sdrl.config_key``, set inside sweeps): the newest.
    A sweep run twice with ``resume=false`` is then not counted twice; runs without the tag
    (single runs) are all kept."""
    newest: dict[tuple[str, str], dict[str, Any]] = {}
    for r in runs:
        key = r["tags"].get("sdrl.config_key")
        if key and r["status"] == "FINISHED":
            k = (r["tags"].get("sdrl.kind", "?"), key)
            if k not in newest or (r["start_time"] or 0) >= (newest[k]["start_time"] or 0):
                newest[k] = r
    keep = {id(r) for r in newest.values()}
    return [r for r in runs if not (r["tags"].get("sdrl.config_key") and r["status"] == "FINISHED") or id(r) in keep]


class Linker:
    """Run ids as links into the MLflow UI (when a server URL is given) and short labels: a
    number backed by one run opens that run's page; a number over several runs (a mean over
    seeds) opens the compare view of exactly those runs."""

    def __init__(self, runs: Sequence[Mapping[str, Any]], ui_url: str | None):
        self.exp = {r["run_id"]: r.get("experiment_id", "0") for r in runs}
        self.ui = ui_url.rstrip("/") if ui_url else None

    def url(self, run_id: str) -> str | None:
        return tracking.run_url(self.ui, self.exp.get(run_id, "0"), run_id) if self.ui else None

    def runs_url(self, run_ids: Sequence[str]) -> str | None:
        if not self.ui or not run_ids:
            return None
        if len(run_ids) == 1:
            return self.url(run_ids[0])
        return tracking.compare_url(self.ui, run_ids, [self.exp.get(r, "0") for r in run_ids])

    def cell(self, text: str, run_ids: Sequence[str]) -> Cell:
        """A number linked to the runs it is computed from; "not run", "missing" and "-" carry no link."""
        if text in (NOT_RUN, MISSING, "-") or not run_ids:
            return Cell(text)
        return Cell(text, self.runs_url(run_ids))

    def ids(self, run_ids: Sequence[str], limit: int = 5) -> Cell:
        if not run_ids:
            return Cell(NOT_RUN)
        shown = ", ".join(r[:8] for r in run_ids[:limit]) + (f" +{len(run_ids) - limit}" if len(run_ids) > limit else "")
        return Cell(shown, self.runs_url(run_ids), runs=True)


def _df_table(df: pd.DataFrame, spec: Sequence[tuple[str, ...]], link: Linker, caption: str) -> Table:
    """Rows of ``df`` as a Table: spec is (column, header, format[, runs column]); a number
    links to the runs it comes from (the row's ``runs``, or the named runs column: SINDy cells
    to SINDy runs, NN cells to NN runs); NaN prints "not run" when those runs are none, else
    "missing"."""
    rows = []
    for _, r in df.iterrows():
        ids = list(r["runs"])
        cells = []
        for col, _, kind, *runs_col in spec:
            v = r[col]
            cell_ids = list(r[runs_col[0]]) if runs_col else ids
            kind, _, count_col = kind.partition("|")  # "g|n_nn": "not run" when n_nn is 0; "g|-": "-" (none exists)
            empty = NOT_RUN if not cell_ids or (count_col not in ("", "-") and not r[count_col]) else MISSING
            if count_col == "-" and cell_ids:  # e.g. no noise floor, or a ratio of two zeros
                empty = "-"
            if kind == "text":
                cells.append(Cell("-" if v is None or (isinstance(v, float) and math.isnan(v)) else str(v)))
            elif kind.startswith("paper"):
                cells.append(Cell(fmt(v, kind[6:] or "g", empty="-")))
            elif kind.endswith("ci"):  # "eci", "gci": the value with its CI from <col>_lo, <col>_hi
                text = _with_ci(v, r.get(f"{col}_lo"), r.get(f"{col}_hi"), kind[:-2], empty)
                n = r.get(f"{col}_n")  # over fewer seeds than the row's (e.g. every rollout of a seed diverged)
                if n is not None and "n_fits" in r and n < r["n_fits"] and text not in (NOT_RUN, MISSING, "-"):
                    text += f" ({n} of {r['n_fits']} seeds)"
                cells.append(link.cell(text, cell_ids))
            else:
                cells.append(link.cell(fmt(v, kind, empty), cell_ids))
        cells.append(link.ids(ids))
        rows.append(cells)
    return Table([s[1] for s in spec] + ["runs"], rows, caption)


def _with_ci(value: Any, lo: Any, hi: Any, kind: str, empty: str) -> str:
    """``value [lo, hi]`` in the number format ``kind``; the value alone when there is no interval."""
    text = fmt(value, kind, empty)
    if text in (NOT_RUN, MISSING, "-") or lo is None or hi is None or math.isnan(lo) or math.isnan(hi) or lo == hi == value:
        return text  # no interval, or every seed gave the same value
    return f"{text} [{fmt(lo, kind)}, {fmt(hi, kind)}]"


def _ci_text(ci: tuple[float, float, float, str], empty: str = NOT_RUN, number: str = "g4") -> str:
    """(point, low, high, statistic) as "point [low, high] (statistic)"; ``empty`` without a point;
    ``number``: "g4" (4 significant digits) or "int" (whole numbers with thousands separators)."""
    point, lo, hi, stat = ci
    if math.isnan(point):
        return empty
    f = (lambda v: f"{v:,.0f}") if number == "int" else (lambda v: f"{v:.4g}")
    if math.isnan(lo):
        return f"{f(point)} ({stat}, 1 seed: no CI)"
    return f"{f(point)} [{f(lo)}, {f(hi)}] ({stat})"


FIDELITY_DIFFERENCES = (
    "Differences explained: the paper gives one MSE and correlation per state and states neither its units "
    "nor its test set. Ours are in the observation's raw units, on a fixed held-out set of fresh real episodes "
    "(`<env>-heldout-v1`, reset seeds the fits never see), one fit per seed. Where an env is stochastic, the "
    "noise-floor column divides the MSE of the floor regime's rows by the replay noise floor of those rows (the "
    "best any deterministic model can do: 1). The 50-step columns are not in the paper: open-loop rollouts "
    "from every 5th step of each test episode with the real actions fed in, the MSE of the state after 50 "
    "steps over the rollouts that stayed finite, and the fraction that diverged. They, and the open-loop panels "
    "of the predicted-vs-true figures, run the regressed law alone, without the rules of the surrogate's task.")
ABLATION_DIFFERENCES = (
    "Differences explained: the paper gives one MSE per library and env without saying how the states are "
    "combined or in what units; ours is the mean over states of the raw-unit MSE (so it is dominated by the "
    "state with the largest spread). Its 'trigonometric' library is our `poly_trig` (polynomial plus sin and "
    "cos terms); the 50-step columns are ours.")
NN_DIFFERENCES = (
    "Differences explained: ours is an MLP on normalized (state, action) predicting the state change (one "
    "hidden tanh layer of 64, AdamW, early stopping; chosen by an Optuna search on data and test sets disjoint "
    "from these), trained on the same transitions as the SINDy fit of the same seed. Compute is the fit's wall "
    "and CPU seconds on this machine (one thread), collection and scoring excluded. Parameters: SINDy's nonzero "
    "coefficients against the NN's weights and biases.")
TRANSFER_DIFFERENCES = (
    "Differences explained: the paper reports total steps and says the surrogate-trained agents perform "
    "comparably, without a final return, seeds or intervals. Ours, per seed: the agent trained only in the "
    "surrogate, then the real env's return over 20 fresh deterministic episodes; beside it the same algorithm "
    "trained in the real env on the same seeds (with the NN surrogate the finished real arm of the same seed is "
    "reused, not retrained, so its rows repeat the SINDy group's). An arm run with `rl.stop_when_solved=true` "
    "stops at its first real evaluation at the threshold, so its total steps are what solving took; without it "
    "the budgets are fixed. `ppo_fast` rows: the fast recipe (many vectorized envs, short rollouts), not in the "
    "paper. Real transitions count the model's data and real training steps, not the evaluation episodes "
    "(reported in the runs as `eval_steps`). Wall seconds are training only.")


def _present(df: pd.DataFrame, *counts: str) -> list[str]:
    """The envs of a table that have runs (a paper env the store lacks has "not run" rows only)."""
    if not len(df):
        return []
    have = sum((df[c].fillna(0) > 0) for c in counts)
    return list(dict.fromkeys(df.loc[have > 0, "env"]))


def _with_notes(text: str, envs: Sequence[str], section: str) -> Para:
    """A section's paragraph: its generic text, then what each env present explains (``reference/<env>.yaml``)."""
    notes = [n.strip() for n in (rt.note(e, section) for e in dict.fromkeys(envs)) if n]
    return Para(" ".join([text, *notes]))


def _nn_models(runs: Sequence[Mapping[str, Any]], kinds: Sequence[str]) -> str:
    """The other NN kinds' networks, read from their fit runs' params."""
    parts = []
    for kind in kinds:
        fits = [r for r in runs if r["tags"].get("sdrl.kind") == "fit" and r["tags"].get("surrogate") == kind]
        if not fits:
            continue
        p = fits[0]["params"]
        size = "x".join([str(p.get("surrogate.model.width", "?"))] * int(p.get("surrogate.model.depth", 1) or 1))
        members = p.get("surrogate.model.ensemble_size", "?")
        elites = f", the best {p['surrogate.model.n_elites']} kept" if "surrogate.model.n_elites" in p else ""
        parts.append(f"`surrogate={kind}`: {members} members of {size} {p.get('surrogate.model.activation', '?')} "
                     f"units{elites}, on the same transitions, its prediction the members' mean")
    return (" The other NN kinds (their fit runs' params): " + "; ".join(parts) + ".") if parts else ""


def _collectors(runs: Sequence[Mapping[str, Any]]) -> str:
    """The collectors of each env's fits in the fidelity table, read from the runs' tags."""
    records = rt.fit_records(runs)
    parts = []
    for env in rt.envs_of(records):
        used = sorted({str(f["collector"]) for f in rt.main_fits(records, env) if f.get("collector")})
        if used:
            parts.append(f"{env}: {', '.join(used)}")
    return f" The fits' data came from these collectors (their runs' tags): {'; '.join(parts)}." if parts else ""


def _int(text: Any) -> int | None:
    try:
        return int(float(text))
    except (TypeError, ValueError):
        return None


def _recipe(group: Sequence[Mapping[str, Any]]) -> str:
    """What one (env, agent) group of transfer runs did, read from their params: budgets, the stop
    rule, the evaluations, the model's data, and the machine's load while they ran."""
    params = [r.get("params", {}) for r in group]

    def one(key: str) -> str | None:
        values = {p.get(key) for p in params if p.get(key) is not None}
        return next(iter(values)) if len(values) == 1 else (f"{len(values)} values" if values else None)

    tags = group[0]["tags"]
    arms = tags.get("arms", "surrogate,real").split(",")
    budgets = [f"{_int(one(f'rl.{a}_steps')):,} {a}" for a in arms if _int(one(f"rl.{a}_steps")) is not None]
    stop = one("rl.stop_when_solved") in ("True", "true")
    every, episodes, final = (_int(one(k)) for k in ("rl.eval_every", "rl.eval_episodes", "rl.final_episodes"))
    text = f"{tags.get('env')}, {tags.get('agent')} ({len(group)} seed{'' if len(group) == 1 else 's'}): " + (
        f"budgets {' / '.join(budgets)} steps" if budgets else "budgets not recorded")
    if every and episodes:
        rule = "stopped at the first one at the threshold" if stop else "the budgets run out (no stop)"
        confirm = one("rl.confirm_episodes")
        if stop and confirm not in (None, "0"):
            rule += f" that {confirm} fresh real episodes confirm"
        text += f", a real evaluation of {episodes} episodes every {every:,} steps, {rule}"
    if final:
        text += f", judged on {final} final real episodes"
    n, collector, eps = one("n_transitions"), one("collector.name"), one("collector.epsilon")
    if "surrogate" in arms and n:
        text += f"; the surrogate's model from {n} real transitions ({collector} collector, eps {eps})"
    loads = [r["metrics"].get("machine/load1_start") for r in group if r["metrics"].get("machine/load1_start") is not None]
    cpus = next((r["metrics"]["machine/cpus"] for r in group if "machine/cpus" in r["metrics"]), None)
    if loads and cpus:
        text += f"; load average when the runs started {min(loads):.1f}-{max(loads):.1f} on {cpus:.0f} cores"
    return text


def _recipes(runs: Sequence[Mapping[str, Any]]) -> str:
    """One sentence per (env, agent) of the transfer table, from its SINDy runs (else its others)."""
    groups: dict[tuple, list] = {}
    for r in rt.finished(runs, "transfer"):
        t = r["tags"]
        groups.setdefault((str(t.get("env")), str(t.get("agent"))), []).append(r)
    parts = []
    for _, group in sorted(groups.items()):
        sindy = [r for r in group if r["tags"].get("surrogate", "sindy") == "sindy"]
        parts.append(_recipe(sindy or group))
    return (" What the runs did (read from their params): " + "; ".join(parts) + ".") if parts else ""


def _total_steps_note(envs: Sequence[str]) -> str:
    parts = [f"{int(t['surrogate']):,} total steps for the surrogate arm against {int(t['real']):,} for the real arm "
             f"on {e}" for e in dict.fromkeys(envs) if {"surrogate", "real"} <= set(t := rt.paper(e, "total_steps"))]
    return f" The paper reports {'; '.join(parts)}." if parts else ""


def _only(df: pd.DataFrame, envs: set[str] | None) -> pd.DataFrame:
    """A table's rows of ``envs`` (None: every row, the paper's envs without runs as "not run")."""
    return df if envs is None or not len(df) else df[df["env"].isin(envs)].reset_index(drop=True)


def table_blocks(runs: Sequence[Mapping[str, Any]], link: Linker, envs: set[str] | None = None) -> list[Block]:
    """Sections 1-5: fidelity, library ablation, SINDy vs NN, RL transfer, Dyna; each with the
    paper's numbers beside ours and a "differences explained" paragraph. ``envs``: only these
    envs' rows (a selection's report leaves out the paper's envs it has no runs of)."""
    out: list[Block] = [Heading(2, "1. Fidelity per state (paper Table 1, top)")]
    fid = _only(rt.fidelity_table(runs), envs)
    out.append(_df_table(fid, [("env", "env", "text"), ("state", "state", "text"), ("library", "library", "text"),
                               ("test_set", "test set", "text"),
                               ("setup", "optimizer, collector, transitions", "text"), ("n_fits", "seeds", "int"),
                               ("mse", "one-step MSE (raw) [95% CI]", "eci"), ("mse_norm", "one-step MSE (normalized)", "e"),
                               ("corr", "corr", "f3"), ("floor_ratio", "one-step MSE / noise floor [95% CI]", "gci|-"),
                               ("floor_regime", "floor regime", "text"),
                               ("rollout", f"{rt.HORIZON}-step MSE (raw) [95% CI]", "eci"),
                               ("diverged", f"{rt.HORIZON}-step diverged", "pct"),
                               ("paper_mse", "paper MSE", "paper:e"), ("paper_corr", "paper corr", "paper:f3")], link,
                         "One fit per seed: the fits inside the paper packs' SINDy transfer runs (else fit runs), "
                         "scored on the named held-out test set. Statistic over seeds: the IQM with a 95% percentile "
                         "bootstrap CI (scipy.stats.bootstrap, 2000 resamples), the mean below 5 seeds. The noise "
                         "floor exists where the env is stochastic."))
    out.append(_with_notes(FIDELITY_DIFFERENCES + _collectors(runs), _present(fid, "n_fits"), "fidelity"))
    out.append(Heading(2, "2. Library ablation (paper Table 1, bottom)"))
    abl = _only(rt.ablation_table(runs), envs)
    out.append(_df_table(abl, [("env", "env", "text"), ("library", "library", "text"),
                                                   ("test_set", "test set", "text"),
                                                   ("setup", "optimizer, collector, transitions", "text"),
                                                   ("n_fits", "seeds", "int"),
                                                   ("mse_mean", "one-step MSE, mean over states (raw) [95% CI]", "eci"),
                                                   ("mse_norm_mean", "normalized", "e"),
                                                   ("rollout_mean", f"{rt.HORIZON}-step MSE, mean over states", "e"),
                                                   ("diverged", f"{rt.HORIZON}-step diverged", "pct"),
                                                   ("n_terms", "active terms", "g"),
                                                   ("paper_mse", "paper MSE", "paper:e")], link,
                         "SINDy fit runs per library, one per seed; IQM over seeds with a 95% bootstrap CI (the mean "
                         "below 5 seeds)."))
    out.append(_with_notes(ABLATION_DIFFERENCES, _present(abl, "n_fits"), "ablation"))
    out.append(Heading(2, "3. SINDy vs NN surrogate"))
    nn = _only(rt.sindy_vs_nn_table(runs), envs)
    kinds = rt.nn_kinds(runs)
    label = {"nn": "NN", "pe": "PE ensemble"}
    out.append(_df_table(nn, [("env", "env", "text"), ("quantity", "quantity", "text"),
                              ("sindy", "SINDy [95% CI]", "gci|n_sindy", "runs_sindy"),
                              *((k, f"{label.get(k, k)} [95% CI]", f"gci|n_{k}", f"runs_{k}") for k in kinds),
                              *((f"sindy_over_{k}", f"SINDy / {label.get(k, k)}", "g|-") for k in kinds),
                              ("n_sindy", "SINDy fits", "int", "runs_sindy"),
                              *((f"n_{k}", f"{label.get(k, k)} fits", "int", f"runs_{k}") for k in kinds)], link,
                         "Each kind over its own fit runs (one per seed; a seed's fits of the two kinds share its "
                         "data, and the fits columns say how many seeds each has); IQM over seeds with a 95% "
                         "bootstrap CI (the mean below 5 seeds)."))
    out.append(_with_notes(NN_DIFFERENCES + _nn_models(runs, [k for k in kinds if k != "nn"]),
                           _present(nn, "n_sindy", *(f"n_{k}" for k in kinds)), "nn"))
    out.append(Heading(2, "4. RL transfer (real-environment evaluation)"))
    tr = _only(rt.transfer_table(runs), envs)
    rows = []
    for _, r in tr.iterrows():
        ids = list(r["runs"])
        e = MISSING if ids else NOT_RUN
        solved = NOT_RUN if not ids else ("not reached" if r["n_solved"] == 0 else
                                         f"{fmt(r['solved_real_steps'], 'int')} ({r['n_solved']}/{r['n_seeds']} seeds)")
        solved_wall = NOT_RUN if not ids else ("not reached" if r["n_solved"] == 0 else fmt(r["solved_wall_seconds"], "f1", e))
        vals = [fmt(r["real_transitions"], "int", e), fmt(r["surrogate_steps"], "int", e), fmt(r["total_steps"], "int", e),
                None,  # the paper's number: linked to no run of ours
                _ci_text((r["return"], r["ci_low"], r["ci_high"], r["statistic"])), fmt(r["success_rate"], "pct", e),
                fmt(r["train_wall_seconds"], "f1", e), solved, solved_wall,
                fmt(r["real_steps_this_run"], "int", "-"), fmt(r["real_steps_all"], "int", "-")]
        cells = [Cell(fmt(r["paper_total_steps"], "int", "-")) if v is None else link.cell(v, ids) for v in vals]
        rows.append([Cell(r["env"]), Cell(r["surrogate"]), Cell(r["arm"]), Cell(r["agent"]), Cell(str(r["n_seeds"]))]
                    + cells + [link.ids(ids)])
    out.append(Table(["env", "surrogate", "arm", "agent", "seeds", "real transitions", "surrogate steps", "total steps",
                      "paper total steps", "final real return [95% CI]", "success", "train wall s",
                      "real steps to solved", "wall s to solved", "real steps: this run's data", "all real steps", "runs"],
                     rows,
                     "Finished transfer runs only (one per seed). Total steps as the paper counts them: surrogate "
                     "steps + real transitions. Return: IQM over seeds (the mean below 5) of each seed's mean "
                     "over 20 real episodes, with a 95% percentile bootstrap CI over seeds (scipy.stats.bootstrap, "
                     "2000 resamples, seed 0). Success: the share of those episodes the env counts as a success "
                     "(its goal, or a return at its threshold). Steps and seconds to solved: at the first real "
                     "evaluation at the threshold, the real transitions spent (a surrogate arm: its model's "
                     "data; the real arm: its training steps) and the wall seconds (training, plus collection "
                     "and fit for a surrogate arm; evaluations excluded), mean over the seeds that reached it. "
                     "Real steps (means over seeds, docs/accounting.md): this run's data = the model's data, "
                     "training and the evaluations that stop it; all real steps = that plus the real steps behind "
                     "the env's fitted priors, a trained collector's training and the recipe's tuning. Judging "
                     "(the final evaluation, the held-out set) is reported apart, in the runs."))
    run_envs = _present(tr, "n_seeds")
    out.append(_with_notes(TRANSFER_DIFFERENCES + _total_steps_note(run_envs) + _recipes(runs), run_envs, "transfer"))
    out += dyna_blocks(runs, link, envs)
    return out


def dyna_blocks(runs: Sequence[Mapping[str, Any]], link: Linker, envs: set[str] | None = None) -> list[Block]:
    """Section 5: Dyna-style refits against the real arm, in real transitions to solve."""
    out: list[Block] = [Heading(2, "5. Dyna: real transitions to solve (not in the paper)")]
    dy = _only(rt.dyna_table(runs), envs)
    if dy.empty:
        out.append(Para("Dyna: not run (no finished `task=dyna` runs)."))
        return out
    rows = []
    for _, r in dy.iterrows():
        ids = list(r["runs"])
        e = MISSING if ids else NOT_RUN
        real = r["method"].startswith("real arm")
        cost = NOT_RUN if not ids else ("not solved" if math.isinf(r["median_to_solve"]) else fmt(r["median_to_solve"], "int"))
        phases = (f"train {fmt(r['phase_a'], 'int', e)}, evaluations {fmt(r['phase_b'], 'int', e)}" if real else
                  f"collect {fmt(r['phase_a'], 'int', e)}, screens {fmt(r['phase_b'], 'int', e)}, "
                  f"confirmations {fmt(r['phase_c'], 'int', e)}")
        cost_all = NOT_RUN if not ids else ("not solved" if math.isinf(r["median_all"]) else fmt(r["median_all"], "int", "-"))
        vals = [f"{r['n_solved']}/{r['n_seeds']}", cost, _ci_text(r["censored"], "-", number="int"), phases, fmt(r["model_data"], "int", e),
                fmt(r["surrogate_steps"], "int", e), fmt(r["wall_seconds"], "f1", e), _ci_text(r["final"], "-"),
                "-" if real else _ci_text(r["audit"], "-"), cost_all, f"{r['n_stopped']}/{r['n_seeds']}",
                "-" if not math.isfinite(r["ratio_to_best_real"]) else f"{r['ratio_to_best_real']:.3g}"]
        rows.append([Cell(r["env"]), Cell(r["method"]), Cell(r["agent"])] + [link.cell(v, ids) for v in vals]
                    + [link.ids(ids)])
    out.append(Table(["env", "method", "agent", "solved", "median real transitions to solve",
                      "real transitions, unsolved = spent [95% CI]", "real steps by phase (mean)",
                      "model data (mean)", "surrogate steps (mean)", "wall s (mean)", "last 20-episode return [95% CI]",
                      "audit return [95% CI]", "median all real steps to solve", "stopped as solved by the loop",
                      "median real transitions to solve / the best real arm's", "runs"],
                     rows,
                     "Dyna (rl/dyna.py): rounds of collecting with the agent, refitting the surrogate and the env's "
                     "learned event models on all real data, and training the same agent on in the refreshed surrogate; "
                     "the loop stops when 20 fresh real episodes average the threshold. Solved: as the audit judges "
                     "(the final agent on fresh real episodes of a seed stream nothing trained or stopped on; runs "
                     "older than the audit's verdict count the loop's own stop); the loop's own verdict is the last "
                     "column. The median real transitions to solve count this run's data (collections, screens and "
                     "confirmations); the median all real steps add the env's fitted priors and the recipe's tuning "
                     "(docs/accounting.md). The real arm: the same agent in real envs, stopped at its first "
                     "evaluation at the threshold; its cost is its training steps plus those evaluations. An unsolved "
                     "seed counts as infinitely many transitions in the medians; in the IQM column it counts what it "
                     "spent (censored at its budget), so read it beside the fraction solved. A variant pack (e.g. "
                     "dyna_lunar_lander_own: every constant from the run's own data) has a row of its own. Real arms of other "
                     "agents on the same env that stopped at the threshold have rows too; the ratio column divides a "
                     "row's median real transitions to solve by the best real arm's on its env (an env config that models the "
                     "same real env in another form has rows of its own; its real arms are its sibling's)."))
    out.append(Para("Differences explained: the paper fits once and counts only the model "
                    "data and the surrogate steps; it reports no real steps spent on evaluation, which here decide "
                    "when Dyna stops and are counted."))
    return out


def selected_envs(inp: ReportInput, runs: Sequence[Mapping[str, Any]]) -> set[str] | None:
    """The envs a selection's report shows (``--parent-run`` or ``--tag``: those its runs are of);
    None for a whole experiment, whose tables keep the paper's envs without runs as "not run"."""
    if not (inp.parent_run or inp.tags):
        return None
    return {str(r["tags"]["env"]) for r in runs if r["tags"].get("env")}


def overview_blocks(inp: ReportInput, runs: Sequence[Mapping[str, Any]], problems: Sequence[str], command: str,
                    envs: set[str] | None = None) -> list[Block]:
    tags = tracking.standard_tags()
    commit = tags.get("git_commit", "unknown")
    out: list[Block] = [Heading(1, "sdrl-bench report: SINDy surrogates in RL, ours beside the paper's"),
                        Para(f"Made by `{command}` from store `{tracking.display_uri(inp.uri)}`, experiment "
                             f"`{inp.experiment}`" + (f", parent run `{inp.parent_run}`" if inp.parent_run else "")
                             + (f", tags `{inp.tags}`" if inp.tags else "") + f", {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}"
                             + f", by sdrl-bench {tags['sdrl.package_version']}"
                             + ("" if commit == "unknown" else f" at commit `{commit}`") + ".")]
    for p in problems:
        out.append(Para(f"Missing: {p}"))
    if runs:
        counts = pd.Series([f"{r['tags'].get('sdrl.kind', '?')} ({r['status']})" for r in runs]).value_counts().sort_index()
        out.append(Para("Runs read: " + ", ".join(f"{k}: {v}" for k, v in counts.items())
                        + ". Only FINISHED runs count; RUNNING, FAILED and KILLED runs are listed here but not used. "
                        "Every run read, with its tags, params and metrics: [runs.csv](runs.csv) beside this report "
                        "(the tables name runs by the first 8 characters of their MLflow run id)."
                        + (_ui_sentence(inp) if inp.ui_url else "")))
        out.append(Para(_machines_sentence(runs)))
    left = [e for e in rt.paper_envs() if envs is not None and e not in envs]
    if left:
        out.append(Para(f"This selection holds runs of {', '.join(sorted(envs)) or 'no env'} only, so the tables leave "
                        f"out the paper's {', '.join(left)} (a report of the whole experiment lists {'it' if len(left) == 1 else 'them'} "
                        "as not run)."))
    return out


def _machines_sentence(runs: Sequence[Mapping[str, Any]]) -> str:
    """Which machines made the runs (their ``sdrl.cpu`` and ``sdrl.cpu_vectors`` tags, with counts):
    a seed's digits repeat only on machines alike in these (docs/seeds.md)."""
    unknown = "not recorded (runs from before the tag)"
    counts = pd.Series([tracking.machine_label(r["tags"]) or unknown for r in runs]).value_counts().sort_index()
    return ("Machines: " + "; ".join(f"{k}: {v} run{'' if v == 1 else 's'}" for k, v in counts.items())
            + ". A seed repeats bit for bit only on machines alike in CPU and vector extensions; "
            "compare other machines' runs over seeds (docs/seeds.md in sdrl-bench's source).")


def _ui_sentence(inp: ReportInput) -> str:
    """Where the runs column's links lead, and (for a local store) how to serve it there."""
    text = f" The runs column links to the runs in the MLflow UI at {inp.ui_url}"
    if inp.uri.startswith(("http://", "https://")):
        return text + " (the tracking server's own UI)."
    return text + f" (serve this store there with `mlflow ui --backend-store-uri {tracking.display_uri(inp.uri)}`)."


def provenance_blocks(path: Path) -> list[Block]:
    """"How this report was made": the rebuild command (``scripts/reproduce.py``), its seeds and
    jobs, and each stage's commands and measured cost, from the ``rebuild.json`` it writes."""

    try:
        state = json.loads(path.read_text())
        stages = state["stages"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ConfigError(f"--provenance: {path} is not a rebuild record ({exc})") from None
    out: list[Block] = [Heading(2, "How this report was made")]
    wall = sum(v.get("wall_seconds", 0.0) for v in stages.values())
    cpu = sum(v.get("cpu_seconds", 0.0) for v in stages.values())
    out.append(Para(f"Rebuilt from an empty store by `{state.get('command', '?')}` (seeds "
                    f"{', '.join(map(str, state.get('seeds', [])))}; {state.get('jobs', '?')} jobs at a time on "
                    f"{state.get('machine', '?')}): {wall / 60:.0f} min wall, {cpu / 60:.0f} min CPU in all. A rerun "
                    "skips the finished stages, and inside a stage each sweep adopts its finished jobs. Per stage:"))
    rows = []
    for name, v in stages.items():
        cmds = "; ".join(v.get("argv") or ["sdrl-bench " + " ".join(c) if c[0] == "-m" else " ".join(c)
                                          for c in v.get("commands", [])])
        rows.append([Cell(name), Cell(v.get("status", "?")), Cell(fmt(v.get("wall_seconds"), "int", "-")),
                     Cell(fmt(v.get("cpu_seconds"), "int", "-")), Cell(v.get("finished_at", "-")), Cell(cmds)])
    out.append(Table(["stage", "status", "wall s", "CPU s (all processes)", "finished", "commands"], rows))
    return out


def build_report(inp: ReportInput, name: str, out_dir: Path, command: str = "sdrl-bench-report",
                 log_run: bool = True, provenance: Path | None = None) -> ReportResult:
    """Write ``out_dir/name/report.md`` and ``report.html`` and, when the experiment exists and
    ``log_run``, log both (with the figures) as artifacts of a "report" run. A folder that holds
    files the report did not write is refused before any work (``report_files``); an earlier
    build's files are replaced, and those this build does not make are removed."""
    start = time.perf_counter()
    report_files(out_dir, name)  # bad input fails before any work
    made = provenance_blocks(provenance) if provenance is not None else []
    runs, problems = select_runs(inp)
    if problems:  # nothing to report: say so, write nothing, log nothing
        raise ConfigError(problems[0])
    runs = latest_per_config(runs)
    problems += rt.missing_metrics(runs)
    folder, earlier, manifest = report_files(out_dir, name)  # again: the runs took seconds to load
    users = clear_earlier_build(folder, earlier, manifest)
    link = Linker(runs, inp.ui_url)
    envs = selected_envs(inp, runs)
    blocks = overview_blocks(inp, runs, problems, command, envs) + made + table_blocks(runs, link, envs)
    blocks += figure_blocks(inp.uri, runs, folder, link.url)
    blocks += fidelity_blocks(runs, folder, link)
    rt.runs_frame(runs).to_csv(folder / "runs.csv", index=False)
    (folder / "report.md").write_text(render_markdown(blocks, folder))
    (folder / "report.html").write_text(render_html(blocks, f"sdrl-bench report {name}"))
    record_build(folder, users)
    run_id = None
    if log_run and inp.experiment in tracking.list_experiments(inp.uri):
        run_id = tracking.log_report(inp.uri, inp.experiment, name, folder, {"report.n_runs": len(runs)})
    return ReportResult(folder, len(runs), problems, run_id, time.perf_counter() - start)
