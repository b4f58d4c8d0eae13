"""The report generator on a real temp SQLite store holding runs logged through tracking.py."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from sdrl_bench.report import tables as rt
from sdrl_bench import tracking
from sdrl_bench.cli.report import main
from sdrl_bench.report.build import ReportInput, build_report
from helpers import compose_cfg, search

EXP = "sdrl-bench"
SETUP_CELL = "stlsq, expert, 1000"  # ``_ll_fit``'s optimizer, collector and real transitions


def _fit(uri: str, env: str, library: str, surrogate: str, seed: int, mse: dict[str, float], parent: str | None = None) -> str:
    tags = {"sdrl.kind": "fit", "env": env, "library": library, "surrogate": surrogate, "seed": seed,
            "collector": "heuristic", "test_set": f"{env}-heldout-v1"}
    with tracking.start_run(uri, EXP, f"fit-{env}-{library}-{surrogate}-s{seed}", tags, parent) as run:
        metrics = {f"mse/{k}": v for k, v in mse.items()}
        metrics.update({f"corr/{k}": 1 - v for k, v in mse.items()}, **{f"mse_norm/{k}": 10 * v for k, v in mse.items()})
        metrics.update({"mse/mean": float(np.mean(list(mse.values()))), "fit_wall_seconds": 0.01 * (seed + 1),
                        "fit_cpu_seconds": 0.02, "n_parameters": 7 if surrogate == "sindy" else 4354})
        run.log_metrics(metrics)
    return run.run_id


def _transfer(uri: str, seed: int, surrogate_return: float, real_return: float, parent: str | None = None,
              agent: str = "sac", older: bool = False) -> str:
    """A transfer run as ``task=train`` logs it: the fit's metrics under a fit run's names and its
    accounting under ``fit/`` (``older``: every fit metric under ``fit/``, as runs before 2026-11-26 did)."""
    fit = {"mse/x": 1e-16, "mse/v": 2e-19, "corr/x": 1.0, "corr/v": 1.0}
    fit = ({f"fit/{k}": v for k, v in fit.items()} if older else
           {**fit, "fit/real_steps/model_data": 75, "fit/real_steps/this_run": 75})
    tags = {"sdrl.kind": "transfer", "env": "mountain_car", "agent": agent, "surrogate": "sindy",
            "library": "poly_trig", "seed": seed, "test_set": "mountain_car-heldout-v1"}
    with tracking.start_run(uri, EXP, f"train-s{seed}", tags, parent) as run:
        run.log_metrics({"surrogate/final_return_mean": surrogate_return, "real/final_return_mean": real_return,
                         "surrogate/real_transitions_model": 75, "surrogate/real_transitions_train": 0,
                         "surrogate/surrogate_steps": 65_000, "surrogate/total_steps": 65_075,
                         "real/real_transitions_model": 0, "real/real_transitions_train": 100_000,
                         "real/surrogate_steps": 0, "real/total_steps": 100_000, "surrogate/success_rate": 1.0,
                         "real/success_rate": 0.5, "surrogate/train_wall_seconds": 10.0 + seed,
                         "real/train_wall_seconds": 20.0, "real/solved_real_steps": 25_000.0, **fit})
        for arm, ret in (("surrogate", surrogate_return), ("real", real_return)):
            run.log_text(f"train_steps,return_mean,return_std\n0,-10,1\n1000,{ret},1\n", f"curves/{arm}.csv")
        run.log_text("x[k+1] = 1 x +1 v +0.0015 u -0.0025 cos(3 x)\nv[k+1] = 1 v +0.0015 u -0.0025 cos(3 x)\n",
                     "model/equations.txt")
    return run.run_id


@pytest.fixture
def fits_store(store: str) -> str:
    _fit(store, "mountain_car", "poly_trig", "sindy", 0, {"x": 1e-16, "v": 3e-19})
    _fit(store, "mountain_car", "poly_trig", "sindy", 1, {"x": 3e-16, "v": 5e-19})
    _fit(store, "mountain_car", "polynomial", "sindy", 0, {"x": 4e-6, "v": 2e-7})
    _fit(store, "mountain_car", "nn", "nn", 0, {"x": 2e-9, "v": 4e-10})
    return store


def _client_metrics(uri: str, filter_string: str) -> list[dict[str, float]]:
    df = search(uri, EXP, filter_string)
    return [{c[len("metrics."):]: row[c] for c in df.columns if c.startswith("metrics.") and not math.isnan(row[c])}
            for _, row in df.iterrows()]


def test_tables_equal_the_runs_metrics_read_through_the_client(fits_store: str) -> None:
    runs = tracking.find_runs(fits_store, EXP, missing_ok=False)
    fid = rt.fidelity_table(runs).set_index(["env", "state"])
    sindy = _client_metrics(fits_store, "tags.library = 'poly_trig' and tags.surrogate = 'sindy'")
    assert len(sindy) == 2
    for state in ("x", "v"):
        row = fid.loc[("mountain_car", state)]
        assert row["mse"] == pytest.approx(np.mean([m[f"mse/{state}"] for m in sindy]), rel=1e-12)
        assert row["corr"] == pytest.approx(np.mean([m[f"corr/{state}"] for m in sindy]), rel=1e-12)
        assert row["paper_mse"] == rt.paper("mountain_car", "fidelity")[state][0] == {"x": 7.21e-4, "v": 3.11e-6}[state]
        assert row["library"] == "poly_trig" and row["n_fits"] == 2
    abl = rt.ablation_table(runs).set_index(["env", "library"])
    poly = _client_metrics(fits_store, "tags.library = 'polynomial'")
    assert abl.loc[("mountain_car", "polynomial"), "mse_mean"] == poly[0]["mse/mean"]
    assert math.isnan(abl.loc[("mountain_car", "rational"), "mse_mean"]) and abl.loc[("mountain_car", "rational"), "runs"] == []
    vs = rt.sindy_vs_nn_table(runs).set_index(["env", "quantity"])
    nn = _client_metrics(fits_store, "tags.surrogate = 'nn'")[0]
    assert vs.loc[("mountain_car", "mse/v"), "nn"] == nn["mse/v"]
    assert vs.loc[("mountain_car", "n_parameters"), "sindy_over_nn"] == pytest.approx(7 / 4354)
    wall = np.mean([m["fit_wall_seconds"] for m in sindy])
    assert vs.loc[("mountain_car", "fit_wall_seconds"), "sindy_over_nn"] == pytest.approx(wall / nn["fit_wall_seconds"])


def test_a_probabilistic_ensembles_fits_get_columns_of_their_own_and_a_sentence_from_their_params(
        fits_store: str, tmp_path) -> None:
    """Section 3 compares SINDy with every NN kind that has fit runs: the MLP, then the PE
    ensemble, each with its IQM, CI, ratio, count and runs; the PE's network is described from
    its runs' params. Without PE fits the table has no PE columns."""
    assert "pe" not in rt.sindy_vs_nn_table(tracking.find_runs(fits_store, EXP)).columns
    pe = _fit(fits_store, "mountain_car", "pe", "pe", 0, {"x": 5e-9, "v": 8e-10})
    tracking.Run(fits_store, pe).log_params({"surrogate.model.width": 128, "surrogate.model.depth": 2,
                                             "surrogate.model.ensemble_size": 7, "surrogate.model.n_elites": 5,
                                             "surrogate.model.activation": "silu"})
    runs = tracking.find_runs(fits_store, EXP)
    assert rt.nn_kinds(runs) == ["nn", "pe"]
    vs = rt.sindy_vs_nn_table(runs).set_index(["env", "quantity"]).loc[("mountain_car", "mse/v")]
    assert vs["pe"] == 8e-10 and vs["n_pe"] == 1 and vs["runs_pe"] == [pe] and vs["nn"] == 4e-10
    assert vs["sindy_over_pe"] == pytest.approx(np.mean([3e-19, 5e-19]) / 8e-10)
    md = (build_report(ReportInput(fits_store, EXP), "pe", tmp_path, log_run=False).folder / "report.md").read_text()
    section = md.split("## 3.")[1].split("## 4.")[0]
    assert "| PE ensemble [95% CI] |" in section and "| SINDy / PE ensemble |" in section
    assert "`surrogate=pe`: 7 members of 128x128 silu units, the best 5 kept" in section


def test_bootstrap_ci_matches_a_hand_computation() -> None:
    three = [90.0, 94.0, 95.5]
    point, lo, hi, name = rt.bootstrap_ci(three, seed=3)
    ref = stats.bootstrap((np.array(three),), np.mean, confidence_level=0.95, n_resamples=2000, method="percentile",
                          rng=np.random.default_rng(3))
    assert (name, point) == ("mean", pytest.approx(np.mean(three)))
    assert (lo, hi) == (ref.confidence_interval.low, ref.confidence_interval.high)
    # a percentile bootstrap by hand: resample seeds, take the 2.5% and 97.5% quantiles
    rng = np.random.default_rng(0)
    boots = np.array(three)[rng.integers(0, 3, size=(20000, 3))].mean(axis=1)
    assert lo == pytest.approx(np.quantile(boots, 0.025), abs=0.6)
    assert hi == pytest.approx(np.quantile(boots, 0.975), abs=0.6)
    six = [10.0, 80.0, 90.0, 91.0, 95.0, 200.0]
    point, lo, hi, name = rt.bootstrap_ci(six)
    assert name == "IQM" and point == pytest.approx(np.mean(sorted(six)[1:5])) and lo <= point <= hi
    assert rt.bootstrap_ci(six[::-1]) == (point, lo, hi, name)  # the same seeds read in another order
    one = rt.bootstrap_ci([5.0])
    assert one[0] == 5.0 and math.isnan(one[1]) and math.isnan(one[2])  # no CI from one seed
    assert math.isnan(rt.bootstrap_ci([])[0])


@pytest.mark.parametrize("older", [False, True])
def test_the_fit_inside_a_transfer_run_is_a_fit_record_under_either_naming(store: str, older: bool) -> None:
    """Today's transfer runs log the fit under a fit run's names (its accounting under ``fit/``),
    older ones all of it under ``fit/``: either way the fit is one record, with unprefixed metrics."""
    rid = _transfer(store, 0, 94.0, 95.0, older=older)
    records = [f for f in rt.fit_records(tracking.find_runs(store, EXP)) if f["run_id"] == rid]
    assert len(records) == 1 and records[0]["source"] == "transfer"
    m = records[0]["metrics"]
    assert (m["mse/x"], m["mse/v"]) == (1e-16, 2e-19) and not [k for k in m if k.startswith(("fit/", "surrogate/", "real/"))]
    assert m.get("real_steps/this_run") == (None if older else 75)
    assert rt.fidelity_table(tracking.find_runs(store, EXP)).set_index(["env", "state"]).loc[("mountain_car", "x"), "n_fits"] == 1


def test_runs_of_two_agents_get_rows_of_their_own(store: str) -> None:
    """The zoo recipe and a fast one (agent=ppo_fast) in one store are not pooled."""
    zoo = [_transfer(store, s, 94.0 + s, 95.0) for s in range(2)]
    fast = [_transfer(store, s, 80.0 + s, 90.0, agent="ppo_fast") for s in range(3)]
    tr = rt.transfer_table(tracking.find_runs(store, EXP)).set_index(["env", "surrogate", "agent", "arm"])
    sac, ppo = tr.loc[("mountain_car", "sindy", "sac", "surrogate")], tr.loc[("mountain_car", "sindy", "ppo_fast", "surrogate")]
    assert sorted(sac["runs"]) == sorted(zoo) and sac["return"] == pytest.approx(94.5)
    assert sorted(ppo["runs"]) == sorted(fast) and ppo["return"] == pytest.approx(81.0)
    assert tr.loc[("mountain_car", "nn", "ppo_fast", "real"), "n_seeds"] == 0


def test_transfer_table_and_report_from_a_sweep(store: str, tmp_path) -> None:
    parent = tracking.create_parent_run(store, EXP, "sweep", {"sdrl.kind": "sweep"})
    ids = [_transfer(store, s, r, 90.0 + s, parent) for s, r in enumerate([93.0, 95.0, 94.0])]
    _fit(store, "mountain_car", "poly_trig", "sindy", 9, {"x": 1e-3, "v": 1e-3})  # outside the sweep
    with tracking.start_run(store, EXP, "unfinished", {"sdrl.kind": "transfer", "env": "mountain_car"}, parent) as run:
        pass
    tracking.Run(store, run.run_id).end("RUNNING")  # still training: must not count
    runs = tracking.find_runs(store, EXP, missing_ok=False)
    tr = rt.transfer_table(runs).set_index(["env", "surrogate", "arm"])
    sur = tr.loc[("mountain_car", "sindy", "surrogate")]
    client = _client_metrics(store, f"tags.`mlflow.parentRunId` = '{parent}' and attributes.status = 'FINISHED'")
    returns = [m["surrogate/final_return_mean"] for m in client]
    assert sur["n_seeds"] == 3 and sorted(sur["runs"]) == sorted(ids)
    assert (sur["return"], sur["ci_low"], sur["ci_high"]) == pytest.approx(rt.bootstrap_ci(returns)[:3])
    assert sur["total_steps"] == 65_075 and sur["real_transitions"] == 75 and sur["train_wall_seconds"] == 11.0
    assert sur["n_solved"] == 0 and tr.loc[("mountain_car", "sindy", "real"), "solved_real_steps"] == 25_000
    assert tr.loc[("lunar_lander", "sindy", "surrogate"), "n_seeds"] == 0

    res = build_report(ReportInput(store, EXP, parent_run=parent, ui_url="http://ui:5000"), "t", tmp_path)
    md = (res.folder / "report.md").read_text()
    html = (res.folder / "report.html").read_text()
    assert res.n_runs == 5 and res.problems == []  # parent, 3 transfers, the RUNNING one
    assert "http://ui:5000/#/experiments/" in md and f"/runs/{ids[0]}" in md
    assert "94 [" in md and "(mean)" in md and "not run" in md
    # the sweep ran MountainCar only: the paper's LunarLander rows ("not run") are left out, and the report says so
    assert "| lunar_lander |" not in md and "| mountain_car | sindy | surrogate | sac | 3 |" in md
    assert ("This selection holds runs of mountain_car only, so the tables leave out the paper's lunar_lander "
            "(a report of the whole experiment lists it as not run).") in md
    cpu = tracking.cpu_tags()  # the machine every run was made on, counted (docs/seeds.md)
    assert f"Machines: {cpu['sdrl.cpu']} [{cpu['sdrl.cpu_vectors']}]: 5 runs." in md
    assert "figures/curves_mountain_car_sac_sindy.png" in md and (res.folder / "figures/curves_mountain_car_sac_sindy.png").is_file()
    assert "data:image/png;base64," in html and "<img class='math'" in html and "src='figures/" not in html
    logged = search(store, EXP, "tags.`sdrl.kind` = 'report'")
    assert list(logged["run_id"]) == [res.report_run_id]


def test_not_run_when_the_store_holds_only_fits(fits_store: str, tmp_path) -> None:
    res = build_report(ReportInput(fits_store, EXP), "fits", tmp_path, log_run=False)
    md = (res.folder / "report.md").read_text()
    ll = [line for line in md.splitlines() if line.startswith("| lunar_lander | sindy | surrogate")]
    assert ll and ll[0].count("not run") >= 5
    assert "RL transfer: not run" in md and "Optuna search: not run" in md
    assert "| mountain_car | rational | - |  | 0 | not run |" in md


@pytest.mark.parametrize("case", ["empty", "experiment", "parent", "not_hex"])
def test_bad_input_gives_one_line_on_stderr_and_no_report(case: str, fits_store: str, tmp_path, capsys) -> None:
    uri = f"sqlite:///{tmp_path / 'empty' / 'mlflow.db'}" if case == "empty" else fits_store
    args = ["--uri", uri, "--out", str(tmp_path / "out"), "--name", case]
    args += {"empty": [], "experiment": ["--experiment", "nope"], "parent": ["--parent-run", "0" * 32],
             "not_hex": ["--parent-run", "notahexid"]}[case]
    n_runs = None if case == "empty" else len(tracking.find_runs(uri, EXP))
    assert main(args) == 2
    err = capsys.readouterr()
    expected = {"empty": "no tracking store at", "experiment": "no experiment 'nope'", "parent": "no run '000",
                "not_hex": "no run 'notahexid'"}[case]
    assert err.out == "" and expected in err.err and len(err.err.strip().splitlines()) == 1
    assert "Traceback" not in err.err
    assert not (tmp_path / "out" / case).exists()  # nothing written (an older report of that name is kept)
    if case == "empty":
        assert not (tmp_path / "empty").exists()  # no store created by looking
    else:
        assert len(tracking.find_runs(uri, EXP)) == n_runs  # no report run logged


def test_runs_missing_metrics_are_named(store: str, tmp_path) -> None:
    with tracking.start_run(store, EXP, "bare", {"sdrl.kind": "transfer", "env": "mountain_car"}) as run:
        pass
    res = build_report(ReportInput(store, EXP), "bare", tmp_path, log_run=False)
    assert any(run.run_id in p and "real/final_return_mean" in p for p in res.problems)
    assert f"run {run.run_id} (bare) lacks" in (res.folder / "report.md").read_text()
    assert main(["--uri", store, "--tag", "nokeyvalue", "--out", str(tmp_path)]) == 2


def test_single_arm_transfer_runs_are_not_reported_as_missing_the_other_arm():
    from sdrl_bench.report.tables import missing_metrics

    base = {"status": "FINISHED", "tags": {"sdrl.kind": "transfer", "mlflow.runName": "t"}}
    one_arm = {**base, "run_id": "a", "tags": {**base["tags"], "arms": "surrogate"},
               "metrics": {"surrogate/final_return_mean": 1.0}}
    both = {**base, "run_id": "b", "tags": {**base["tags"], "arms": "surrogate,real"},
            "metrics": {"surrogate/final_return_mean": 1.0}}
    assert missing_metrics([one_arm, both]) == ["run b (t) lacks real/final_return_mean"]


def _md_rows(md: str, section: str) -> list[list[str]]:
    """The table rows of a numbered report section, each cell as Markdown with the link it
    carries: read from ``report.html`` beside ``report.md`` when ``md`` is that file's text (the
    HTML links every number; the Markdown keeps plain numbers and links only the runs column)."""
    import html as html_mod
    import re

    if md.startswith("<") or "<table" in md:
        title = section.lstrip("# ").strip()
        part = md.split(f">{html_mod.escape(title)}", 1)[1].split("<h2", 1)[0]
        rows = []
        for tr in re.findall(r"<tr>(.*?)</tr>", part, flags=re.S):
            cells = re.findall(r"<td>(.*?)</td>", tr, flags=re.S)
            if not cells:
                continue
            out = []
            for c in cells:
                m = re.fullmatch(r"<a href='(.*)'>(.*)</a>", c, flags=re.S)
                out.append(f"[{html_mod.unescape(m.group(2))}]({html_mod.unescape(m.group(1))})" if m
                           else html_mod.unescape(c))
            rows.append(out)
        return rows
    part = md.split(section, 1)[1].split("\n## ", 1)[0]
    return [[c.strip() for c in line.strip("|").split(" | ")] for line in part.splitlines()
            if line.startswith("| ") and not line.startswith("| env |")]


def _link(cell: str) -> str | None:
    import re

    m = re.fullmatch(r"\[.*\]\((.*)\)", cell)
    return m.group(1) if m else None


def test_each_report_cell_links_to_runs_of_its_own_kind_and_seed_set(fits_store: str, tmp_path) -> None:
    """SINDy vs NN: the SINDy mean over two seeds opens the compare view of exactly those two
    SINDy runs, the NN number the NN run's page; a count of 0 links nowhere; the RL table's
    mean over seeds opens all its seeds."""
    from urllib.parse import unquote

    runs = tracking.find_runs(fits_store, EXP)
    ids = {(r["tags"]["library"], r["tags"]["seed"]): r["run_id"] for r in runs}
    sindy = {ids[("poly_trig", "0")], ids[("poly_trig", "1")]}
    nn = ids[("nn", "0")]
    transfers = [_transfer(fits_store, s, 90.0 + s, 80.0) for s in range(2)]
    res = build_report(ReportInput(fits_store, EXP, ui_url="http://ui:5000"), "links", tmp_path, log_run=False)
    md = (res.folder / "report.html").read_text()  # every number's link (the Markdown links the runs column only)
    rows = {(r[0], r[1]): r for r in _md_rows(md, "## 3. SINDy vs NN")}
    row = rows[("mountain_car", "mse/x")]  # env, quantity, SINDy, NN, ratio, SINDy fits, NN fits, runs
    s_url, n_url = unquote(_link(row[2])), unquote(_link(row[3]))
    assert s_url.startswith("http://ui:5000/#/compare-runs?runs=") and "workflowType=machine_learning" in s_url
    assert {i for i in sindy if i in s_url} == sindy and nn not in s_url
    assert n_url == f"http://ui:5000/#/experiments/{runs[0]['experiment_id']}/runs/{nn}?workflowType=machine_learning"
    assert row[5].startswith("[2](") and sindy <= set(unquote(_link(row[5])).replace('"', " ").split())
    assert _link(row[6]) == n_url
    rl = [r for r in _md_rows(md, "## 4. RL transfer") if r[:3] == ["mountain_car", "sindy", "surrogate"]][0]
    rl_url = unquote(_link(rl[9]))  # the final real return, a mean over both seeds
    assert all(t in rl_url for t in transfers) and "compare-runs" in rl_url
    assert rl[8] == "65,075" and _link(rl[8]) is None  # the paper's own figure links to none of our runs


def test_a_missing_kind_links_nowhere(store: str, tmp_path) -> None:
    _fit(store, "mountain_car", "poly_trig", "sindy", 0, {"x": 1e-16, "v": 3e-19})
    res = build_report(ReportInput(store, EXP, ui_url="http://ui:5000"), "nonn", tmp_path, log_run=False)
    row = {(r[0], r[1]): r for r in _md_rows((res.folder / "report.html").read_text(), "## 3. SINDy vs NN")}[("mountain_car", "mse/x")]
    assert row[3] == "not run" and row[6] == "0"  # "NN fits 0" used to link to a SINDy run
    assert _link(row[2]).endswith("?workflowType=machine_learning") and "/runs/" in _link(row[2])


def _dyna(uri: str, seed: int, surrogate: str, solved: bool, total: float, audit: float,
          params: dict | None = None) -> str:
    tags = {"sdrl.kind": "dyna", "env": "lunar_lander", "agent": "ppo_fast", "surrogate": surrogate, "seed": seed}
    with tracking.start_run(uri, EXP, f"dyna-s{seed}", tags) as run:
        if params:
            run.log_params(params)
        run.log_metrics({"solved": float(solved), "real_transitions_total": total, "real_transitions_model": total - 5000,
                         "real_steps_collect": total - 9000, "real_steps_evaluate": 4000, "real_steps_final": 5000,
                         "surrogate_steps": 600_000 + seed, "wall_seconds": 30.0 + seed,
                         "final_return_mean": 205.0 + seed, "audit_return_mean": audit})
    return run.run_id


def _real_arm(uri: str, seed: int, solved_at: float | None) -> str:
    tags = {"sdrl.kind": "transfer", "env": "lunar_lander", "agent": "ppo_fast", "surrogate": "sindy", "seed": seed,
            "arms": "real"}
    with tracking.start_run(uri, EXP, f"real-s{seed}", tags) as run:
        m = {"real/final_return_mean": 210.0 + seed, "real/eval_steps": 3000.0, "real/train_wall_seconds": 40.0}
        if solved_at is not None:
            m["real/solved_real_steps"] = solved_at
        run.log_metrics(m)
    return run.run_id


def test_dyna_loops_of_other_settings_get_rows_of_their_own(store: str) -> None:
    """Dyna runs of one pack and surrogate whose loops were set differently (rl.dyna.* overrides)
    are two rows, each naming the settings it differs in, not one average over both."""
    three = [_dyna(store, s, "sindy", True, 20_000 + s, 250.0, {"rl.dyna.max_rounds": 3}) for s in (0, 1, 2)]
    two = [_dyna(store, s, "sindy", False, 8_000 + s, 100.0, {"rl.dyna.max_rounds": 2}) for s in (0, 1)]
    dy = rt.dyna_table(tracking.find_runs(store, EXP))
    rows = dy[dy["method"].str.startswith("Dyna, sindy")].set_index("method")
    assert list(rows.index) == ["Dyna, sindy; max_rounds=3", "Dyna, sindy; max_rounds=2"]
    assert sorted(rows.loc["Dyna, sindy; max_rounds=3", "runs"]) == sorted(three)
    assert sorted(rows.loc["Dyna, sindy; max_rounds=2", "runs"]) == sorted(two)
    assert list(rows["n_solved"]) == [3, 0]


def test_dyna_rows_show_without_any_transfer_run_in_the_store(store: str, tmp_path) -> None:
    """Section 5 stands on the Dyna runs alone (an env with no transfer runs keeps its rows), in
    a report of the whole experiment and in one of a selection (--tag)."""
    for seed in (0, 1):
        _dyna(store, seed, "sindy", True, 20_000 + seed, 250.0)
    for tags in ({}, {"env": "lunar_lander"}):
        md = (build_report(ReportInput(store, EXP, tags=tags), f"dyna-{len(tags)}", tmp_path, log_run=False).folder
              / "report.md").read_text()
        assert "Dyna: not run" not in md and "| lunar_lander | Dyna, sindy | ppo_fast | 2/2 |" in md


def test_dyna_table_equals_the_runs_metrics_and_links_its_runs(store: str, tmp_path) -> None:
    """Section 5: solved counts, the median real transitions to solve (an unsolved seed counts
    as infinite) and their IQM or mean censored at what an unsolved seed spent, phase means and the audit IQM come from the Dyna runs' metrics; the real arm's
    cost is its training steps to the first solve plus its evaluations; every number links to
    exactly the runs of its row."""
    from urllib.parse import unquote

    sindy = [_dyna(store, 0, "sindy", True, 20_000, 230.0), _dyna(store, 1, "sindy", True, 30_000, 190.0),
             _dyna(store, 2, "sindy", False, 50_500, 150.0)]
    nn = [_dyna(store, 0, "nn", False, 50_100, 120.0)]
    real = [_real_arm(store, 0, 200_000.0), _real_arm(store, 1, 250_000.0)]
    runs = tracking.find_runs(store, EXP, missing_ok=False)
    dy = rt.dyna_table(runs).set_index(["env", "method"])
    row = dy.loc[("lunar_lander", "Dyna, sindy")]
    assert (row["n_seeds"], row["n_solved"]) == (3, 2)
    assert row["median_to_solve"] == 30_000  # median of 20k, 30k and infinity
    # censored: the unsolved seed counts what it spent (3 seeds: the mean, with its bootstrap CI)
    assert row["censored"][:3] == pytest.approx(rt.bootstrap_ci([20_000, 30_000, 50_500])[:3])
    assert row["censored"][0] == pytest.approx(np.mean([20_000, 30_000, 50_500]))
    metrics = _client_metrics(store, "tags.`sdrl.kind` = 'dyna' and tags.surrogate = 'sindy'")
    assert row["phase_a"] == pytest.approx(np.mean([m["real_steps_collect"] for m in metrics]))
    assert row["audit"][:3] == pytest.approx(rt.bootstrap_ci([m["audit_return_mean"] for m in metrics])[:3])
    assert math.isinf(dy.loc[("lunar_lander", "Dyna, nn"), "median_to_solve"])
    r = dy.loc[("lunar_lander", "real arm")]
    assert r["median_to_solve"] == np.median([203_000, 253_000]) and r["n_solved"] == 2

    res = build_report(ReportInput(store, EXP, ui_url="http://ui:5000"), "dyna", tmp_path, log_run=False)
    md = (res.folder / "report.html").read_text()
    rows = {r[1]: r for r in _md_rows(md, "## 5. Dyna")}
    assert rows["Dyna, sindy"][3].startswith("[2/3](") and rows["Dyna, sindy"][4].startswith("[30,000](")
    assert rows["Dyna, nn"][4].startswith("[not solved](")
    assert rows["real arm"][4].startswith("[228,000](")
    assert rows["Dyna, sindy"][5].startswith("[33,500 [")  # the censored mean, whole numbers
    for method, ids in (("Dyna, sindy", sindy), ("Dyna, nn", nn), ("real arm", real)):
        url = unquote(_link(rows[method][4]))
        assert {i for i in sindy + nn + real if i in url} == set(ids)


def test_another_agents_real_arm_that_stopped_at_the_threshold_is_a_row_and_the_ratio_uses_the_best(store: str, tmp_path) -> None:
    """A real-only arm of another agent (SB3's default PPO) stopped by ``rl.stop_when_solved`` is
    a row of its own, one per pack; one that ran a fixed budget is not (its cost to solve is unknown); every
    row's ratio divides its median real transitions to solve by the best real arm's; section 6
    draws every arm against its real steps, all counted."""
    d = _dyna(store, 0, "sindy", True, 20_000, 230.0)
    tracking.Run(store, d).log_text("real_transitions,return_mean,return_std\n9000,300,0\n20000,750,0\n", "curves/dyna.csv")
    _real_arm(store, 0, 400_000.0)
    stopped = []
    for seed, solved_at in ((0, 90_000.0), (1, 110_000.0)):
        rid = _real_arm(store, seed, solved_at)
        tracking.Run(store, rid).set_tags({"agent": "ppo", "sdrl.experiment": "real_pack"})
        tracking.Run(store, rid).log_params({"rl.stop_when_solved": "True"})
        tracking.Run(store, rid).log_text("train_steps,return_mean,return_std\n0,0,0\n50000,400,0\n100000,720,0\n",
                                          "curves/real.csv")
        stopped.append(rid)
    fixed = _real_arm(store, 2, None)
    tracking.Run(store, fixed).set_tags({"agent": "sac"})
    other_pack = _real_arm(store, 0, 300_000.0)  # the same agent in another pack: an arm of its own
    tracking.Run(store, other_pack).set_tags({"agent": "ppo", "sdrl.experiment": "other_pack"})
    tracking.Run(store, other_pack).log_params({"rl.stop_when_solved": "True"})
    confirmed = _real_arm(store, 0, 150_000.0)  # the same pack, its stops confirmed: another procedure, another row
    tracking.Run(store, confirmed).set_tags({"agent": "ppo", "sdrl.experiment": "real_pack"})
    tracking.Run(store, confirmed).log_params({"rl.stop_when_solved": "True", "rl.confirm_episodes": "20"})
    dy = rt.dyna_table(tracking.find_runs(store, EXP))
    assert list(dy[dy["agent"] == "ppo"]["method"]) == ["real arm, other_pack", "real arm, real_pack",
                                                        "real arm, real_pack, confirmed on 20"]
    assert dy[dy["method"] == "real arm, other_pack"].iloc[0]["runs"] == [other_pack]
    assert dy[dy["method"] == "real arm, real_pack, confirmed on 20"].iloc[0]["runs"] == [confirmed]
    real = dy[dy["method"].isin(["real arm", "real arm, real_pack"])].set_index("agent")
    assert sorted(real.index) == ["ppo", "ppo_fast"] and sorted(real.loc["ppo", "runs"]) == sorted(stopped)
    best = np.median([93_000, 113_000])  # training steps to solve plus the 3,000 evaluation steps
    assert real.loc["ppo", "median_to_solve"] == best and real.loc["ppo", "ratio_to_best_real"] == 1.0
    assert real.loc["ppo_fast", "ratio_to_best_real"] == pytest.approx(403_000 / best)
    sindy = dy[dy["method"] == "Dyna, sindy"].iloc[0]
    assert sindy["ratio_to_best_real"] == pytest.approx(20_000 / best)
    res = build_report(ReportInput(store, EXP), "ratio", tmp_path, log_run=False)
    rows = {(r[1], r[2]): r for r in _md_rows((res.folder / "report.md").read_text(), "## 5. Dyna")}
    assert rows[("Dyna, sindy", "ppo_fast")][-2] == f"{20_000 / best:.3g}"
    fig = res.folder / "figures" / "real_steps_lunar_lander.png"
    assert fig.stat().st_size > 1000 and "figures/real_steps_lunar_lander.png" in (res.folder / "report.md").read_text()
    # a real arm's x: its training steps plus its evaluations so far (3,000 evaluation steps over 3 points)
    from sdrl_bench.report.figures import _all_counted

    run = next(r for r in tracking.find_runs(store, EXP) if r["run_id"] == stopped[0])
    assert list(_all_counted(store, run, tmp_path / "dl")["real_steps"]) == [1000.0, 52_000.0, 103_000.0]


def test_the_real_arm_row_holds_each_dyna_seeds_own_real_arm(store: str) -> None:
    """Seed 0's Dyna run was plotted beside its real arm (``dyna.real_arm_run``); seed 1's real
    arm ran after it (found by ``dyna.real_arm_key``); seed 2's Dyna run predates both tags (its
    seed's real arm); seed 3's real arm belongs to no Dyna run and is not in the row."""
    arms = {s: _real_arm(store, s, 200_000.0 + s) for s in range(4)}
    tags = {0: {"dyna.real_arm_run": arms[0]}, 1: {"dyna.real_arm_key": "key-1"}, 2: {}}
    tracking.Run(store, arms[1]).set_tags({"real_arm_key": "key-1"})
    for seed, extra in tags.items():
        tracking.Run(store, _dyna(store, seed, "sindy", True, 20_000, 230.0)).set_tags(extra)
    dy = rt.dyna_table(tracking.find_runs(store, EXP)).set_index(["env", "method"])
    row = dy.loc[("lunar_lander", "real arm")]
    assert sorted(row["runs"]) == sorted(arms[s] for s in (0, 1, 2)) and row["n_seeds"] == 3


def test_a_seed_run_twice_counts_once_the_newest(store: str) -> None:
    _dyna(store, 0, "sindy", False, 51_000, 180.0)
    newer = _dyna(store, 0, "sindy", True, 20_000, 230.0)
    other = _dyna(store, 1, "sindy", True, 30_000, 220.0)
    row = rt.dyna_table(tracking.find_runs(store, EXP)).set_index(["env", "method"]).loc[("lunar_lander", "Dyna, sindy")]
    assert row["n_seeds"] == 2 and row["n_solved"] == 2 and sorted(row["runs"]) == sorted([newer, other])


def test_another_surrogate_kind_gets_rows_of_its_own_and_absent_ones_none(store: str) -> None:
    """A probabilistic-ensemble Dyna run (surrogate=pe) is a row beside SINDy's; the NN, not run,
    keeps its "not run" row; a kind nobody ran gets none."""
    _dyna(store, 0, "sindy", True, 20_000, 230.0)
    pe = _dyna(store, 0, "pe", True, 25_000, 240.0)
    dy = rt.dyna_table(tracking.find_runs(store, EXP)).set_index(["env", "method"])
    assert list(dy.loc["lunar_lander"].index) == ["Dyna, sindy", "Dyna, nn", "Dyna, pe", "real arm"]
    row = dy.loc[("lunar_lander", "Dyna, pe")]
    assert row["runs"] == [pe] and row["median_to_solve"] == 25_000 and row["n_solved"] == 1
    assert dy.loc[("lunar_lander", "Dyna, nn"), "n_seeds"] == 0


def test_report_exports_every_run_it_read_and_names_its_commit(fits_store: str, tmp_path) -> None:
    """runs.csv beside the report: one row per run read, its tags, params and metrics as the
    store holds them; the report names the commit it was made at."""
    import pandas as pd

    ids = [_transfer(fits_store, s, 90.0 + s, 80.0) for s in range(2)]
    tracking.Run(fits_store, ids[0]).log_params({"agent.name": "sac"})
    res = build_report(ReportInput(fits_store, EXP), "export", tmp_path, log_run=False)
    df = pd.read_csv(res.folder / "runs.csv")
    runs = tracking.find_runs(fits_store, EXP)
    assert sorted(df["run_id"]) == sorted(r["run_id"] for r in runs) and len(df) == res.n_runs == 6
    by_id = df.set_index("run_id")
    for r in runs:
        for k, v in r["metrics"].items():
            assert by_id.loc[r["run_id"], f"metric.{k}"] == pytest.approx(v, rel=1e-12)
        assert by_id.loc[r["run_id"], "tag.sdrl.kind"] == r["tags"]["sdrl.kind"]
    assert by_id.loc[ids[0], "param.agent.name"] == "sac" and pd.isna(by_id.loc[ids[1], "param.agent.name"])
    md = (res.folder / "report.md").read_text()
    tags = tracking.standard_tags()
    made_by = f"by sdrl-bench {tags['sdrl.package_version']}"
    assert (made_by + ("." if tags["git_commit"] == "unknown" else f" at commit `{tags['git_commit']}`.")) in md
    assert "[runs.csv](runs.csv)" in md


def _ll_fit(uri: str, library: str, surrogate: str, seed: int, kind: str = "fit", optimizer: str = "stlsq",
            params: dict | None = None) -> str:
    """A LunarLander fit (or a transfer run's fit) with the fidelity metrics a real one logs:
    one-step and 50-step MSE per state, the flight regime's noise-floor ratio, divergence."""
    states = ("x", "y", "vx", "vy", "angle", "angvel")
    tags = {"sdrl.kind": kind, "env": "lunar_lander", "library": library, "surrogate": surrogate, "seed": seed,
            "collector": "expert", "optimizer": optimizer, "test_set": "lunar_lander-heldout-v1", "agent": "ppo",
            "arms": "surrogate,real",
            "fit_regime": "flight" if library == "lunar_lander_flight" else "all"}
    rng = np.random.default_rng(seed + (100 if surrogate == "nn" else 0))
    m: dict[str, float] = {}
    for i, s in enumerate(states):
        m[f"mse/{s}"] = float(10.0 ** (-8 + i) * rng.uniform(1, 3))
        m[f"mse_norm/{s}"] = float(rng.uniform(0, 1e-2))
        m[f"corr/{s}"] = float(1 - rng.uniform(0, 1e-3))
        m[f"rollout50_mse/{s}"] = float(10.0 ** (-5 + i) * rng.uniform(1, 3))
        m[f"floor_ratio_flight/{s}"] = float(rng.uniform(1, 40))
        m[f"floor_ratio_contact/{s}"] = float(rng.uniform(100, 400))
    m.update({"mse/mean": float(np.mean([m[f"mse/{s}"] for s in states])), "mse_norm/mean": 1e-3,
              "rollout50/diverged_fraction": float(rng.uniform(0, 0.2)), "fit_wall_seconds": 0.1 + seed,
              "fit_cpu_seconds": 0.05, "n_parameters": 40.0 + seed if surrogate == "sindy" else 1222.0})
    if kind == "transfer":
        m.update({"surrogate/final_return_mean": 150.0 + 10 * seed, "real/final_return_mean": 260.0})
    with tracking.start_run(uri, EXP, f"{kind}-ll-{library}-{surrogate}-s{seed}", tags) as run:
        run.log_metrics(m)
        run.log_params({"n_transitions": 1000, **(params or {})})
    return run.run_id


def test_fits_of_different_setups_get_rows_of_their_own(store: str) -> None:
    """A sweep over optimizers (or collectors, or numbers of transitions) on the same seeds: the
    ablation has a row per setup, each over its own newest fit per seed, the setup with the most
    seeds first; the fidelity table stands on one setup, never the newest fit of each seed across
    setups."""
    stlsq = [_ll_fit(store, "polynomial", "sindy", s) for s in (0, 1, 2)]
    ensemble = [_ll_fit(store, "polynomial", "sindy", s, optimizer="ensemble") for s in (0, 1)]
    # the paper pack's library (the fidelity table's): three seeds of stlsq, and two seeds of the
    # ensemble fitted three times each (more runs, fewer seeds), the newest last
    flight = [_ll_fit(store, "lunar_lander_flight", "sindy", s) for s in (0, 1, 2)]
    for _ in range(3):
        flight_ens = [_ll_fit(store, "lunar_lander_flight", "sindy", s, optimizer="ensemble") for s in (0, 1)]
    runs = tracking.find_runs(store, EXP)
    abl = rt.ablation_table(runs)
    poly = abl[(abl["env"] == "lunar_lander") & (abl["library"] == "polynomial")]
    assert list(poly["setup"]) == [SETUP_CELL, "ensemble, expert, 1000"]
    assert list(poly["n_fits"]) == [3, 2]
    assert [sorted(r) for r in poly["runs"]] == [sorted(stlsq), sorted(ensemble)]
    by_id = {r["run_id"]: r["metrics"] for r in runs}
    assert poly.iloc[1]["mse_mean"] == pytest.approx(np.mean([by_id[i]["mse/mean"] for i in ensemble]))
    flight_rows = abl[(abl["env"] == "lunar_lander") & (abl["library"] == "lunar_lander_flight")]
    assert list(flight_rows["setup"]) == [SETUP_CELL, "ensemble, expert, 1000"]  # by seeds, not by runs
    assert [sorted(r) for r in flight_rows["runs"]] == [sorted(flight), sorted(flight_ens)]
    assert set(abl[abl["library"] == "rational"]["n_fits"]) == {0}  # a paper library not run: one row
    fid = rt.fidelity_table(runs)
    fid = fid[fid["env"] == "lunar_lander"]
    assert set(fid["setup"]) == {SETUP_CELL} and all(sorted(r) == sorted(flight) for r in fid["runs"])


def test_fits_of_other_hyperparameters_get_rows_of_their_own_and_the_pack_optimizer_leads(store: str) -> None:
    """A sweep over thresholds on the same seeds: a row per threshold, each naming it (the newest
    fit of a seed once dropped the other threshold's); on the pack's library, an optimizer the
    pack does not use (sr3, which sorts first) never stands for the env in the fidelity table."""
    coarse = [_ll_fit(store, "polynomial", "sindy", s, params={"optimizer.threshold": 0.03}) for s in (0, 1)]
    fine = [_ll_fit(store, "polynomial", "sindy", s, params={"optimizer.threshold": 0.0003}) for s in (0, 1)]
    stlsq = [_ll_fit(store, "lunar_lander_flight", "sindy", s) for s in (0, 1)]
    sr3 = [_ll_fit(store, "lunar_lander_flight", "sindy", s, optimizer="sr3") for s in (0, 1)]
    runs = tracking.find_runs(store, EXP)
    abl = rt.ablation_table(runs)
    poly = abl[(abl["env"] == "lunar_lander") & (abl["library"] == "polynomial")]
    assert sorted(poly["setup"]) == [f"{SETUP_CELL}; optimizer.threshold=0.0003", f"{SETUP_CELL}; optimizer.threshold=0.03"]
    by_setup = dict(zip(poly["setup"], poly["runs"], strict=True))
    assert sorted(by_setup[f"{SETUP_CELL}; optimizer.threshold=0.03"]) == sorted(coarse)
    assert sorted(by_setup[f"{SETUP_CELL}; optimizer.threshold=0.0003"]) == sorted(fine)
    fid = rt.fidelity_table(runs)
    fid = fid[fid["env"] == "lunar_lander"]
    assert all(sorted(r) == sorted(stlsq) for r in fid["runs"]) and not set(sr3) & set(fid["runs"].iloc[0])
    vs = rt.sindy_vs_nn_table(runs)
    assert sorted(vs[vs["env"] == "lunar_lander"]["runs_sindy"].iloc[0]) == sorted(stlsq)


def test_five_seed_fidelity_tables_report_iqm_cis_rollouts_and_noise_floor_ratios(store: str, tmp_path) -> None:
    """Five seeds: the fidelity table's one-step and 50-step cells are the IQM and bootstrap CI
    of the runs' own metrics, the noise-floor ratio is the flight regime's; the ablation and
    SINDy-vs-NN tables the same; every number in the report links to exactly its row's runs."""
    from urllib.parse import unquote

    flight = [_ll_fit(store, "lunar_lander_flight", "sindy", s, kind="transfer") for s in range(5)]
    poly = [_ll_fit(store, "polynomial", "sindy", s) for s in range(5)]
    nn = [_ll_fit(store, "nn", "nn", s) for s in range(5)]
    runs = tracking.find_runs(store, EXP, missing_ok=False)
    by_id = {r["run_id"]: r["metrics"] for r in runs}
    fid = rt.fidelity_table(runs).set_index(["env", "state"])
    for state in ("x", "vy", "angvel"):
        row = fid.loc[("lunar_lander", state)]
        assert sorted(row["runs"]) == sorted(flight) and row["library"] == "lunar_lander_flight"
        for col, key in (("mse", f"mse/{state}"), ("rollout", f"rollout50_mse/{state}"),
                         ("floor_ratio", f"floor_ratio_flight/{state}")):
            ref = rt.bootstrap_ci([by_id[i][key] for i in flight])
            assert ref[3] == "IQM" and (row[col], row[f"{col}_lo"], row[f"{col}_hi"]) == pytest.approx(ref[:3], rel=1e-12)
        assert row["floor_regime"] == "flight" and row["statistic"] == "IQM"
        assert row["diverged"] == pytest.approx(np.mean([by_id[i]["rollout50/diverged_fraction"] for i in flight]))
    abl = rt.ablation_table(runs).set_index(["env", "library"]).loc[("lunar_lander", "polynomial")]
    assert abl["mse_mean"] == pytest.approx(rt.bootstrap_ci([by_id[i]["mse/mean"] for i in poly])[0], rel=1e-12)
    roll = [np.mean([by_id[i][f"rollout50_mse/{s}"] for s in ("x", "y", "vx", "vy", "angle", "angvel")]) for i in poly]
    assert abl["rollout_mean"] == pytest.approx(rt.iqm(np.array(roll)), rel=1e-12)
    assert abl["n_terms"] == pytest.approx(42.0) and abl["n_fits"] == 5
    vs = rt.sindy_vs_nn_table(runs).set_index(["env", "quantity"]).loc[("lunar_lander", "rollout50_mse/vx")]
    assert sorted(vs["runs_sindy"]) == sorted(poly) and sorted(vs["runs_nn"]) == sorted(nn)
    ref_s = rt.bootstrap_ci([by_id[i]["rollout50_mse/vx"] for i in poly])
    ref_n = rt.bootstrap_ci([by_id[i]["rollout50_mse/vx"] for i in nn])
    assert (vs["sindy"], vs["sindy_lo"], vs["sindy_hi"]) == pytest.approx(ref_s[:3], rel=1e-12)
    assert vs["sindy_over_nn"] == pytest.approx(ref_s[0] / ref_n[0])

    res = build_report(ReportInput(store, EXP, ui_url="http://ui:5000"), "five", tmp_path, log_run=False)
    md = (res.folder / "report.md").read_text()
    plain = {r[1]: r for r in _md_rows(md, "## 1. Fidelity per state")}["angvel"]  # Markdown: plain numbers
    assert not plain[6].startswith("[") and plain[-1].startswith("[")  # only the runs column links
    assert plain[4] == SETUP_CELL  # the fits' one setup: optimizer, collector, real transitions
    row = {r[1]: r for r in _md_rows((res.folder / "report.html").read_text(), "## 1. Fidelity per state")}["angvel"]
    ref = rt.bootstrap_ci([by_id[i]["mse/angvel"] for i in flight])
    assert row[6].startswith(f"[{ref[0]:.3e} [{ref[1]:.3e}, {ref[2]:.3e}]](")
    assert row[10] == "flight"
    for cell in row[6:10] + row[11:13]:
        assert {i for i in flight + poly + nn if i in unquote(_link(cell))} == set(flight)
    vs_row = {r[1]: r for r in _md_rows((res.folder / "report.html").read_text(), "## 3. SINDy vs NN")}["rollout50_mse/vx"]
    assert {i for i in flight + poly + nn if i in unquote(_link(vs_row[2]))} == set(poly)
    assert {i for i in flight + poly + nn if i in unquote(_link(vs_row[3]))} == set(nn)
    for heading in ("## 1.", "## 2.", "## 3.", "## 4."):  # every table is followed by its differences paragraph
        section = md.split(heading, 1)[1].split("\n## ", 1)[0]
        assert "Differences explained:" in section


def test_report_states_how_it_was_made_from_the_rebuild_record(fits_store: str, tmp_path) -> None:
    import json

    record = {"command": "python scripts/reproduce.py --jobs 2", "seeds": [0, 1, 2, 3, 4], "jobs": 2,
              "machine": "2 cores", "stages": {
                  "fits": {"commands": [["-m", "env=mountain_car", "seed=0,1,2,3,4"]], "status": "finished",
                           "wall_seconds": 120.0, "cpu_seconds": 230.0, "finished_at": "2026-11-24 14:00 UTC"},
                  "transfer": {"commands": [["-m", "experiment=paper_mountain_car", "seed=0,1,2,3,4"]],
                               "status": "finished", "wall_seconds": 3000.0, "cpu_seconds": 5900.0,
                               "finished_at": "2026-11-24 15:00 UTC"}}}
    path = tmp_path / "rebuild.json"
    path.write_text(json.dumps(record))
    assert main(["--uri", fits_store, "--name", "made", "--out", str(tmp_path), "--no-log", "--provenance", str(path)]) == 0
    md = (tmp_path / "made" / "report.md").read_text()
    assert "`python scripts/reproduce.py --jobs 2`" in md and "52 min wall, 102 min CPU in all" in md
    rows = {r[0]: r for r in _md_rows(md, "## How this report was made")}
    assert rows["transfer"][2] == "3,000" and rows["fits"][5] == "sdrl-bench -m env=mountain_car seed=0,1,2,3,4"
    path.write_text("not json")
    assert main(["--uri", fits_store, "--name", "bad", "--out", str(tmp_path), "--no-log", "--provenance", str(path)]) == 2
    assert not (tmp_path / "bad").exists()


def test_fit_tables_take_one_fit_per_seed_from_the_paper_packs_and_skip_real_only_runs(store: str) -> None:
    """Table 1 stands on the paper pack's transfer runs (agent ``ppo``), not on a fast recipe's
    runs that fit the same data again, nor on real-arm-only runs, which fit nothing; a seed
    fitted twice counts once (the newest); the Dyna real arm is the run each Dyna run was
    plotted beside, not every real arm of the agent."""
    paper = [_ll_fit(store, "lunar_lander_flight", "sindy", s, kind="transfer") for s in range(3)]
    runs_fast = []
    for s in range(3):  # the fast recipe's transfer runs: same fits, another agent
        with tracking.start_run(store, EXP, f"fast-s{s}", {"sdrl.kind": "transfer", "env": "lunar_lander", "agent": "ppo_fast",
                                                           "surrogate": "sindy", "library": "lunar_lander_flight", "seed": s,
                                                           "arms": "surrogate,real"}) as run:
            run.log_metrics({"mse/x": 1.0, "mse/mean": 1.0, "surrogate/final_return_mean": 1.0,
                             "real/final_return_mean": 230.0 + s, "real/solved_real_steps": 100_000.0 * (s + 1)})
        runs_fast.append(run.run_id)
    with tracking.start_run(store, EXP, "real-only", {"sdrl.kind": "transfer", "env": "lunar_lander", "agent": "ppo_fast",
                                                     "surrogate": "sindy", "seed": 7, "arms": "real"}) as run:
        run.log_metrics({"real/final_return_mean": 100.0, "real/solved_real_steps": 900_000.0})
    real_only = run.run_id
    again = _ll_fit(store, "polynomial", "sindy", 0)
    polys = [_ll_fit(store, "polynomial", "sindy", s) for s in range(2)]  # seed 0 fitted again, newest wins
    runs = tracking.find_runs(store, EXP, missing_ok=False)
    records = rt.fit_records(runs)
    assert real_only not in {r["run_id"] for r in records}
    fid = rt.fidelity_table(runs).set_index(["env", "state"]).loc[("lunar_lander", "x")]
    assert sorted(fid["runs"]) == sorted(paper) and fid["n_fits"] == 3
    abl = rt.ablation_table(runs).set_index(["env", "library"]).loc[("lunar_lander", "polynomial")]
    assert abl["n_fits"] == 2 and again not in abl["runs"] and sorted(abl["runs"]) == sorted(polys)
    dyna = _dyna(store, 0, "sindy", True, 20_000, 230.0)
    tracking.Run(store, dyna).set_tags({"dyna.real_arm_run": runs_fast[0]})
    dy = rt.dyna_table(tracking.find_runs(store, EXP)).set_index(["env", "method"]).loc[("lunar_lander", "real arm")]
    assert dy["runs"] == [runs_fast[0]] and dy["median_to_solve"] == 100_000.0


def test_a_studys_best_refit_is_not_a_fit_of_the_tables(fits_store: str) -> None:
    """sdrl-bench-search logs its best trial's refit as a fit run (no library or seed tag, the
    study's name): the study's section reports it; the fit tables do not pool it."""
    with tracking.start_run(fits_store, EXP, "mountain_car-tpe-s0-best-refit",
                            {"sdrl.kind": "fit", "env": "mountain_car", "sdrl.study": "mountain_car-tpe-s0",
                             "sdrl.role": "best-refit", "test_set": "mountain_car-heldout-v1"}) as run:
        run.log_metrics({"mse/x": 5.0, "mse/v": 5.0, "mse/mean": 5.0})
    runs = tracking.find_runs(fits_store, EXP)
    assert run.run_id not in {r["run_id"] for r in rt.fit_records(runs)}
    assert all(run.run_id not in ids for ids in rt.ablation_table(runs)["runs"])
    assert rt.fidelity_table(runs).set_index(["env", "state"]).loc[("mountain_car", "x"), "mse"] < 1


@pytest.mark.parametrize("stop,budget,confirm", [(True, 96, 0), (False, 128, 0), (True, 96, 3)])
def test_what_the_runs_did_is_read_from_the_runs(store: str, tmp_path, stop: bool, budget: int, confirm: int) -> None:
    """The transfer section's sentence about what the runs did (budgets, stop rule, evaluations,
    the model's data, the machine's load) comes from the runs' own params and metrics: change the
    pack and the sentence changes."""
    from sdrl_bench.cli.build import build_fit_job
    from sdrl_bench.cli.train import run_train

    cfg = compose_cfg("experiment=quick_mountain_car", f"tracking.uri={store}", f"rl.surrogate_steps={budget}",
                      f"rl.real_steps={budget}", "rl.eval_every=64", "rl.eval_episodes=1", "rl.final_episodes=2",
                      f"rl.stop_when_solved={str(stop).lower()}", "collector.epsilon=0.3", "n_transitions=60",
                      "agent.algo.train_freq=16", "agent.algo.gradient_steps=1", "agent.algo.batch_size=32",
                      "agent.algo.policy_kwargs.net_arch=[16]", "progress_bar=false", f"rl.confirm_episodes={confirm}")
    run_train(cfg, build_fit_job(cfg), None)
    res = build_report(ReportInput(store, EXP), "t", tmp_path)
    md = (res.folder / "report.md").read_text()
    rule = "stopped at the first one at the threshold" if stop else "the budgets run out (no stop)"
    rule += f" that {confirm} fresh real episodes confirm" if confirm else ""
    assert (f"mountain_car, sac (1 seed): budgets {budget:,} surrogate / {budget:,} real steps, a real evaluation "
            f"of 1 episodes every 64 steps, {rule}, judged on 2 final real episodes; the surrogate's model from 60 "
            "real transitions (heuristic collector, eps 0.3); load average when the runs started") in md


def test_the_machines_sentence_counts_runs_by_cpu_and_names_runs_without_the_tag() -> None:
    from sdrl_bench.report.build import _machines_sentence

    a = {"sdrl.cpu": "AMD EPYC (family 25, model 17)", "sdrl.cpu_vectors": "sse4_2 avx avx2 fma"}
    b = {"sdrl.cpu": "Xeon (family 6, model 143)", "sdrl.cpu_vectors": "sse4_2 avx avx2 fma avx512f amx_tile"}
    text = _machines_sentence([{"tags": a}, {"tags": b}, {"tags": a}, {"tags": {}}])
    assert text.startswith("Machines: AMD EPYC (family 25, model 17) [sse4_2 avx avx2 fma]: 2 runs; "
                           "Xeon (family 6, model 143) [sse4_2 avx avx2 fma avx512f amx_tile]: 1 run; "
                           "not recorded (runs from before the tag): 1 run.")
