"""The fidelity-vs-transfer study: one cluster end to end into a temp store (tiny SB3 agents), its
resume, its bad input, and the analysis (cluster bootstrap, halves, pooled ranks) on known data."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from helpers import compose_cfg, search
from sdrl_bench import ConfigError, tracking
from sdrl_bench.cli.fidelity_task import build_cluster, cluster_axes, run_fidelity_task
from sdrl_bench.report import fidelity_study as fs
from sdrl_bench.fidelity import ROLLOUT_CAP, normalized_error
from sdrl_bench.rl.fidelity_study import CANDIDATES

TINY = [
    "task=fidelity", "env=mountain_car", "library=poly_trig", "agent=ppo_fast", "agent.n_envs=4", "agent.algo.n_steps=16",
    "agent.algo.batch_size=32", "agent.algo.n_epochs=1", "fidelity.train_steps=64", "fidelity.agent_seeds=2",
    "fidelity.final_episodes=1", "fidelity.onpolicy_episodes=1", "fidelity.reference=heuristic",
    "fidelity.reference_episodes=1", "fidelity.axes.n_transitions=[75]", "fidelity.axes.collector=[heuristic]",
    "progress_bar=false",
]


def cluster(store, *extra):
    overrides = [f"tracking.uri={store}", *TINY, *extra]
    # as inside a sweep: the job's config key on the cluster's tags (each surrogate must still get its own)
    return run_fidelity_task(compose_cfg(*overrides), None, extra_tags={"sdrl.config_key": "the-cluster-job"},
                             given=overrides)


def test_a_cluster_scores_each_surrogate_and_counts_its_real_steps(store, capsys, tmp_path):
    out = cluster(store, "fidelity.models={law: [], polynomial: ['library=polynomial']}")
    runs = search(store)
    parent = runs[runs["tags.sdrl.kind"] == "fidelity-cluster"]
    assert len(parent) == 1 and parent.iloc[0]["status"] == "FINISHED"
    assert parent.iloc[0]["metrics.real_steps/model_data"] == 75
    sur = runs[runs["tags.sdrl.kind"] == "fidelity-surrogate"].set_index("tags.model")
    assert set(sur.index) == {"law", "polynomial"} and set(sur["status"]) == {"FINISHED"}
    assert set(sur["tags.mlflow.parentRunId"]) == {parent.iloc[0]["run_id"]}
    law, poly = sur.loc["law"], sur.loc["polynomial"]
    # the exact law from 75 heuristic transitions (docs/fidelity.md): float rounding only
    assert law["metrics.candidate/one_step"] < 1e-10 and law["metrics.candidate/rollout50"] < 1e-8
    assert poly["metrics.candidate/one_step"] > 1e3 * law["metrics.candidate/one_step"]
    for name in ("one_step", "rollout10", "rollout_episode", "reward_error", "onpolicy_one_step", "reference_gap",
                 "optimism_gap", "n_terms"):
        assert np.isfinite(law[f"metrics.candidate/{name}"]), name
    assert set(k.split("/", 1)[1] for k in runs.columns if k.startswith("metrics.candidate/")) <= set(CANDIDATES)
    # the thing to predict: the mean over agents of their real return
    assert law["metrics.real_return"] == pytest.approx((law["metrics.agent0/real_return"] + law["metrics.agent1/real_return"]) / 2)
    assert out["law"] == pytest.approx(law["metrics.real_return"])
    assert law["metrics.episodes_per_agent"] == 1  # fidelity.final_episodes: the report says what judged them
    pts = fs.points(tracking.find_runs(store, "sdrl-bench"))
    assert set(pts["n_agents"]) == {2} and set(pts["agent"]) == {"ppo_fast"} and set(pts["episodes"]) == {1.0}
    # every real step by purpose: data, one on-policy episode per agent (MountainCar: 1 to 999 steps), the judging
    for s in (law, poly):
        assert s["metrics.real_steps/model_data"] == 75
        assert 2 <= s["metrics.real_steps/onpolicy"] <= 2 * 999
        assert s["metrics.real_steps/judge"] > 2  # two final episodes and the held-out set
        assert s["metrics.real_steps/reference"] == parent.iloc[0]["metrics.real_steps/reference"] > 0

    # a rerun with one more surrogate adopts the finished ones and fits only the new one
    cluster(store, "fidelity.models={law: [], polynomial: ['library=polynomial'], trig: ['library=trig']}")
    assert "law: finished in run" in capsys.readouterr().err
    sur2 = search(store, filter_string="tags.`sdrl.kind` = 'fidelity-surrogate'")
    assert sorted(sur2["tags.model"]) == ["law", "polynomial", "trig"]

    # the report's section 6 reads them: the population, the table (3 surrogates: a Spearman, no CI) and a figure
    from sdrl_bench.report.build import ReportInput, build_report

    res = build_report(ReportInput(store), "r", tmp_path, log_run=False)
    text = (res.folder / "report.md").read_text()
    assert "## 7. Which fidelity predicts transfer" in text
    assert "mountain_car: 3 surrogates in 1 clusters" in text
    assert "Selecting on a metric: not run" in text
    assert (res.folder / "figures" / "fidelity_mountain_car.png").stat().st_size > 10_000
    table = pd.read_csv(res.folder / "fidelity_correlations.csv")
    one = table[table["metric"] == "one_step"].iloc[0]
    assert one["all_n"] == 3 and np.isfinite(one["all_rho"]) and np.isnan(one["all_lo"])  # one cluster: no CI


def test_bad_models_and_axes_fail_before_any_run(store):
    with pytest.raises(ConfigError, match="fidelity.models.law"):
        build_cluster(compose_cfg(*TINY, "fidelity.models={law: notalist}"), given=[])
    with pytest.raises(ConfigError, match=r"^fidelity.models.law: .*nope") as err:
        build_cluster(compose_cfg(*TINY, "fidelity.models={law: ['library=nope']}"), given=[])
    assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="fidelity.axes.collector"):
        build_cluster(compose_cfg(*TINY, "fidelity.axes.collector=[]"), given=[])
    # a bad-input audit: a string for the models was a traceback, a list for the study's name trained on
    with pytest.raises(ConfigError, match=r"^fidelity.models: a mapping label -> list of overrides is required$"):
        build_cluster(compose_cfg(*TINY, "fidelity.models=abc"), given=[])
    with pytest.raises(ConfigError, match=r"^fidelity.study: a name is required .*got \['a', 'b'\]$"):
        build_cluster(compose_cfg(*TINY, "fidelity.study=[a,b]"), given=[])
    with pytest.raises(ConfigError, match=r"^fidelity.axes.n_transitions: integers >= 1 are required, got 0$"):
        build_cluster(compose_cfg(*TINY, "fidelity.axes.n_transitions=[0]"), given=[])
    with pytest.raises(ConfigError, match=r"^fidelity.axes.data_noise: finite numbers >= 0 are required, got -0.1$"):
        build_cluster(compose_cfg(*TINY, "fidelity.axes.data_noise=[-0.1]"), given=[])
    assert search(store).empty


def test_cluster_seeds_cover_the_factorial_once():
    seen = set()
    for seed in range(12):
        cfg = compose_cfg("experiment=fidelity_mountain_car", f"seed={seed}")
        a = cluster_axes(cfg)
        assert a["n_clusters"] == 12
        seen.add((a["n_transitions"], a["collector"], a["data_noise"]))
    assert len(seen) == 12


def test_normalized_error_caps_non_finite_rows():
    e = normalized_error(np.zeros((3, 2)), np.array([[1.0, 1.0], [np.nan, 0.0], [1e9, 0.0]]), np.array([1.0, 2.0]))
    assert e.tolist() == [pytest.approx(0.625), ROLLOUT_CAP, ROLLOUT_CAP]


def synthetic(n_clusters=10, per=4, noise=0.0, seed=0, envs=("a", "b")):
    rng = np.random.default_rng(seed)
    rows = []
    for env in envs:
        for c in range(n_clusters):
            base = rng.normal()
            for j in range(per):
                err = rng.lognormal()
                ret = -np.log(err) + noise * rng.normal() + 0.1 * base
                rows.append({"env": env, "cluster": c, "family": "sindy" if j % 2 else "nn", "model": f"m{j}",
                             "real_return": ret, "one_step": err, "n_terms": rng.normal()})
    return pd.DataFrame(rows)


def test_a_monotone_metric_has_rho_one_and_noise_has_a_ci_around_zero():
    df = synthetic()
    rho, lo, hi, n = fs.cluster_bootstrap(df[df["env"] == "a"], "one_step", n_boot=300)
    assert n == 40 and rho > 0.97 and lo > 0.9  # return falls with the error (minus a small cluster effect)
    rho, lo, hi, _ = fs.cluster_bootstrap(df[df["env"] == "a"], "n_terms", n_boot=300)
    assert lo < 0 < hi and abs(rho) < 0.5
    pooled = fs.cluster_bootstrap(df, "one_step", n_boot=300, pooled=True)
    assert pooled[0] > 0.95 and pooled[3] == 80


def test_the_cluster_bootstrap_is_wider_than_a_row_bootstrap_when_clusters_repeat():
    # 6 clusters of 8 near-copies: 48 rows but 6 independent draws
    rng = np.random.default_rng(1)
    rows = []
    for c in range(6):
        err, ret = rng.lognormal(), rng.normal()
        for j in range(8):
            rows.append({"env": "a", "cluster": c, "family": "sindy", "model": f"m{j}",
                         "real_return": ret + 1e-3 * rng.normal(), "one_step": err * (1 + 1e-3 * rng.normal())})
    df = pd.DataFrame(rows)
    _, lo, hi, _ = fs.cluster_bootstrap(df, "one_step", n_boot=400)
    rowwise = df.assign(cluster=np.arange(len(df)))
    _, lo2, hi2, _ = fs.cluster_bootstrap(rowwise, "one_step", n_boot=400)
    assert hi - lo > 1.5 * (hi2 - lo2)


def test_halves_split_each_envs_clusters_in_two_and_the_table_has_every_part():
    df = synthetic(n_clusters=8)
    half = fs.halves(df)
    for _env, g in df.groupby("env"):
        per_cluster = half[g.index].groupby(g["cluster"]).nunique()
        assert (per_cluster == 1).all()  # a cluster is never split
        assert (half[g.index].groupby(g["cluster"]).first() == "select").sum() == 4
    assert fs.halves(df).equals(half)  # seeded
    table = fs.correlation_table(df, n_boot=100)
    assert set(table["env"]) == {"a", "b", "pooled"} and set(table["metric"]) == {"one_step", "n_terms"}
    assert fs.best_metric(table, ["one_step", "n_terms"]) == "one_step"


def test_the_studys_text_says_what_agents_and_episodes_its_runs_used():
    """Section 7 describes the runs it read (it once said "3 agents ... 10 real episodes" whatever
    the runs used)."""
    df = pd.DataFrame({"n_agents": [2, 2, 3], "agent": ["ppo_fast", "ppo_fast", "ppo_jax"],
                       "episodes": [2.0, 2.0, float("nan")]})
    assert fs._agents_phrase(df) == ("2 or 3 agents (ppo_fast or ppo_jax)", " on 2 real episodes each")
    assert fs._agents_phrase(df.assign(episodes=float("nan"))) == ("2 or 3 agents (ppo_fast or ppo_jax)", "")


def test_the_selection_table_gives_each_picks_agents_an_iqm_and_ci():
    def run(model, returns):
        metrics = {"real_return": float(np.mean(returns)), "candidate/one_step": 0.1, "candidate/onpolicy_one_step": 0.2,
                   "real_steps/model_data": 1000.0, "real_steps/judge": 5000.0,
                   **{f"agent{k}/real_return": v for k, v in enumerate(returns)}}
        return {"run_id": f"{model:0<32}", "status": "FINISHED", "metrics": metrics,
                "tags": {"sdrl.kind": "fidelity-surrogate", "sdrl.study": "select-lunar_lander", "env": "lunar_lander",
                         "seed": "100", "model": model, "family": "sindy"}}

    runs = [run("one_step", [10.0 * k for k in range(10)]), run("onpolicy_one_step", [-500.0 - k for k in range(10)])]
    blocks = fs.selection_blocks(runs)
    rows = {r[1].text: r for r in blocks[-1].rows}
    assert rows["one_step"][3].text.startswith("IQM 45.0 [") and rows["onpolicy_one_step"][3].text.startswith("IQM -504.5 [")
    assert fs.points(runs).empty  # the selection's clusters stay out of the correlation population


def test_the_agent_ceiling_is_a_guide_that_a_perfect_metric_passes():
    """One agent's return against the other agents' mean: 1 when the surrogate alone decides the
    return, lower as the agents' own luck grows; an error that is the surrogate's quality itself
    passes it, since a metric is set against all the agents' mean (the report says "a guide")."""
    rng = np.random.default_rng(3)
    quality = rng.normal(size=60)

    def frame(luck):
        returns = [list(q + luck * rng.normal(size=3)) for q in quality]
        return pd.DataFrame({"env": "a", "cluster": np.arange(60) // 2, "family": "sindy", "model": "m",
                             "agent_returns": returns, "real_return": [float(np.mean(r)) for r in returns],
                             "one_step": np.exp(-quality)})

    agree, _, _, n = fs.agent_ceiling(frame(0.0), n_boot=200)
    assert n == 60 and agree == pytest.approx(1.0)
    noisy = frame(1.0)
    ceiling, lo, hi, _ = fs.agent_ceiling(noisy, n_boot=200)
    metric = fs.cluster_bootstrap(noisy, "one_step", n_boot=200)[0]
    assert 0.2 < ceiling < 0.8 and lo < ceiling < hi
    assert metric > ceiling + 0.1
