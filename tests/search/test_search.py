"""Search: space validation, tracked studies and their exported config, grid vs TPE, the Pareto
mode, refinement, resuming after SIGKILL, parallel workers (joblib, submitit), an mlflow server.
MountainCar's exact law from 100 TPE trials runs under ``-m slow``."""

from __future__ import annotations

import itertools
import json
import os
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import optuna
import pytest
from mlflow.tracking import MlflowClient

from sdrl_bench import ConfigError, seeds, tracking
from sdrl_bench.cli.build import build_fit_job, compose
from sdrl_bench.cli.search import make_build_job, run_refine, run_search
from sdrl_bench.data import collect, heuristic_policy, held_out_test_set
from sdrl_bench.pipeline import fit_dynamics
from sdrl_bench.search.study import counted, evaluate_params
from sdrl_bench.search.summary import comparison_table, load_summaries
from sdrl_bench.search.space import parse_space

ROOT = Path(__file__).resolve().parents[2]
EXPERIMENT = "sdrl-bench-search"
EXACT = {"x": {"x", "v", "u", "cos(3 x)"}, "v": {"v", "u", "cos(3 x)"}}


@pytest.fixture(scope="module")
def uri(tmp_path_factory) -> str:
    """One MLflow store for the module (creating one costs seconds), MLFLOW_TRACKING_URI unset."""
    with pytest.MonkeyPatch.context() as mp:
        mp.delenv("MLFLOW_TRACKING_URI", raising=False)
        u = f"sqlite:///{tmp_path_factory.mktemp('store') / 'mlflow.db'}"
        tracking.ensure_experiment(u, EXPERIMENT)
        yield u


def search_cfg(tmp: Path, uri: str, *overrides: str):
    """The ``sdrl-bench-search`` config for a temp storage, small folds, quiet."""
    return compose([f"study.storage='sqlite:///{tmp}/optuna.db'", f"study.export_dir='{tmp}/export'",
                    f"tracking.uri='{uri}'", "search.k_folds=3", *overrides],
                   config_name="search_app", return_hydra_config=True)


def children(uri: str, parent: str) -> list[dict]:
    return tracking.find_runs(uri, EXPERIMENT, f"tags.`mlflow.parentRunId` = '{parent}'")


def exact_law(equations: str) -> bool:
    terms = {}
    for line in equations.strip().splitlines():
        lhs, rhs = line.split(" = ")
        terms[lhs.split("[")[0]] = {t.split(" ", 1)[1] if " " in t else "1" for t in rhs.replace(" -", " +").split(" +") if t}
    return terms == EXACT


# ---------------------------------------------------------------------- bad input
@pytest.mark.parametrize("space, match", [
    ({"threshold": {"type": "float", "low": 0.1, "high": 0.01}}, r"search.space.threshold: low \(0.1\) must be below high \(0.01\)"),
    ({"poly_degree": {"type": "int", "low": 2, "high": 2}}, r"search.space.poly_degree: low \(2\) must be below high"),
    ({"alpha": {"type": "float", "low": 0.0, "high": 1.0, "log": True}}, r"search.space.alpha: a log scale needs positive bounds"),
    ({"alpha": {"type": "float", "low": 0.1, "high": 1.0, "log": "maybe"}},
     r"search.space.alpha.log: true or false is required, got 'maybe'"),  # was a log scale
    ({"gamma": {"type": "float", "low": 0.1, "high": 1.0}}, r"search.space.gamma: unknown parameter 'gamma'; known parameters: threshold"),
    ({"poly_degree": {"type": "int", "low": 1.5, "high": 3}}, r"search.space.poly_degree.low: an integer is required"),
    ({"library": {"type": "categorical", "choices": []}}, r"search.space.library.choices: .*non-empty"),
    ({"threshold": {"type": "float", "low": 1e-3, "high": 1e-1, "grid": [1e-4]}}, r"search.space.threshold.grid: values \[0.0001\]"),
    ({"threshold": {"type": "float", "lo": 1e-3, "high": 1e-1}}, r"search.space.threshold: unknown fields \['lo'\]"),
])
def test_bad_search_space_is_a_one_line_config_error(space, match):
    with pytest.raises(ConfigError, match=match) as err:
        parse_space(space)
    assert "\n" not in str(err.value)


def test_a_value_is_sampled_only_under_the_group_choices_whose_configs_interpolate_it():
    """Conditions come from the group configs' interpolations: a value read by some options of a
    group and not others is conditional on them (either of two groups reading it suffices), one
    read by every option of the study is not, and one no option reads is refused."""
    from sdrl_bench.search.space import conditions, reads, suggest

    assert reads({"opt": {"alpha": "${env.sindy.alpha}"}}, "env.sindy.alpha")
    assert reads(["${oc.select:env.sindy.alpha,0.1}"], "env.sindy.alpha")  # inside a resolver's arguments
    assert reads("${env.sindy}", "env.sindy.alpha")  # a node above it
    assert not reads("${env.sindy.alpha_max}", "env.sindy.alpha") and not reads("env.sindy.alpha", "env.sindy.alpha")
    space = parse_space({"optimizer": {"type": "categorical", "choices": ["a", "b", "c"]},
                         "library": {"type": "categorical", "choices": ["p", "q"]},
                         "alpha": {"type": "float", "low": 1e-3, "high": 1.0},
                         "threshold": {"type": "float", "low": 1e-3, "high": 1.0}})
    groups = {"optimizer": {"a": {"alpha": "${env.sindy.alpha}", "threshold": "${env.sindy.threshold}"},
                            "b": {"threshold": "${env.sindy.threshold}"}, "c": {"threshold": 0.1}},
              "library": {"p": {"x": "${env.sindy.alpha}"}, "q": {}}}
    when = conditions(space, groups)
    assert when == {"alpha": (("optimizer", frozenset({"a"})), ("library", frozenset({"p"}))),
                    "threshold": (("optimizer", frozenset({"a", "b"})),)}
    seen = set()
    for n in range(40):
        trial = optuna.trial.FixedTrial({"optimizer": "abc"[n % 3], "library": "pq"[n // 3 % 2], "alpha": 0.5, "threshold": 0.5})
        params = suggest(trial, space, when)
        assert list(params) == [k for k in ("optimizer", "library", "alpha", "threshold") if k in params]  # the space's order
        assert ("alpha" in params) == (params["optimizer"] == "a" or params["library"] == "p")
        assert ("threshold" in params) == (params["optimizer"] != "c")
        seen.add(tuple(params))
    assert len(seen) == 4
    # the groups are drawn first whatever the space's order, and the params come back in that order
    late = parse_space({"alpha": {"type": "float", "low": 1e-3, "high": 1.0},
                        "optimizer": {"type": "categorical", "choices": ["a", "b"]}})
    for opt in "ab":
        params = suggest(optuna.trial.FixedTrial({"optimizer": opt, "alpha": 0.5}), late, {"alpha": (("optimizer", frozenset("a")),)})
        assert list(params) == (["alpha", "optimizer"] if opt == "a" else ["optimizer"])
    with pytest.raises(ConfigError, match=r"^search.space.alpha: no config this study fits interpolates env.sindy.alpha "
                                          r"\(optimizer=b,c, library=q as composed here\)"):
        conditions(space, {"optimizer": {k: groups["optimizer"][k] for k in "bc"}, "library": {"q": {}}})


def test_bad_storage_choice_or_mode_fail_before_any_trial(tmp_path, uri):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    cases = [
        ("study.storage='postgresql://me:secret@127.0.0.1:1/optuna'",
         r"^study.storage: cannot open postgresql://me:\*\*\*@127.0.0.1:1/optuna \("),
        (f"study.storage='sqlite:///{blocker}/optuna.db'", rf"^study.storage: cannot open sqlite:///{blocker}/optuna.db"),
        ("search.space.library.choices=[polynomial,nope]", r"^search.space.library: unknown choice 'nope' \(the library group has \[.*'poly_trig', 'polynomial'"),
        ("search.pruner=median", r"^search.pruner: pruning needs a single objective"),
    ]
    for i, (override, match) in enumerate(cases):
        extra = ["search=pareto"] if "pruner" in override else []
        cfg = search_cfg(tmp_path, uri, *extra, override, f"study.name=bad{i}")
        with pytest.raises(ConfigError, match=match) as err:
            run_search(cfg, quiet=True)
        assert "\n" not in str(err.value) and "secret" not in str(err.value)
        assert tracking.find_runs(uri, EXPERIMENT, f"tags.`sdrl.study` = 'bad{i}'") == []


def test_resuming_with_a_different_space_is_refused_before_a_trial(tmp_path, uri):
    run_search(search_cfg(tmp_path, uri, "study.name=same", "search.n_trials=2", "study.final_score=false"), quiet=True)
    cfg = search_cfg(tmp_path, uri, "study.name=same", "search.n_trials=4", "search.space.threshold.low=1e-5")
    with pytest.raises(ConfigError, match=r"^study.name: study 'same' in sqlite:///.* was created with a different "
                                          r"setup \(search space: threshold.low 1e-06 -> 1e-05\); use another study.name"):
        run_search(cfg, quiet=True)
    study = optuna.load_study(study_name="same", storage=f"sqlite:///{tmp_path}/optuna.db")
    assert len(study.trials) == 2


# ---------------------------------------------------------------------- a tracked study
@pytest.fixture(scope="module")
def mc_study(tmp_path_factory, uri):
    tmp = tmp_path_factory.mktemp("mc")
    cfg = search_cfg(tmp, uri, "study.name=mc", "search.n_trials=14")
    result, summary = run_search(cfg, quiet=True)
    return cfg, result, summary, tmp


def test_every_trial_is_a_child_run_with_params_objective_and_terms(mc_study, uri):
    _, result, summary, _ = mc_study
    trials = result.study.trials
    runs = {int(r["tags"]["optuna.trial"]): r for r in children(uri, result.parent_run_id)
            if r["tags"].get("sdrl.kind") == "trial"}
    assert sorted(runs) == [t.number for t in trials] == result.trials
    for t in trials:
        r = runs[t.number]
        assert r["status"] == "FINISHED" and r["tags"]["optuna.state"] == t.state.name
        # under the names a fit run logs them (optimizer.threshold, library.name, ...), tagged as fits are
        from sdrl_bench.search.study import FIT_PARAM_NAMES

        assert {k: r["params"][FIT_PARAM_NAMES[k]] for k in t.params} == {k: str(v) for k, v in t.params.items()}
        # alpha is STLSQ's ridge weight: a trial fitting SR3, which has none, samples and logs none
        assert ("alpha" in t.params) == ("optimizer.alpha" in r["params"]) == (t.params["optimizer"] == "stlsq")
        assert r["params"]["seed"] == "0" and r["tags"]["env"] == "mountain_car" and r["tags"]["seed"] == "0"
        assert r["tags"]["mlflow.source.name"] == "sdrl-bench-search" and r["tags"]["mlflow.user"]
        assert r["tags"]["library"] == r["params"]["library.name"]
        if t.state == optuna.trial.TrialState.COMPLETE:
            assert r["metrics"]["error"] == pytest.approx(t.value, rel=1e-12)
            assert r["metrics"]["n_terms"] == t.user_attrs["n_terms"]
            assert r["metrics"]["n_fits"] == 4  # 3 folds + the fit on all the data
    assert {t.params["optimizer"] for t in trials} == {"stlsq", "sr3"}
    assert summary.n_trials == 14 and summary.fits_total == sum(int(r["metrics"]["n_fits"]) for r in runs.values())


def test_parent_holds_best_params_value_and_figures(mc_study, uri):
    _, result, summary, _ = mc_study
    parent = MlflowClient(uri).get_run(result.parent_run_id)
    assert parent.info.status == "FINISHED"
    assert parent.data.metrics["best_error"] == pytest.approx(result.study.best_value, rel=1e-12)
    assert summary.best_number == result.study.best_trial.number
    assert {k: parent.data.tags[f"best.{k}"] for k in summary.best_params} == {k: str(v) for k, v in summary.best_params.items()}
    names = {a.path for a in MlflowClient(uri).list_artifacts(result.parent_run_id, "figures")}
    assert names == {"figures/optimization_history.png", "figures/param_importances.png", "figures/pareto_front.png"}
    assert parent.data.metrics["test/mse_norm/mean"] == pytest.approx(summary.test_error, rel=1e-12)
    assert parent.data.tags["importance.left_out"] == "alpha"  # sampled in STLSQ's trials only


def test_objective_is_k_fold_on_the_collected_data_and_reproducible(mc_study):
    cfg, result, summary, _ = mc_study
    sd = result.data
    spec = sd.spec
    assert sd.sha256 == collect(spec, heuristic_policy, 75, 0.2, seeds.reset_seed(0, "collect")).content_hash()
    assert sd.sha256 != held_out_test_set(spec)[1].content_hash()
    rows = sorted(i for f in sd.folds for i in f.valid.tolist())
    assert rows == list(range(75)) and len(sd.folds) == 3
    again = evaluate_params(summary.best_params, make_build_job(cfg), sd)
    assert again.error == result.study.best_value and again.n_terms == summary.best_n_terms


def test_exported_best_config_is_what_a_plain_fit_run_uses(mc_study):
    _, _, summary, tmp = mc_study
    pack = compose([f"hydra.searchpath=[file://{tmp}/export]", "experiment=mc"])
    plain = compose(summary.overrides)
    for cfg in (pack, plain):
        assert cfg.env.sindy.threshold == summary.best_params["threshold"]
        fit = fit_dynamics(build_fit_job(cfg))
        assert fit.fidelity.metrics["mse_norm/mean"] == pytest.approx(summary.test_error, rel=1e-9)
        assert fit.model.describe() == summary.best_equations


def test_an_nn_search_chooses_its_hyperparameters_on_the_studys_own_data(tmp_path, uri):
    """search=nn: TPE over the MLP's width, depth, activation, learning rate and weight decay,
    k-fold on the study's own data; trials log them under a fit's names, and the exported best
    config is a plain NN fit with those hyperparameters and the same test error."""
    from sdrl_bench.search.study import FIT_PARAM_NAMES

    cfg = search_cfg(tmp_path, uri, "surrogate=nn", "search=nn", "search.n_trials=3", "study.name=nn",
                     "surrogate.model.max_steps=150", "search.pruner=none")
    result, summary = run_search(cfg, quiet=True)
    trials = result.study.trials
    assert len(trials) == 3 and {t.state for t in trials} == {optuna.trial.TrialState.COMPLETE}
    assert len({t.value for t in trials}) == 3  # different hyperparameters, different held-out errors
    runs = [r for r in children(uri, result.parent_run_id) if r["tags"].get("sdrl.kind") == "trial"]
    for r in runs:
        t = trials[int(r["tags"]["optuna.trial"])]
        assert {FIT_PARAM_NAMES[k] for k in t.params} == {f"surrogate.model.{k}" for k in
                                                          ("width", "depth", "activation", "learning_rate", "weight_decay")}
        assert {k: r["params"][FIT_PARAM_NAMES[k]] for k in t.params} == {k: str(v) for k, v in t.params.items()}
        assert r["metrics"]["n_fits"] == 4 and r["metrics"]["error"] == pytest.approx(t.value, rel=1e-12)
    assert "surrogate=nn" in summary.overrides and not any(o.startswith(("library=", "optimizer=")) for o in summary.overrides)
    assert summary.best_n_terms is None and "active terms" not in summary.experiment_yaml
    fit = fit_dynamics(build_fit_job(compose(summary.overrides)))
    assert fit.model.width == summary.best_params["width"] and fit.model.activation == summary.best_params["activation"]
    assert fit.fidelity.metrics["mse_norm/mean"] == pytest.approx(summary.test_error, rel=1e-9)


def test_a_space_for_the_other_model_kind_is_refused_before_any_trial(tmp_path, uri):
    with pytest.raises(ConfigError, match=r"search.space.width: an NN hyperparameter, but the search fits surrogate=sindy"):
        run_search(search_cfg(tmp_path, uri, "search=nn", "study.name=x"), quiet=True)
    with pytest.raises(ConfigError, match=r"search.space.library: a SINDy hyperparameter, but the search fits surrogate=nn"):
        run_search(search_cfg(tmp_path, uri, "surrogate=nn", "study.name=y"), quiet=True)
    with pytest.raises(ConfigError, match=r"search.objectives: n_terms counts SINDy's active terms; surrogate=nn has none"):
        run_search(search_cfg(tmp_path, uri, "surrogate=nn", "search=nn", "search.objectives=[error,n_terms]",
                              "study.name=z"), quiet=True)
    assert not (tmp_path / "optuna.db").exists()


def test_journal_storage_resumes_too(tmp_path, uri):
    journal = f"study.storage='journal:{tmp_path}/optuna.journal'"
    first, _ = run_search(search_cfg(tmp_path, uri, journal, "study.name=j", "search.n_trials=3",
                                     "study.final_score=false"), quiet=True)
    again, summary = run_search(search_cfg(tmp_path, uri, journal, "study.name=j", "search.n_trials=5",
                                           "study.final_score=false"), quiet=True)
    assert first.trials == [0, 1, 2] and again.trials == [3, 4] and summary.n_trials == 5
    assert (tmp_path / "optuna.journal").stat().st_size > 0 and not (tmp_path / "optuna.db").exists()



def test_a_study_run_from_outside_the_checkout_names_the_harness_commit(tmp_path, uri, monkeypatch):
    """A study's parent run carries the standard tags every other run has: its git_commit is the
    working directory's repository's, else the sdrl_bench checkout's (it read "unknown" when the
    search ran from a folder that is no repository, as scripts/reproduce.py's stages do)."""
    from sdrl_bench.tracking import meta

    outside = tmp_path / "elsewhere"
    outside.mkdir()
    monkeypatch.chdir(outside)
    result, _ = run_search(search_cfg(tmp_path, uri, "study.name=commit", "search.n_trials=2",
                                      "study.final_score=false"), quiet=True)
    tags = MlflowClient(uri).get_run(result.parent_run_id).data.tags
    assert meta.git_commit(outside) == "unknown" and meta.package_commit() != "unknown"
    assert tags["git_commit"] == tags["mlflow.source.git.commit"] == meta.package_commit()
    assert tags["mlflow.source.name"] == "sdrl-bench-search" and tags["sdrl.kind"] == "study"


def test_a_resumed_study_draws_new_points_not_its_first_ones_again(tmp_path, uri):
    """TPE's first trials are random draws from the sampler's seed; a rerun seeded as at the
    start drew them again (trial 3 ran trial 0's parameters). A resumed study's sampler has a
    stream of its own; the same rerun of the same study still draws the same points."""
    def params(study):
        return [tuple(sorted(t.params.items())) for t in study.trials]

    for name in ("a", "b"):  # the same study twice over: determinism
        run_search(search_cfg(tmp_path, uri, f"study.name={name}", "search.n_trials=3", "study.final_score=false"),
                   quiet=True)
    again = {name: run_search(search_cfg(tmp_path, uri, f"study.name={name}", "search.n_trials=6",
                                         "study.final_score=false"), quiet=True)[0] for name in ("a", "b")}
    drawn = params(again["a"].study)
    assert again["a"].trials == [3, 4, 5] and len(set(drawn)) == 6  # no point drawn twice
    assert params(again["b"].study) == drawn


def test_a_rerun_of_a_done_study_adds_no_second_refit_of_the_same_best_trial(tmp_path, uri):
    """The best trial's refit on the test set is a fit run of its own; a rerun of a study that has
    its trials (or whose best trial did not change) reuses its score and adds no refit run."""
    cfg = search_cfg(tmp_path, uri, "study.name=refit", "search.n_trials=2")
    first, summary = run_search(cfg, quiet=True)
    again, summary_again = run_search(cfg, quiet=True)
    refits = tracking.find_runs(uri, EXPERIMENT, f"tags.`mlflow.parentRunId` = '{first.parent_run_id}' "
                                                 "and tags.`sdrl.role` = 'best-refit'")
    assert again.trials == [] and again.parent_run_id == first.parent_run_id
    assert len(refits) == 1 and refits[0]["status"] == "FINISHED"
    assert refits[0]["tags"]["optuna.trial"] == str(summary.best_number)
    assert summary_again.test_error == summary.test_error and summary.test_error > 0
    assert summary_again.test_metrics == summary.test_metrics
    parent = tracking.find_runs(uri, EXPERIMENT, f"attributes.run_id = '{first.parent_run_id}'")[0]
    assert parent["metrics"]["test/mse_norm/mean"] == summary.test_error
    scores = again.study.user_attrs["sdrl.refit_scores"]  # per trial: a best that is best again reuses its own
    assert list(scores) == [str(summary.best_number)] and scores[str(summary.best_number)]["test_error"] == summary.test_error


def test_grid_visits_every_point_once_and_compares_with_tpe(tmp_path, uri):
    grid = ["search=grid", "search.space.threshold.grid=[1e-4,1e-3,1e-2]", "search.space.alpha.grid=[1e-10,1e-5]"]
    result, summary = run_search(search_cfg(tmp_path, uri, "study.name=grid", *grid), quiet=True)
    seen = sorted((t.params["threshold"], t.params["alpha"]) for t in result.study.trials)
    assert seen == sorted(itertools.product([1e-4, 1e-3, 1e-2], [1e-10, 1e-5]))
    assert summary.fits_total == 6 * 4 and summary.fits_to_best == 4 * (summary.best_number + 1)
    rerun, _ = run_search(search_cfg(tmp_path, uri, "study.name=grid", "study.final_score=false", *grid), quiet=True)
    assert rerun.trials == [] and len(rerun.study.trials) == 6
    run_search(search_cfg(tmp_path, uri, "study.name=tpe", "search.n_trials=6"), quiet=True)
    table = comparison_table(load_summaries(f"sqlite:///{tmp_path}/optuna.db", ["grid", "tpe"]))
    assert table.splitlines()[2].split()[:2] == ["grid", "grid"] and "verdict: " in table


def test_pareto_mode_logs_the_non_dominated_front(tmp_path, uri):
    cfg = search_cfg(tmp_path, uri, "search=pareto", "study.name=pareto", "search.n_trials=10", "study.final_score=false")
    result, summary = run_search(cfg, quiet=True)
    front = {(e, k) for _, e, k in summary.pareto}
    assert front == {(t.values[0], int(t.values[1])) for t in result.study.best_trials}
    names = {a.path for a in MlflowClient(uri).list_artifacts(result.parent_run_id, "figures")}
    assert "figures/pareto_front.png" in names


def test_refinement_adds_trig_to_polynomials_and_stops(tmp_path, uri):
    out, fit = run_refine(search_cfg(tmp_path, uri, "search=refine", "study.name=refine"), quiet=True)
    assert [c.families for c in out.stages[0]] == [()]
    accepted = [next((c.families for c in s if c.accepted), None) for s in out.stages]
    assert accepted == [(), ("trig",), None]  # rational never pays after trig
    assert out.final.families == ("trig",) and out.final.n_terms == 7
    assert exact_law(fit.model.describe())
    parent = tracking.find_runs(uri, EXPERIMENT, "tags.`sdrl.kind` = 'refine' and tags.`sdrl.study` = 'refine'")[0]
    stages = [r for r in children(uri, parent["run_id"]) if r["tags"].get("sdrl.kind") == "refine-stage"]
    assert sorted(r["tags"]["accepted"] for r in stages) == ["base", "none", "trig"]


# ---------------------------------------------------------------------- processes
def _cli(tmp: Path, uri: str, *args: str, multirun: bool = False) -> list[str]:
    return [sys.executable, "-m", "sdrl_bench.cli.search", *(["-m"] if multirun else []),
            f"study.storage='sqlite:///{tmp}/optuna.db'",
            f"tracking.uri='{uri}'", "search.k_folds=3", "study.final_score=false",
            f"study.export_dir='{tmp}/export'", f"hydra.run.dir='{tmp}/run'", f"hydra.sweep.dir='{tmp}/sweep'", *args]


def _env() -> dict:
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    env["PYTHONPATH"] = str(ROOT)
    return env


def test_sigkill_mid_study_then_rerun_loses_and_duplicates_nothing(tmp_path, uri):
    storage = f"sqlite:///{tmp_path}/optuna.db"
    total = 20  # the kill comes at 4 complete trials (polled every 0.2 s): it lands mid-study even when trials run fast
    args = _cli(tmp_path, uri, "study.name=killed", f"search.n_trials={total}", "study.heartbeat_grace=1")
    proc = subprocess.Popen(args, cwd=tmp_path, env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 240
        while True:  # wait until the study holds 5 complete trials, then kill the worker mid-study
            assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
            assert time.monotonic() < deadline
            try:
                study = optuna.load_study(study_name="killed", storage=storage)
                if len(study.get_trials(states=(optuna.trial.TrialState.COMPLETE,))) >= 4:
                    break
            except Exception:  # the study is not created yet
                pass
            time.sleep(0.2)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    before = {t.number: (t.state, t.params, t.values) for t in study.get_trials() if counted(t)}
    assert 4 <= len(before) < total
    result, summary = run_search(search_cfg(tmp_path, uri, "study.name=killed", f"search.n_trials={total}",
                                            "study.heartbeat_grace=1", "study.final_score=false"), quiet=True)
    trials = result.study.get_trials()
    assert {t.number: (t.state, t.params, t.values) for t in trials if t.number in before} == before
    assert summary.n_trials == sum(map(counted, trials)) == total
    assert len(result.trials) == total - len(before)  # the rerun ran exactly what was missing
    lost = [t for t in trials if not counted(t)]  # the killed trial: FAIL once its heartbeat went
    # stale (RUNNING if the kill came before its first heartbeat: Optuna cannot tell it from a live one)
    assert len(lost) <= 1 and all("error" not in t.user_attrs for t in lost)
    runs = [r for r in children(uri, result.parent_run_id) if r["tags"].get("sdrl.kind") == "trial"]
    numbers = [int(r["tags"]["optuna.trial"]) for r in runs]
    assert len(numbers) == len(set(numbers))  # one run per trial: nothing duplicated
    by_number = {int(r["tags"]["optuna.trial"]): r for r in runs}
    for t in trials:
        if counted(t):
            assert by_number[t.number]["status"] == "FINISHED"
            assert by_number[t.number]["tags"]["optuna.state"] == t.state.name
        elif t.number in by_number and t.state == optuna.trial.TrialState.FAIL:
            assert by_number[t.number]["status"] == "KILLED"
    assert len(tracking.find_runs(uri, EXPERIMENT, "tags.`sdrl.kind` = 'study' and tags.`sdrl.study` = 'killed'")) == 1


def test_a_trial_whose_worker_died_after_its_run_ended_gets_its_run_killed(tmp_path, uri):
    """The window the kill test can land in by chance, made on purpose: a worker's trial run
    ended FINISHED, then the worker died before Optuna recorded the trial. The next worker's
    heartbeat check fails the trial, and its run says so: KILLED, ``optuna.state`` FAIL."""
    result, _ = run_search(search_cfg(tmp_path, uri, "study.name=window", "search.n_trials=2",
                                      "study.heartbeat_grace=1", "study.final_score=false"), quiet=True)
    storage = optuna.storages.RDBStorage(f"sqlite:///{tmp_path}/optuna.db", heartbeat_interval=1, grace_period=1)
    trial = optuna.load_study(study_name="window", storage=storage).ask()  # the dead worker's trial
    storage.record_heartbeat(trial._trial_id)
    run_id = tracking.create_parent_run(uri, EXPERIMENT, "window-trial-dead", {
        tracking.PARENT_TAG: result.parent_run_id, "sdrl.kind": "trial", "optuna.trial": trial.number,
        "optuna.state": "COMPLETE"})
    tracking.end_run(uri, run_id, "FINISHED")
    trial.set_user_attr("mlflow_run_id", run_id)
    time.sleep(2.5)  # past the grace period: the trial's heartbeat is stale
    run_search(search_cfg(tmp_path, uri, "study.name=window", "search.n_trials=3", "study.heartbeat_grace=1",
                          "study.final_score=false"), quiet=True)
    assert optuna.load_study(study_name="window", storage=storage).trials[trial.number].state == optuna.trial.TrialState.FAIL
    run = MlflowClient(uri).get_run(run_id)
    assert run.info.status == "KILLED" and run.data.tags["optuna.state"] == "FAIL"


def _check_workers(tmp: Path, uri: str, name: str, n_workers: int) -> None:
    study = optuna.load_study(study_name=name, storage=f"sqlite:///{tmp}/optuna.db")
    reports = [json.loads(p.read_text()) for p in sorted((tmp / "sweep").glob("*/worker.json"))]
    assert sorted(r["worker"] for r in reports) == list(range(n_workers))
    ran = [n for r in reports for n in r["trials"]]
    assert sorted(ran) == [t.number for t in study.trials]  # each trial run by exactly one worker
    assert all(t.state != optuna.trial.TrialState.FAIL for t in study.trials)
    parents = tracking.find_runs(uri, EXPERIMENT, f"tags.`sdrl.kind` = 'study' and tags.`sdrl.study` = '{name}'")
    assert len(parents) == 1
    runs = [r for r in children(uri, parents[0]["run_id"]) if r["tags"].get("sdrl.kind") == "trial"]
    per_worker = {r["worker"]: len(r["trials"]) for r in reports}
    assert {w: sum(x["tags"]["sdrl.worker"] == str(w) for x in runs) for w in per_worker} == per_worker


def test_a_summary_that_fails_leaves_the_parent_failed_and_a_later_one_finishes_it(tmp_path, uri):
    """A worker whose summary raises (here an export folder that is a file, which the CLI refuses
    up front) ends the study's parent run FAILED, not RUNNING; the next summary finishes it."""
    from sdrl_bench.cli.search import runtime_choices, study_settings
    from sdrl_bench.search.study import run_study
    from sdrl_bench.search.summary import summarize

    cfg = search_cfg(tmp_path, uri, "study.name=unsummarized", "search.n_trials=2", "study.final_score=false")
    result = run_study(study_settings(cfg, runtime_choices(cfg)), make_build_job(cfg))  # its trials, no summary
    (tmp_path / "f").write_text("mine")
    with pytest.raises(NotADirectoryError):
        summarize(result, make_build_job(cfg), False, tmp_path / "f")
    status = lambda: tracking.find_runs(uri, EXPERIMENT, f"attributes.run_id = '{result.parent_run_id}'")[0]["status"]  # noqa: E731
    assert status() == "FAILED" and (tmp_path / "f").read_text() == "mine"
    summarize(result, make_build_job(cfg), False, tmp_path / "export")
    assert status() == "FINISHED"


def _flock_waiters(path: Path) -> int:
    """Processes blocked in ``flock`` on ``path`` (the ``->`` lines of /proc/locks on its inode)."""
    if not path.exists():
        return 0
    inode = str(path.stat().st_ino)
    return sum(1 for line in Path("/proc/locks").read_text().splitlines()
               if "->" in line and "FLOCK" in line and line.split()[-3].rsplit(":", 1)[-1] == inode)


def test_workers_that_summarize_together_refit_the_best_once(tmp_path, uri):
    """Workers of one study that finish together summarize one at a time (``summary_lock``): three
    processes summarizing a done study at the same moment (the test holds the lock until all three
    wait on it) add one refit run of its best trial, and each ends with the parent FINISHED and its
    params logged once. Before, each worker refitted the best, and two logging the parent's
    params at once failed the sweep (a UNIQUE constraint)."""
    from sdrl_bench.search.storage import summary_lock

    first, _ = run_search(search_cfg(tmp_path, uri, "study.name=together", "search.n_trials=2",
                                     "study.final_score=false"), quiet=True)
    args = [a for a in _cli(tmp_path, uri, "study.name=together", "search.n_trials=2") if a != "study.final_score=false"]
    storage = f"sqlite:///{tmp_path}/optuna.db"
    lock = tmp_path / "optuna.db.together.summary.lock"
    procs: list[subprocess.Popen] = []
    try:
        with summary_lock(storage, "together"):
            inode = str(lock.stat().st_ino)
            held = [x for x in Path("/proc/locks").read_text().splitlines() if x.split()[-3].rsplit(":", 1)[-1] == inode]
            if not held:  # this file system shows its locks under other inodes: the waiters cannot be counted
                pytest.skip("/proc/locks does not list the lock file's inode here")
            procs = [subprocess.Popen(args, cwd=tmp_path, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                      text=True) for _ in range(3)]
            deadline = time.monotonic() + 300
            while _flock_waiters(lock) < 3:  # all three at the summary, none past it
                assert all(p.poll() is None for p in procs), [p.communicate()[1][-2000:] for p in procs if p.poll() is not None]
                assert time.monotonic() < deadline, "the workers never waited on the summary lock"
                time.sleep(0.2)
        for p in procs:
            out, err = p.communicate(timeout=300)
            assert p.returncode == 0, err[-3000:]
            assert "waiting for another worker's summary" in out  # each said why it paused
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    refits = tracking.find_runs(uri, EXPERIMENT, f"tags.`mlflow.parentRunId` = '{first.parent_run_id}' "
                                                 "and tags.`sdrl.role` = 'best-refit'")
    assert len(refits) == 1 and refits[0]["status"] == "FINISHED"
    parent = tracking.find_runs(uri, EXPERIMENT, f"attributes.run_id = '{first.parent_run_id}'")[0]
    assert parent["status"] == "FINISHED" and parent["params"]["n_transitions"] == "75"
    assert parent["metrics"]["test/mse_norm/mean"] > 0


@pytest.mark.slow
def test_four_parallel_workers_share_one_study(tmp_path, uri):
    args = _cli(tmp_path, uri, "study.worker=0,1,2,3", "hydra.launcher.n_jobs=4",
                "study.name=parallel", "search.n_trials=24", multirun=True)
    res = subprocess.run(args, cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "OperationalError" not in res.stderr and "database is locked" not in res.stderr
    _check_workers(tmp_path, uri, "parallel", 4)


@pytest.mark.slow
def test_submitit_local_executor_runs_two_workers(tmp_path, uri):
    args = _cli(tmp_path, uri, "hydra/launcher=submitit_local", "hydra.launcher.timeout_min=10",
                "study.worker=0,1", "study.name=submitit", "search.n_trials=8", multirun=True)
    res = subprocess.run(args, cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    _check_workers(tmp_path, uri, "submitit", 2)


def _get(url: str, body: dict | None = None) -> dict:
    """GET ``url``, or POST ``body`` as JSON: the MLflow REST API over plain HTTP."""
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url, data=data, headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=10) as r:
        return json.loads(r.read())


def test_search_against_a_real_mlflow_server(tmp_path, mlflow_server):
    base = mlflow_server
    cfg = search_cfg(tmp_path, base, "study.name=served", "search.n_trials=4")
    result, summary = run_search(cfg, quiet=True)
    exp = _get(f"{base}/api/2.0/mlflow/experiments/get-by-name?experiment_name={EXPERIMENT}")["experiment"]
    runs = _get(f"{base}/api/2.0/mlflow/runs/search", {"experiment_ids": [exp["experiment_id"]], "max_results": 100})["runs"]
    tags = [{t["key"]: t["value"] for t in r["data"].get("tags", [])} for r in runs]
    kinds = sorted(t.get("sdrl.kind") for t in tags)
    assert kinds == ["fit", "study"] + ["trial"] * 4
    parent = next(r for r, t in zip(runs, tags, strict=True) if t.get("sdrl.kind") == "study")
    metrics = {m["key"]: m["value"] for m in parent["data"]["metrics"]}
    assert metrics["best_error"] == pytest.approx(summary.best_error, rel=1e-12) and metrics["n_trials"] == 4
    listed = _get(f"{base}/api/2.0/mlflow/artifacts/list?run_id={result.parent_run_id}&path=figures")["files"]
    assert {f["path"] for f in listed} >= {"figures/optimization_history.png", "figures/pareto_front.png"}


# ---------------------------------------------------------------------- done-when (long)
@pytest.mark.slow
def test_mountain_car_100_tpe_trials_find_the_exact_law(tmp_path, uri):
    result, summary = run_search(search_cfg(tmp_path, uri, "study.name=mc100", "search.k_folds=5",
                                            "search.n_trials=100"), quiet=True)
    assert summary.n_trials == 100
    assert exact_law(summary.best_equations), summary.best_equations
    assert summary.test_error < 1e-13


def test_an_open_loop_objective_ranks_by_rollout_error_and_is_part_of_the_studys_identity(tmp_path, uri):
    grid = ["search=grid", "search.space.threshold.grid=[1e-3,3e-2]", "search.space.alpha.grid=[1e-10]",
            "study.final_score=false"]
    result, summary = run_search(search_cfg(tmp_path, uri, "study.name=roll", "search.objective=rollout10", *grid), quiet=True)
    errors = {t.params["threshold"]: t.values[0] for t in result.study.trials}
    # the exact law (threshold 1e-3) is at float noise over 10 open-loop steps; the coarse one is far off
    assert errors[1e-3] < 1e-6 < errors[3e-2]
    assert summary.best_params["threshold"] == 1e-3
    parent = tracking.find_runs(uri, EXPERIMENT, "tags.`sdrl.study` = 'roll' and tags.`sdrl.kind` = 'study'")[0]
    assert parent["tags"]["search.objective"] == "rollout10"
    with pytest.raises(ConfigError, match=r"^study.name: study 'roll' .* different setup"):
        run_search(search_cfg(tmp_path, uri, "study.name=roll", *grid), quiet=True)  # today's objective: another study
    with pytest.raises(ConfigError, match=r"^search.objective: one of \['one_step', 'rollout10'"):
        run_search(search_cfg(tmp_path, uri, "study.name=bad_objective", "search.objective=bogus"), quiet=True)


def test_a_policy_objective_trains_an_agent_per_trial_and_counts_its_real_episodes(tmp_path, uri):
    tiny = ["agent=ppo_fast", "agent.n_envs=4", "agent.algo.n_steps=16", "agent.algo.batch_size=32", "agent.algo.n_epochs=1",
            "search.policy.train_steps=64", "search.policy.episodes=1"]
    grid = ["search=grid", "search.space.threshold.grid=[1e-3,3e-2]", "search.space.alpha.grid=[1e-10]",
            "study.final_score=false"]
    result, _ = run_search(search_cfg(tmp_path, uri, "study.name=onpol", "search.objective=onpolicy_one_step", *tiny, *grid),
                           quiet=True)
    errors = {t.params["threshold"]: t.values[0] for t in result.study.trials}
    # the exact law predicts the agent's own real steps to float noise; the coarse fit does not
    assert errors[1e-3] < 1e-8 < errors[3e-2]
    trials = tracking.find_runs(uri, EXPERIMENT, "tags.`sdrl.study` = 'onpol' and tags.`sdrl.kind` = 'trial'")
    assert len(trials) == 2
    for t in trials:  # one real episode of MountainCar per trial (1 to 999 steps), counted as selection
        assert 1 <= t["metrics"]["real_steps/selection"] <= 999
    gap, _ = run_search(search_cfg(tmp_path, uri, "study.name=refgap", "search.objective=reference_gap",
                                   "search.policy.reference=heuristic", "search.policy.episodes=2", *grid), quiet=True)
    gaps = {t.params["threshold"]: t.values[0] for t in gap.study.trials}
    assert gaps[1e-3] < gaps[3e-2]
    again, _ = run_search(search_cfg(tmp_path, uri, "study.name=refgap", "search.objective=reference_gap",  # resumes
                                     "search.policy.reference=heuristic", "search.policy.episodes=2", *grid), quiet=True)
    assert again.trials == [] and len(again.study.trials) == 2
    with pytest.raises(ConfigError, match=r"^search.objective=onpolicy_one_step: needs search.policy"):
        run_search(search_cfg(tmp_path, uri, "study.name=nopol", "~search.policy", "search.objective=onpolicy_one_step"),
                   quiet=True)
