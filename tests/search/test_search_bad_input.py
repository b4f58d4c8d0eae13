"""Bad input to ``sdrl-bench-search``: one line naming the config key the user sets, exit 2,
before any data are collected, and nothing written (no study, no MLflow run)."""

from __future__ import annotations

from pathlib import Path

import optuna
import pytest

from helpers import run_cli
from sdrl_bench import ConfigError
from sdrl_bench.cli.build import compose
from sdrl_bench.cli.search import run_refine, runtime_choices, study_settings

LIBRARIES = sorted(p.stem for p in (Path(__file__).resolve().parents[2] / "sdrl_bench" / "conf" / "library").glob("*.yaml"))


def _search(tmp: Path, *args: str):
    """``sdrl-bench-search`` in a real process, its study storage and MLflow store in ``tmp``."""
    return run_cli(f"study.storage='sqlite:///{tmp}/optuna.db'", f"tracking.uri='sqlite:///{tmp}/mlflow.db'",
                   "study.final_score=false", *args, cwd=tmp, timeout=120, module="sdrl_bench.cli.search")


def _refused(proc, tmp: Path, line: str) -> None:
    assert (proc.returncode, proc.stderr.strip().splitlines()) == (2, [f"sdrl-bench-search: error: {line}"]), proc.stderr
    assert proc.stdout == ""  # no trial ran
    assert not (tmp / "mlflow.db").exists()  # no MLflow run, so none left RUNNING


def test_a_non_integer_setting_is_one_line_naming_its_key(tmp_path):
    proc = _search(tmp_path, "search.k_folds=2.5")  # was truncated to 2 folds ('abc': a traceback, exit 1)
    _refused(proc, tmp_path, "search.k_folds: an integer is required, got 2.5")
    assert not (tmp_path / "optuna.db").exists()


def test_a_sweeps_bad_worker_is_one_line_before_the_stores_exist(tmp_path):
    """``-m``: each worker's check (``cli.search.check_job``) runs in the driver before the sweep's
    storage callback makes the study storage and the MLflow store (it made both empty, before)."""
    proc = run_cli("-m", f"study.storage='sqlite:///{tmp_path}/optuna.db'", f"tracking.uri='sqlite:///{tmp_path}/mlflow.db'",
                   "study.worker=0,abc", cwd=tmp_path, timeout=120, module="sdrl_bench.cli.search")
    _refused(proc, tmp_path, "study.worker: an integer is required, got 'abc'")
    assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.mark.parametrize("key", ["seed", "n_transitions", "search.k_folds", "search.n_trials", "study.seed",
                                 "study.worker", "study.heartbeat_interval", "study.heartbeat_grace"])
@pytest.mark.parametrize("value, shown", [("abc", "'abc'"), ("1.5", "1.5"), ("true", "True")])
def test_every_integer_setting_refuses_a_string_a_fraction_and_a_bool(key, value, shown):
    cfg = compose([f"{key}={value}"], config_name="search_app", return_hydra_config=True)
    with pytest.raises(ConfigError) as err:
        study_settings(cfg, runtime_choices(cfg))
    assert str(err.value) == f"{key}: an integer is required, got {shown}"


@pytest.mark.parametrize("override, line", [
    ("search.base_library=nosuch", f"search.base_library: unknown choice 'nosuch' (the library group has {LIBRARIES})"),
    ("search.k_folds=abc", "search.k_folds: an integer is required, got 'abc'"),
    ("search.margin=1", "search.margin must be in [0, 1), got 1.0"),
    ("search.thresholds=[abc]", "search.thresholds: a non-empty list of finite numbers >= 0 is required, got ['abc']"),
    ("search.families.trig=[{library: {_target_: nosuch.Lib}}]",
     "search.families.trig[0].library: cannot import 'nosuch.Lib': ModuleNotFoundError: No module named 'nosuch'"),
    ("study.name=[a,b]", "study.name: \"['a', 'b']\" must be letters, digits, '_', '.' or '-'"),  # a YAML traceback
    ("study.name=a/b", "study.name: 'a/b' must be letters, digits, '_', '.' or '-'"),
])
def test_refinement_settings_name_the_search_key_before_any_data(tmp_path, override, line):
    cfg = compose(["search=refine", override, f"tracking.uri='sqlite:///{tmp_path}/mlflow.db'"],
                  config_name="search_app", return_hydra_config=True)
    with pytest.raises(ConfigError) as err:
        run_refine(cfg, quiet=True)
    assert str(err.value) == line
    assert not (tmp_path / "mlflow.db").exists()


def test_an_unknown_base_library_names_search_base_library(tmp_path):
    proc = _search(tmp_path, "search=refine", "search.base_library=nosuch")
    _refused(proc, tmp_path, f"search.base_library: unknown choice 'nosuch' (the library group has {LIBRARIES})")


@pytest.mark.parametrize("studies, line", [
    (None, "search.studies: a non-empty list of study names is required (search.studies=[name1,name2]), got []"),
    ("[nosuch]", "search.studies: no study named 'nosuch' in sqlite:///{tmp}/optuna.db (it holds ['other'])"),
])
def test_compare_names_search_studies(tmp_path, studies, line):
    optuna.create_study(study_name="other", storage=f"sqlite:///{tmp_path}/optuna.db")
    proc = _search(tmp_path, "search=compare", *([f"search.studies={studies}"] if studies else []))
    _refused(proc, tmp_path, line.format(tmp=tmp_path))
    assert optuna.get_all_study_names(f"sqlite:///{tmp_path}/optuna.db") == ["other"]


@pytest.mark.parametrize("overrides, line", [
    (["search.space.library.choices=[polynomial,lunar_lander_flight]"],
     "search.space.library.choices: 'lunar_lander_flight' cannot be fitted on env 'mountain_car': "
     "library.equations.vx: not a regressed state; regressed: x, v"),
    (["search.space.threshold.low=-0.5", "search.space.threshold.log=false"],
     "search.space.threshold.low: -0.5 cannot be fitted on env 'mountain_car': optimizer: threshold cannot be negative"),
])
def test_a_space_value_the_env_or_its_domain_refuses_is_named_before_any_trial(tmp_path, overrides, line):
    # before: every trial failed with the same Optuna traceback, and the command exited 0
    proc = _search(tmp_path, "search.n_trials=2", "study.name=space", *overrides)
    _refused(proc, tmp_path, line)
    assert not (tmp_path / "optuna.db").exists()


@pytest.mark.parametrize("overrides, line", [
    (["search=grid", "optimizer=sr3"],
     "search.space.alpha: no config this study fits interpolates env.sindy.alpha (library=poly_trig, optimizer=sr3 as "
     "composed here), so no trial would use it: remove alpha from the space or fit a library or optimizer that reads it"),
    (["search=grid", "optimizer.alpha=0.01"],  # the command line replaced the interpolation the searched alpha goes through
     "search.space.alpha: no config this study fits interpolates env.sindy.alpha (library=poly_trig, optimizer=stlsq as "
     "composed here), so no trial would use it: remove alpha from the space or fit a library or optimizer that reads it"),
    (["search.sampler=grid", "+search.space.threshold.grid=[0.001,0.01]", "+search.space.alpha.grid=[0.01,0.1]"],
     "search.space.alpha: only optimizer=stlsq reads it, so the grid would fit the other optimizer choices once per "
     "alpha value; use search.sampler=tpe or random, or one grid study per optimizer"),
])
def test_a_searched_value_no_trial_would_use_is_refused_before_any_trial(tmp_path, overrides, line):
    # before: SR3 fits ignored the sampled alpha, so a grid fitted each point once per alpha value
    proc = _search(tmp_path, "study.name=dead", *overrides)
    _refused(proc, tmp_path, line)
    assert not (tmp_path / "optuna.db").exists()


def test_a_sweeps_check_names_the_groups_a_dead_value_would_be_fitted_with(tmp_path):
    """``-m``: the driver's check of each worker (which has no runtime choices) names the options."""
    proc = run_cli("-m", f"study.storage='sqlite:///{tmp_path}/optuna.db'", f"tracking.uri='sqlite:///{tmp_path}/mlflow.db'",
                   "study.worker=0,1", "search=grid", "optimizer=sr3", cwd=tmp_path, timeout=120, module="sdrl_bench.cli.search")
    _refused(proc, tmp_path, "search.space.alpha: no config this study fits interpolates env.sindy.alpha (library=poly_trig, "
                             "optimizer=sr3 as composed here), so no trial would use it: remove alpha from the space or fit "
                             "a library or optimizer that reads it")


@pytest.mark.parametrize("overrides, when", [
    ([], {"alpha": (("optimizer", frozenset({"stlsq"})),)}),
    (["search.sampler=nsga2"], {}),  # NSGA-II evolves only what every trial has: alpha stays in every trial
    (["search.space.optimizer.choices=[stlsq,ensemble]"], {}),  # both read it
    (["search.sampler=grid", "+search.space.threshold.grid=[0.01]", "+search.space.alpha.grid=[0.01]",
      "search.space.optimizer.choices=[stlsq,sr3]"], {"alpha": (("optimizer", frozenset({"stlsq"})),)}),  # one value: allowed
])
def test_which_values_a_study_samples_only_under_some_choices(overrides, when):
    from sdrl_bench.search.study import check_settings

    cfg = compose(overrides, config_name="search_app", return_hydra_config=True)
    settings = study_settings(cfg, runtime_choices(cfg))
    check_settings(settings)
    assert settings.when == when


def test_an_export_dir_that_is_a_file_is_refused_before_any_data(tmp_path):
    """Before, every trial and the final refit ran, then a NotADirectoryError traceback left the
    study's parent run RUNNING."""
    (tmp_path / "f").write_text("mine")
    proc = _search(tmp_path, f"study.export_dir='{tmp_path}/f'", "search.n_trials=2")
    _refused(proc, tmp_path, f"study.export_dir: {tmp_path}/f is a file, not a folder "
                             f"(the best config goes to {tmp_path}/f/experiment/mountain_car-tpe-s0.yaml)")
    assert (tmp_path / "f").read_text() == "mine"


def test_a_users_file_where_the_best_config_would_go_is_never_replaced(tmp_path):
    """Before, a file of the user's named like the study's export was overwritten, exit 0. A
    best config this study exported before is replaced by a rerun (test_search's rerun test)."""
    mine = tmp_path / "e" / "experiment" / "mountain_car-tpe-s0.yaml"
    mine.parent.mkdir(parents=True)
    mine.write_text("# MY OWN PACK\n")
    proc = _search(tmp_path, f"study.export_dir='{tmp_path}/e'", "search.n_trials=2")
    _refused(proc, tmp_path, f"study.export_dir: {mine} exists and is not a best config this study exported; "
                             "move it, or set study.export_dir to another folder")
    assert mine.read_text() == "# MY OWN PACK\n"


def test_a_heartbeat_grace_shorter_than_its_interval_is_refused():
    cfg = compose(["study.heartbeat_interval=10", "study.heartbeat_grace=5"], config_name="search_app",
                  return_hydra_config=True)
    with pytest.raises(ConfigError) as err:
        study_settings(cfg, runtime_choices(cfg))
    assert str(err.value) == ("study.heartbeat_grace: 5 s is shorter than study.heartbeat_interval (10 s), so other "
                              "workers would fail live trials as stale; set it to a few intervals (Optuna's default is "
                              "twice the interval)")


def test_a_policy_objective_whose_agent_cannot_act_in_the_env_is_refused_before_any_data(tmp_path):
    """Before, trial 0 collected and fitted, then SB3's assertion failed it with a traceback."""
    proc = _search(tmp_path, "search.objective=onpolicy_one_step", "agent=dqn", "search.n_trials=2")
    _refused(proc, tmp_path, "agent=dqn: DQN needs discrete actions but env 'mountain_car' has continuous (Box) "
                             "actions; use agent=sac, agent=td3 or agent=ppo")
    assert not (tmp_path / "optuna.db").exists()
