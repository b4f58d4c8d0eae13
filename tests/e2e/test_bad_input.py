"""Bad input: one clear line naming the key or file, non-zero exit, no run left RUNNING."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from helpers import compose_cfg, run_cli, search
from sdrl_bench import ConfigError, tracking
from sdrl_bench.cli.main import run_fit


def no_running_runs(uri: str) -> int:
    """The count of runs in the store at ``uri`` (0 where no store was made), none RUNNING."""
    if not tracking.sqlite_path(uri).is_file():
        return 0
    try:
        runs = search(uri)
    except Exception:  # experiment never created: no run at all
        return 0
    assert "RUNNING" not in set(runs["status"]) if len(runs) else True
    return len(runs)


@pytest.mark.parametrize("override,needle", [
    ("env=moon", "env"), ("library=splines", "library"), ("optimizer=adam", "optimizer"),
    ("collector=oracle", "collector"),
])
def test_unknown_group_option_fails_at_composition(new_store, tmp_path, override, needle):
    store = new_store
    res = run_cli(override, f"tracking.uri={store}", cwd=tmp_path)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"sdrl-bench: error: {override}: no such option of '{needle}' (options: ")
    assert no_running_runs(store) == 0 and not (tmp_path / "outputs").exists() and not (tmp_path / "multirun").exists()
    assert not (tmp_path / "mlruns").exists()  # refused before the store was made


@pytest.mark.parametrize("args,line", [
    (["n_transition=5"], "n_transition: unknown config key; did you mean n_transitions? (to add a new key: +n_transition=...)"),
    (["env=lunar_lander", "env.spec.fit_regim=x"],
     "env.spec.fit_regim: unknown config key; did you mean env.spec.fit_regime? (to add a new key: +env.spec.fit_regim=...)"),
    (["-m", "seed=0,1", "rl.surrogate_stepz=5"],
     "rl.surrogate_stepz: unknown config key; did you mean rl.surrogate_steps? (to add a new key: +rl.surrogate_stepz=...)"),
    (["optimizer=sr3", "optimizer.alpha=0.1"],  # no near key in the block (not _target_): its keys
     "optimizer.alpha: unknown config key; optimizer has max_iter, name, normalize_columns, relax_coeff_nu, "
     "threshold (to add a new key: +optimizer.alpha=...)"),
    (["-m", "library=polynomial,splines"], "library=splines: no such option of 'library' (options: "),
    (["seed=[1"], "seed=[1: cannot parse this override (no viable alternative at input '[1')"),
    (["optimizer.threshold=${env.nope}"], "optimizer.threshold: Interpolation key 'env.nope' not found"),
])
def test_unknown_keys_options_and_bad_overrides_are_one_line(new_store, tmp_path, args, line):
    """Checked before Hydra runs: one line naming the key (and the nearest valid one), exit 2,
    no output folder, no store, no run; a sweep's every value is checked, not only its first."""
    store = new_store
    res = run_cli(*args, f"tracking.uri={store}", cwd=tmp_path)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"sdrl-bench: error: {line}"), res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == [] and no_running_runs(store) == 0


@pytest.mark.parametrize("args,line", [
    (["seed=0,1", "collector.epsilon=2"], "collector.epsilon must be within [0.0, 1.0], got 2"),
    (["seed=0,-1"], "seed must be >= 0, got -1"),
    (["experiment=quick_mountain_car", "agent=dqn", "seed=0,1"],
     "agent=dqn: DQN needs discrete actions but env 'mountain_car' has continuous (Box) actions"),
    (["experiment=dyna_mountain_car", "seed=0,1", "rl.dyna.max_rounds=0"],
     "rl.dyna.max_rounds: a positive integer is required, got 0"),
    (["seed=0,1", "hydra.launcher.n_jobs=0"],  # joblib's traceback after the parent run, before
     "hydra.launcher.n_jobs: a whole number of parallel jobs other than 0 is required (1, 2, ...; -1 for every core), "
     "got 0"),
    (["seed=0,1", "hydra.launcher.n_jobs=abc"],  # was Hydra's "Error merging override ...", no reason given
     "hydra.launcher.n_jobs: Value 'abc' of type 'str' could not be converted to Integer"),
    (["seed=0,1", "hydra.job.chdir=maybe"], "hydra.job.chdir: Value 'maybe' is not a valid bool (type str)"),
])
def test_a_sweeps_bad_job_is_one_line_before_the_sweep_starts(new_store, tmp_path, args, line):
    """``-m``: each job's own check (``cli.build.check_job``) runs in the driver first, so a bad
    value, in any of a sweep's values, is one line and exit 2 with no Hydra folder, no store and
    no parent run (before, the sweep started, its jobs failed, and a FAILED parent was left)."""
    res = run_cli("-m", *args, f"tracking.uri={new_store}", cwd=tmp_path)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"sdrl-bench: error: {line}"), res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_a_compiled_agent_without_the_jax_extra_is_one_line(store, tmp_path):
    """The compiled agents need the ``[jax]`` extra; where jax cannot be imported (made so here,
    installed or not) a run says so in one line naming ``agent.algo``, exit 2, before any run."""
    import subprocess
    import sys

    script = ("import sys; sys.modules['jax'] = None; sys.argv = ['sdrl-bench', *sys.argv[1:]]; "
              "from sdrl_bench.cli.main import main; main()")
    res = subprocess.run([sys.executable, "-c", script, "experiment=quick_mountain_car", "agent=sac_jax",
                          f"tracking.uri={store}"], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [
        "sdrl-bench: error: agent.algo: the compiled SAC (agent=sac_jax, sdrl_bench.rl.jax_agent.JaxSAC) needs jax, "
        "an optional extra: pip install 'sdrl-bench[jax]'"]
    assert no_running_runs(store) == 0


def test_a_dm_control_env_without_the_dmc_extra_is_one_line_naming_it(store, tmp_path):
    """``env=cartpole_swingup`` needs the ``[dmc]`` extra; without it (made so here) one line names
    the extra to install, exit 2, before any run."""
    import subprocess
    import sys

    script = ("import sys; sys.modules['shimmy'] = None; sys.argv = ['sdrl-bench', *sys.argv[1:]]; "
              "from sdrl_bench.cli.main import main; main()")
    res = subprocess.run([sys.executable, "-c", script, "env=cartpole_swingup", f"tracking.uri={store}"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("sdrl-bench: error: env.spec.")
    assert lines[0].endswith("the dm_control envs need the [dmc] extra (shimmy is missing): "
                             "pip install 'sdrl-bench[dmc]'")
    assert no_running_runs(store) == 0


def test_a_yaml_syntax_error_in_a_users_config_is_one_line_with_file_and_line(store, tmp_path):
    conf = tmp_path / "conf" / "env"
    conf.mkdir(parents=True)
    (conf / "bad.yaml").write_text("spec:\n  _target_: sdrl_bench.envs.EnvSpec\n  name: bad\n  state_names: [x, v\n")
    res = run_cli("--config-dir", str(tmp_path / "conf"), "env=bad", f"tracking.uri={store}", cwd=tmp_path)
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [
        f"sdrl-bench: error: {conf / 'bad.yaml'}:5: YAML syntax error: expected ',' or ']', but got '<stream end>'"]


def test_negative_threshold_exits_2_with_one_line(store, tmp_path):
    res = run_cli("optimizer.threshold=-0.1", f"tracking.uri={store}", cwd=tmp_path)
    assert res.returncode == 2
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert lines == ["sdrl-bench: error: optimizer: threshold cannot be negative"]
    assert no_running_runs(store) == 0


@pytest.mark.parametrize("override,line", [
    ("+env.spec.touchdown_set=/no/such.npz", "env.spec.touchdown_set: no such file: /no/such.npz"),
    ("dataset.path=/no/such.csv", "dataset.path: no such file: /no/such.csv"),
])
def test_a_file_the_config_names_must_exist(store, tmp_path, override, line):
    """A missing file is one line naming the key, exit 2, before any collection or run."""
    env = "env=lunar_lander" if "touchdown" in override else "env=mountain_car"
    res = run_cli(env, override, f"tracking.uri={store}", cwd=tmp_path)
    assert res.returncode == 2
    assert [ln for ln in res.stderr.splitlines() if ln.strip()] == [f"sdrl-bench: error: {line}"]
    assert no_running_runs(store) == 0


def test_fewer_transitions_than_library_terms(store):
    with pytest.raises(ConfigError, match=r"n_transitions=10: fewer transitions than the 12 terms of library 'poly_trig'"):
        run_fit(compose_cfg("n_transitions=10", f"tracking.uri={store}"))
    assert no_running_runs(store) == 0


@pytest.mark.parametrize("value", ["0", "-5", "abc", "2.5"])
def test_bad_episode_cut_is_rejected_naming_the_key(store, value):
    with pytest.raises(ConfigError, match=r"collector.max_steps_per_episode must be a positive integer or null"):
        run_fit(compose_cfg(f"collector.max_steps_per_episode={value}", f"tracking.uri={store}"))
    assert no_running_runs(store) == 0


def test_episode_cut_splits_the_collection_into_episodes(store):
    """n_transitions=200 cut every 30 steps: 7 episodes (six of 30, one of 20), all logged."""
    res = run_fit(compose_cfg("n_transitions=200", "collector.max_steps_per_episode=30", f"tracking.uri={store}"))
    assert len(set(res.data.episode.tolist())) == 7 and len(res.data) == 200
    runs = search(store)
    assert runs["params.collector.max_steps_per_episode"].tolist() == ["30"]
    assert runs["metrics.n_episodes"].tolist() == [7.0]


def _dataset(tmp_path, mutate):
    from sdrl_bench.data import collect, heuristic_policy, save_csv
    from sdrl_bench.envs.mountain_car import MountainCarSpec

    spec = MountainCarSpec()
    path = save_csv(collect(spec, heuristic_policy, 40, 0.2, 0), spec, tmp_path / "d.csv")
    df = pd.read_csv(path)
    mutate(df)
    df.to_csv(path, index=False)
    return path


def test_a_folder_as_dataset_path_is_named_as_a_folder(store, tmp_path):
    with pytest.raises(ConfigError, match=f"^dataset.path: {tmp_path} is a folder, not a CSV file$"):
        run_fit(compose_cfg(f"dataset.path={tmp_path}", f"tracking.uri={store}"))
    assert no_running_runs(store) == 0


def test_dataset_with_nan_is_rejected_naming_file_and_column(store, tmp_path):
    path = _dataset(tmp_path, lambda df: df.__setitem__("ns_v", df["ns_v"].where(df.index != 3, np.nan)))
    with pytest.raises(ConfigError, match=r"d.csv has a missing or non-numeric value in column 'ns_v' \(data row 4\)"):
        run_fit(compose_cfg(f"dataset.path={path}", f"tracking.uri={store}"))
    assert no_running_runs(store) == 0


@pytest.mark.parametrize("column, value, line", [
    ("episode", 0.5, "column 'episode' must be a whole number >= 0, got 0.5 (data row 4)"),
    ("step", -1, "column 'step' must be a whole number >= 0, got -1 (data row 4)"),
    ("terminated", 7, "column 'terminated' must be 0 or 1, got 7 (data row 4)"),
])
def test_dataset_bookkeeping_columns_are_checked_not_truncated(store, tmp_path, column, value, line):
    """An episode 0.5 was read as 0 and terminated 7 as true: now one line naming the column."""
    path = _dataset(tmp_path, lambda df: df.__setitem__(column, df[column].astype(float).where(df.index != 3, value)))
    with pytest.raises(ConfigError) as err:
        run_fit(compose_cfg(f"dataset.path={path}", f"tracking.uri={store}"))
    assert str(err.value) == f"dataset.path: {path} {line}"
    assert no_running_runs(store) == 0


def test_a_config_dir_that_is_not_a_folder_is_one_line(new_store, tmp_path):
    res = run_cli("--config-dir", str(tmp_path / "nodir"), f"tracking.uri={new_store}", cwd=tmp_path)
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [f"sdrl-bench: error: --config-dir: {tmp_path / 'nodir'} is not a folder"]


def test_dataset_with_missing_column_is_rejected(store, tmp_path):
    path = _dataset(tmp_path, lambda df: df.drop(columns=["a_0"], inplace=True))
    res = run_cli(f"dataset.path={path}", f"tracking.uri={store}", cwd=tmp_path)
    assert res.returncode == 2
    assert res.stderr.strip() == f"sdrl-bench: error: dataset.path: {path} lacks columns ['a_0'] for env 'mountain_car'"


def test_dataset_file_can_be_fitted_when_valid(store, tmp_path):
    path = _dataset(tmp_path, lambda df: None)
    result = run_fit(compose_cfg(f"dataset.path={path}", f"tracking.uri={store}"))
    assert len(result.data) == 40
    assert search(store).iloc[0]["status"] == "FINISHED"


def test_unwritable_tracking_location(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    uri = f"sqlite:///{blocker / 'mlruns' / 'mlflow.db'}"
    with pytest.raises(ConfigError) as err:
        run_fit(compose_cfg(f"tracking.uri={uri}"))
    assert str(err.value) == (f"tracking.uri: cannot write the tracking store at {blocker / 'mlruns'} "
                              f"({blocker} is a file, not a folder)")
    assert blocker.read_text() == "not a folder"  # nothing the user had is lost


def test_failure_after_the_run_started_marks_it_failed(store, tmp_path):
    # every transition at a bound: detected only once data exists, inside the run
    path = _dataset(tmp_path, lambda df: df.__setitem__("ns_x", -1.2))
    with pytest.raises(ConfigError, match="every transition lies on a state bound"):
        run_fit(compose_cfg(f"dataset.path={path}", f"tracking.uri={store}", "library=trig"))
    runs = search(store)
    assert list(runs["status"]) == ["FAILED"]
    assert runs["tags.sdrl.error"].tolist() == [
        "ConfigError: dataset: every transition lies on a state bound or outside the fitted regime; nothing to fit"]


def test_sigterm_mid_run_ends_the_run_killed(store, tmp_path):
    import signal
    import subprocess
    import sys
    import time

    from mlflow.tracking import MlflowClient

    # the progress bar on, and both streams in one: the bar's last line comes before the stop's
    # line, not after it (the bar was once drawn at the interpreter's exit, below the message)
    proc = subprocess.Popen(
        [sys.executable, "-m", "sdrl_bench.cli.main", "task=train", "rl.arms=[real]", "rl.real_steps=100000",
         "rl.eval_every=500", "progress_bar=true", f"tracking.uri={store}"],
        cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline:  # wait until the agent trains (a curve point past step 0), then stop it
        try:
            runs = search(store)
            if len(runs) and len(MlflowClient(store).get_metric_history(runs.iloc[0]["run_id"],
                                                                        "real/curve_return_mean")) >= 2:
                break
        except Exception:
            pass
        time.sleep(0.5)
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM
    lines = out.strip().splitlines()
    assert lines[-1] == "sdrl-bench: stopped by SIGTERM; the run ended KILLED", out[-2000:]
    assert lines[-2].startswith("real arm, SAC"), out[-2000:]  # the bar, closed before the line
    assert list(search(store)["status"]) == ["KILLED"]


def test_unknown_agent_fails_at_composition(tmp_path, store):
    res = run_cli("task=train", "agent=a2c_magic", f"tracking.uri={store}", cwd=tmp_path)
    assert res.returncode == 2 and "sdrl-bench: error: agent=a2c_magic: no such option of 'agent'" in res.stderr


def test_a_default_fit_prints_no_warning(store, tmp_path):
    """``sdrl-bench`` with no argument: exit 0, the table and equations on stdout, nothing on
    stderr that says warning (MLflow's type-hint note, a library's deprecation)."""
    res = run_cli(f"tracking.uri={store}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "warn" not in res.stderr.lower(), res.stderr[-2000:]
    assert "x[k+1] = 1 x +1 v +0.0015 u -0.0025 cos(3 x)" in res.stdout


def test_a_swingup_fit_prints_no_warning_or_import_notes(store, tmp_path):
    """The DeepMind Control Suite env (dm_control through shimmy): its imports leave the warning
    filters and the log as they were."""
    res = run_cli("env=cartpole_swingup", "collector=random", "n_transitions=1000", f"tracking.uri={store}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "warn" not in res.stderr.lower(), res.stderr[-2000:]
    assert "absl" not in res.stderr + res.stdout and "OpenGL" not in res.stderr + res.stdout
    assert "x' = x +0.00" in res.stdout


def test_a_config_yaml_in_the_config_dir_that_hydra_passes_over_is_warned_of(tmp_path):
    """Hydra reads the package's config.yaml before one in ``--config-dir`` (the user's is silently
    unused); the run says so, and under another name with ``--config-name`` it is read."""
    conf = tmp_path / "conf"
    conf.mkdir()
    text = "defaults:\n  - config\n  - _self_\nn_transitions: 33\n"
    (conf / "config.yaml").write_text(text)
    (conf / "mine.yaml").write_text(text)
    shadowed = run_cli("--config-dir", str(conf), "--cfg", "job", cwd=tmp_path)
    assert shadowed.returncode == 0, shadowed.stderr[-2000:]
    assert shadowed.stderr.strip().splitlines()[0] == (
        f"sdrl-bench: warning: --config-dir: {conf / 'config.yaml'} is not read (the package's config.yaml comes "
        "first); to use it, rename it and pass --config-name <its name>, its defaults list starting with 'config'")
    assert "\nn_transitions: ${env.n_transitions}\n" in shadowed.stdout  # the package's, not 33
    named = run_cli("--config-dir", str(conf), "--config-name", "mine", "--cfg", "job", cwd=tmp_path)
    assert named.returncode == 0 and "warning" not in named.stderr, named.stderr[-2000:]
    assert "\nn_transitions: 33\n" in named.stdout
