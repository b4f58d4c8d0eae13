"""Which fidelity predicts transfer: the study's analysis (``task=fidelity`` runs -> table, figures).

Per env and candidate metric (``rl.fidelity_study.CANDIDATES``, all errors): the Spearman rank
correlation of ``-metric`` with the surrogates' real return (positive: lower error, better agents),
with a 95% CI from a bootstrap that resamples *clusters* (the surrogates fitted on one data set
are not independent), and the same pooled over envs on ranks taken within each env. The metric is
chosen on one half of the clusters (a seeded random half per env) and confirmed on the other.

Hand-written, and why: ``scipy.stats.bootstrap`` resamples observations, not groups of them; the
cluster bootstrap here resamples whole clusters with replacement and calls ``scipy.stats.spearmanr``
on each resample (percentile interval). ``scipy.stats.spearmanr`` gives every point estimate.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd
from scipy import stats

SURROGATE_KIND = "fidelity-surrogate"
N_BOOT = 2000
SPLIT_SEED = 0
MIN_CLUSTERS = 3
"""Fewer clusters in an env: a Spearman without a CI."""
TARGET = 0.8
"""The Spearman correlation the issue asks a metric to reach on an env."""


STUDY_PREFIX = "fidelity-"
"""The studies the report pools (``fidelity.study``, default ``fidelity-<env>``); others (a
selection experiment's clusters, ``select-<env>``) are read by their own scripts."""


def points(runs: Sequence[Mapping[str, Any]], prefix: str = STUDY_PREFIX) -> pd.DataFrame:
    """One row per finished surrogate of the studies named ``prefix*``: env, study, cluster, family,
    model, data settings, real return and every ``candidate/*`` metric (columns named by the candidate)."""
    rows = []
    for r in runs:
        if r.get("status") != "FINISHED" or r["tags"].get("sdrl.kind") != SURROGATE_KIND \
                or not str(r["tags"].get("sdrl.study", "")).startswith(prefix):
            continue
        t, m = r["tags"], r["metrics"]
        if "real_return" not in m:
            continue
        row = {"run_id": r["run_id"], "env": t.get("env"), "study": t.get("sdrl.study"), "cluster": int(t.get("seed", -1)),
               "family": t.get("family"), "model": t.get("model"), "n_transitions": t.get("n_transitions"),
               "collector": t.get("collector"), "data_noise": t.get("data_noise"), "real_return": m["real_return"],
               "real_steps_onpolicy": m.get("real_steps/onpolicy", 0.0), "real_steps_model": m.get("real_steps/model_data", 0.0),
               "real_steps_judge": m.get("real_steps/judge", 0.0), "real_steps_reference": m.get("real_steps/reference", 0.0)}
        row.update({k.split("/", 1)[1]: v for k, v in m.items() if k.startswith("candidate/")})
        k, agents = 0, []
        while f"agent{k}/real_return" in m:
            agents.append(m[f"agent{k}/real_return"])
            k += 1
        row["agent_returns"] = agents
        row.update(agent=t.get("agent"), n_agents=len(agents), episodes=m.get("episodes_per_agent"))
        rows.append(row)
    df = pd.DataFrame(rows)
    if not df.empty:  # a surrogate rerun after an adoption: the newest run per (study, cluster, model)
        df = df.drop_duplicates(["study", "cluster", "model"], keep="first")
    return df


def candidates_of(df: pd.DataFrame) -> list[str]:
    from sdrl_bench.rl.fidelity_study import CANDIDATES

    return [c for c in CANDIDATES if c in df.columns and df[c].notna().any()]


def _rho(x: np.ndarray, y: np.ndarray) -> float:
    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 3 or np.ptp(x[ok]) == 0 or np.ptp(y[ok]) == 0:
        return float("nan")
    return float(stats.spearmanr(x[ok], y[ok]).statistic)


def _within_ranks(df: pd.DataFrame, col: str) -> np.ndarray:
    """Ranks within each env, scaled to (0, 1]: envs pooled on a common scale."""
    return df.groupby("env")[col].rank(pct=True).to_numpy()


def cluster_bootstrap(df: pd.DataFrame, metric: str, n_boot: int = N_BOOT, seed: int = 0,
                      pooled: bool = False) -> tuple[float, float, float, int]:
    """(rho, CI low, CI high, n) of Spearman(-metric, real return) over ``df``'s surrogates;
    the CI resamples clusters (per env, stratified, when ``pooled``)."""
    d = df[np.isfinite(df[metric].to_numpy(float))]
    if len(d) < 3:
        return float("nan"), float("nan"), float("nan"), len(d)

    def rho(sub: pd.DataFrame) -> float:
        if pooled:
            return _rho(-_within_ranks(sub, metric), _within_ranks(sub, "real_return"))
        return _rho(-sub[metric].to_numpy(float), sub["real_return"].to_numpy(float))

    est = rho(d)
    rng = np.random.default_rng(seed)
    groups = {key: g for key, g in d.groupby(["env", "cluster"])}
    by_env: dict[str, list] = {}
    for (env, _), g in groups.items():
        by_env.setdefault(env, []).append(g)
    if min(len(gs) for gs in by_env.values()) < MIN_CLUSTERS:  # resampling one or two clusters is no interval
        return est, float("nan"), float("nan"), len(d)
    boots = []
    for _ in range(n_boot):
        parts = []
        for gs in by_env.values():
            for i in rng.integers(len(gs), size=len(gs)):
                parts.append(gs[i])
        b = rho(pd.concat(parts, ignore_index=True))
        if math.isfinite(b):
            boots.append(b)
    if len(boots) < n_boot // 2:
        return est, float("nan"), float("nan"), len(d)
    lo, hi = np.percentile(boots, [2.5, 97.5])
    return est, float(lo), float(hi), len(d)


def agent_ceiling(df: pd.DataFrame, n_boot: int = N_BOOT) -> tuple[float, float, float, int]:
    """How well the target can be predicted at all: Spearman of one agent's real return with the
    other agents' mean in the same surrogate, across surrogates (cluster-bootstrap CI). Agents that
    fail or succeed regardless of the surrogate pull it below 1, and no fidelity metric can rank
    surrogates much better than their own agents agree (a guide, not a hard bound: a metric is
    correlated with all the agents' mean, less noisy than the one agent here)."""
    d = df[df["agent_returns"].map(len) >= 2].copy()
    d["first"] = d["agent_returns"].map(lambda r: r[0])
    d["others"] = d["agent_returns"].map(lambda r: float(np.mean(r[1:])))
    d = d.assign(**{"real_return": d["others"], "_first": -d["first"]})
    return cluster_bootstrap(d, "_first", n_boot)


def halves(df: pd.DataFrame, seed: int = SPLIT_SEED) -> pd.Series:
    """``"select"`` or ``"confirm"`` per row: a seeded random half of each env's clusters selects."""
    half = pd.Series("confirm", index=df.index)
    for env, g in df.groupby("env"):
        clusters = np.array(sorted(g["cluster"].unique()))
        rng = np.random.default_rng([seed, sum(map(ord, str(env)))])
        pick = set(rng.permutation(clusters)[: len(clusters) // 2].tolist())
        half[g.index[g["cluster"].isin(pick)]] = "select"
    return half


def correlation_table(df: pd.DataFrame, n_boot: int = N_BOOT) -> pd.DataFrame:
    """Per (env or "pooled", metric): rho [CI] on all surrogates, on the selection half and on the
    confirmation half, and n."""
    half = halves(df)
    rows = []
    envs = sorted(df["env"].unique())
    for metric in candidates_of(df):
        for env in [*envs, "pooled"]:
            d = df if env == "pooled" else df[df["env"] == env]
            if env == "pooled" and len(envs) < 2:
                continue
            row: dict[str, Any] = {"env": env, "metric": metric}
            for part, sel in (("all", d.index), ("select", d.index[half[d.index] == "select"]),
                              ("confirm", d.index[half[d.index] == "confirm"])):
                rho, lo, hi, n = cluster_bootstrap(d.loc[sel], metric, n_boot, pooled=env == "pooled")
                row.update({f"{part}_rho": rho, f"{part}_lo": lo, f"{part}_hi": hi, f"{part}_n": n})
            rows.append(row)
    return pd.DataFrame(rows)


def best_metric(table: pd.DataFrame, selectable: Sequence[str]) -> str | None:
    """The selector the study recommends: among ``selectable`` metrics measured on every env, the
    highest lower CI bound of the pooled Spearman (ranks within env) on the selection half; its
    confirmation-half interval is then read off the same table. One env alone: that env's bound."""
    envs = set(table.loc[table["env"] != "pooled", "env"])
    per_env = table[table["env"] != "pooled"].dropna(subset=["select_rho"])
    everywhere = [m for m in selectable if set(per_env.loc[per_env["metric"] == m, "env"]) == envs]
    scope = "pooled" if len(envs) > 1 else next(iter(envs), None)
    t = table[(table["env"] == scope) & table["metric"].isin(everywhere)].dropna(subset=["select_lo"])
    return str(t.loc[t["select_lo"].idxmax(), "metric"]) if not t.empty else None


def scatter_figure(df: pd.DataFrame, env: str, metrics: Sequence[str]):
    """Metric vs real return, one point per surrogate, coloured by model family; one panel per metric."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = df[df["env"] == env]
    n = len(metrics)
    cols = min(4, n)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.0 * rows), squeeze=False)
    colours = {f: plt.cm.tab10(i) for i, f in enumerate(sorted(d["family"].dropna().unique()))}
    for ax, metric in zip(axes.ravel(), metrics, strict=False):
        x = d[metric].to_numpy(float)
        for fam, c in colours.items():
            sel = (d["family"] == fam).to_numpy() & np.isfinite(x)
            ax.scatter(x[sel], d["real_return"].to_numpy(float)[sel], s=14, color=c, label=fam, alpha=0.8)
        pos = x[np.isfinite(x)]
        if len(pos) and pos.min() > 0 and pos.max() / pos.min() > 100:
            ax.set_xscale("log")
        rho = _rho(-x, d["real_return"].to_numpy(float))
        ax.set_title(f"{metric} (rho {rho:+.2f})", fontsize=9)
        ax.tick_params(labelsize=7)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    axes[0, 0].set_ylabel("real return")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"{env}: fidelity metric vs real return of agents trained in the surrogate", fontsize=10)
    fig.tight_layout()
    return fig


def _ci(rho: float, lo: float, hi: float) -> str:
    if not math.isfinite(rho):
        return "-"
    return f"{rho:+.2f} [{lo:+.2f}, {hi:+.2f}]" if math.isfinite(lo) else f"{rho:+.2f}"


def _agents_phrase(df: pd.DataFrame) -> tuple[str, str]:
    """What the runs read say of their agents: (how many per surrogate and which, how many real
    episodes judge each), e.g. ("3 agents (ppo_jax)", " on 10 real episodes each")."""
    def alts(values) -> str:
        found = sorted({v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))})
        return " or ".join(f"{v:g}" if isinstance(v, float) else str(v) for v in found)

    n, agents, eps = alts(df["n_agents"]), alts(df["agent"]), alts(df["episodes"])
    return (f"{n or '?'} agents" + (f" ({agents})" if agents else ""),
            f" on {eps} real episodes each" if eps else "")


def fidelity_blocks(runs: Sequence[Mapping[str, Any]], folder, link) -> list:
    """Section 6 of the report: the population, the correlation table, one scatter figure per env,
    the recommended selector and the real steps the study spent."""
    from sdrl_bench.report.render import Cell, Heading, Image, Para, Table
    from sdrl_bench.rl.fidelity_study import CANDIDATES, NEEDS_POLICY

    out: list = [Heading(2, "7. Which fidelity predicts transfer (not in the paper)")]
    df = points(runs)
    if df.empty:
        out.append(Para("Fidelity study: not run (no finished `task=fidelity` surrogates; "
                        "`sdrl-bench -m experiment=fidelity_<env>`)."))
        return out
    lines = []
    for env, g in df.groupby("env"):
        lines.append(f"{env}: {len(g)} surrogates in {g['cluster'].nunique()} clusters (families "
                     + ", ".join(f"{f} {n}" for f, n in g["family"].value_counts().sort_index().items())
                     + f"), real return {g['real_return'].min():.1f} to {g['real_return'].max():.1f}; real steps: "
                     f"model data {g.groupby('cluster')['real_steps_model'].first().sum():,.0f}, on-policy "
                     f"{g['real_steps_onpolicy'].sum():,.0f}, reference {g.groupby('cluster')['real_steps_reference'].first().sum():,.0f}, "
                     f"judging {g['real_steps_judge'].sum():,.0f}")
    who, episodes = _agents_phrase(df)
    out.append(Para("Each surrogate is fitted on one cluster's real data (a data size, collector and noise level "
                    f"chosen by the cluster's seed); {who} train in it, with one recipe and budget per study, and are "
                    f"judged in the real env{episodes} (stream `final_eval`); its real return is their mean. "
                    "Spearman of minus the metric with the real return (positive: lower error, better agents), 95% CI "
                    "from 2,000 cluster-bootstrap resamples; select / confirm: a seeded random half of each env's "
                    "clusters each; pooled: ranks within env. " + "; ".join(lines) + "."))
    table = correlation_table(df)
    ceilings, ceiling = [], {}
    for env in sorted(df["env"].unique()):
        rho, lo, hi, n = agent_ceiling(df[df["env"] == env])
        ceilings.append(f"{env} {_ci(rho, lo, hi)}")
        ceiling[env] = rho
    out.append(Para("How far the target can be predicted: the Spearman of one agent's real return with the other "
                    "agents' mean in the same surrogates (the agents agree on a surrogate only as far as its quality, "
                    "not their own luck, decides their return): " + "; ".join(ceilings) + "."))
    rows = []
    for _, r in table.iterrows():
        rows.append([Cell(r["env"]), Cell(r["metric"]), Cell(str(int(r["all_n"]))), Cell(_ci(r["all_rho"], r["all_lo"], r["all_hi"])),
                     Cell(_ci(r["select_rho"], r["select_lo"], r["select_hi"])),
                     Cell(_ci(r["confirm_rho"], r["confirm_lo"], r["confirm_hi"]))])
    out.append(Table(["env", "metric", "surrogates", "Spearman, all [95% CI]", "selection half", "confirmation half"], rows,
                     "Metrics: " + "; ".join(f"`{k}`: {v}" for k, v in CANDIDATES.items())))
    from sdrl_bench.fidelity import DATA_METRICS, POLICY_METRICS

    selectable = [m for m in candidates_of(df) if m in DATA_METRICS + POLICY_METRICS]  # what search.objective offers
    best = best_metric(table, selectable)
    if best is not None:
        conf = table[(table["metric"] == best)]
        text = ", ".join(f"{r['env']} {_ci(r['confirm_rho'], r['confirm_lo'], r['confirm_hi'])}" for _, r in conf.iterrows())
        needs = " It needs trained agents' real episodes (real steps per candidate)." if best in NEEDS_POLICY else ""
        out.append(Para(f"Chosen on the selection half (the highest lower CI bound of the pooled Spearman among the "
                        f"metrics every env measures that `search.objective` offers: "
                        f"{', '.join(f'`{m}`' for m in selectable)}): `{best}`; on the confirmation half: {text}.{needs}"))
    envs = sorted(df["env"].unique())
    for env in envs:
        t = table[(table["env"] == env)]
        top = t["all_rho"].max()
        if not (top >= TARGET):
            limit = (f"the agents themselves agree only to {ceiling[env]:+.2f} (one agent with the others' mean), "
                     "a guide to what a metric can show, not a strict bound (a metric is correlated with all "
                     "the agents' mean, which is less noisy than one agent)"
                     if ceiling.get(env, math.nan) < TARGET else
                     f"the agents agree ({ceiling.get(env, math.nan):+.2f}): the surrogate decides their return, "
                     "and no metric here sees enough of what in it does")
            out.append(Para(f"{env}: no metric reaches Spearman {TARGET} (best {t.loc[t['all_rho'].idxmax(), 'metric']} "
                            f"{top:+.2f}); {limit}." if math.isfinite(top) else f"{env}: too few surrogates for a correlation."))
    figs = folder / "figures"
    figs.mkdir(parents=True, exist_ok=True)
    for env in envs:
        fig = scatter_figure(df, env, candidates_of(df))
        path = figs / f"fidelity_{env}.png"
        fig.savefig(path, dpi=90)
        import matplotlib.pyplot as plt

        plt.close(fig)
        out.append(Image(path, f"{env}: each candidate metric against the real return (one point per surrogate)"))
    table.to_csv(folder / "fidelity_correlations.csv", index=False)
    out.append(Para("The table as numbers: [fidelity_correlations.csv](fidelity_correlations.csv)."))
    out += selection_blocks(runs)
    return out


def selection_blocks(runs: Sequence[Mapping[str, Any]]) -> list:
    """Selecting on a metric: the clusters of ``studies/select_on_fidelity.py`` (studies ``select-<env>``),
    each surrogate a search's pick, its agents' real return as the IQM with a 95% bootstrap CI."""
    from sdrl_bench.report.render import Cell, Heading, Para, Table
    from sdrl_bench.report.tables import bootstrap_ci

    df = points(runs, prefix="select-")
    if df.empty:
        return [Para("Selecting on a metric: not run (`studies/select_on_fidelity.py`).")]
    rows = []
    for (env, model), g in df.groupby(["env", "model"]):
        r = g.iloc[0]
        point, lo, hi, stat = bootstrap_ci(r["agent_returns"])
        rows.append([Cell(env), Cell(model), Cell(str(len(r["agent_returns"]))), Cell(f"{stat} {point:.1f} [{lo:.1f}, {hi:.1f}]"),
                     Cell(f"{r['one_step']:.3g}"), Cell(f"{r.get('onpolicy_one_step', float('nan')):.3g}"),
                     Cell(f"{r['real_steps_model']:,.0f} + judge {r['real_steps_judge']:,.0f}"), Cell(r["run_id"][:8])])
    return [Heading(3, "Selecting the surrogate on a metric"),
            Para("Two Optuna searches (20 TPE trials each, the default SINDy space) on the same real data (seed 100, outside "
                 "the study's clusters): one with today's objective (`one_step`: k-fold one-step error), one with the "
                 "study's recommended metric; each pick fitted on the data and 10 agents trained in it with the study's "
                 "recipe, judged on 10 real episodes each. The policy objective's own real episodes per trial are logged "
                 "on the search's trial runs (`real_steps/selection`)."),
            Table(["env", "selected on", "agents", "real return [95% CI]", "test one-step error",
                   "agents' on-policy error", "real steps (model data + judging)", "run"], rows)]
