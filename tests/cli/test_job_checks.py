"""What a job checks before its run exists (``cli.build.check_job``, the same checks a run makes
and a ``-m`` sweep's driver makes for each job): settings an audit found unchecked, each one line
naming the key, where before they failed mid-training with a traceback (an SB3 learning rate of
-1, a batch size "abc", a setting SAC does not have), trained anyway (a compiled PPO's negative
learning rate), or were read as true ("maybe")."""

from __future__ import annotations

import importlib.util

import pytest

from helpers import ROOT, compose_cfg
from sdrl_bench import ConfigError
from sdrl_bench.cli.build import check_job

QUICK = ("experiment=quick_mountain_car", "rl.arms=[surrogate]")


@pytest.mark.parametrize("overrides, line", [
    (("agent.algo.learning_rate=-1",), "agent.algo.learning_rate: a number > 0 is required, got -1"),
    (("agent.algo.batch_size=abc",), "agent.algo.batch_size: an integer >= 1 is required, got 'abc'"),
    (("agent.algo.batch_size=1.5",), "agent.algo.batch_size: an integer >= 1 is required, got 1.5"),
    (("agent.algo.gamma=1.5",), "agent.algo.gamma: a number >= 0 and <= 1 is required, got 1.5"),
    (("agent.algo.learning_starts=-3",), "agent.algo.learning_starts: an integer >= 0 is required, got -3"),
    (("agent.algo.gradient_steps=-2",), "agent.algo.gradient_steps: an integer >= 0, or -1, is required, got -2"),
    (("agent.algo.train_freq=[1,episode]",), "agent.algo.train_freq: an integer >= 1 is required, got [1, 'episode']"),
    (("agent.algo.learning_starts=1e4",), None),  # SB3 takes a whole float here
    (("agent.algo.learning_starts=1.5",), "agent.algo.learning_starts: an integer >= 0 is required, got 1.5"),
    (("agent.algo.gamma=0",), None),
    (("agent.algo.ent_coef=-0.1",), "agent.algo.ent_coef: a number >= 0 or 'auto' is required, got -0.1"),
    (("+agent.algo.foo=1",), "agent.algo.foo: not a setting of SAC (its settings: policy, learning_rate, "),
    (("agent.n_envs=abc",), "agent.n_envs: a positive integer is required, got 'abc'"),
    (("torch_threads=0",), "torch_threads must be >= 1, got 0"),
    (("torch_threads=abc",), "torch_threads: an integer is required, got 'abc'"),
    (("seed=99999999999999999999",), "seed must be <= 4294967295, got 99999999999999999999"),
    (("rl.reuse_real_arm=maybe",), "rl.reuse_real_arm: true or false is required, got 'maybe'"),
    (("resume=maybe",), "resume: true or false is required, got 'maybe'"),  # was read as true
    (("progress_bar=nah",), "progress_bar: true or false is required, got 'nah'"),
    (("task=fit", "resume=no"), "resume: true or false is required, got 'no'"),  # a fit's too
    (("dataset.exclude_bound_transitions=abc",), "dataset.exclude_bound_transitions: true or false is required, got 'abc'"),
    (("rl.arms=surrogate",), "rl.arms: a list is required (e.g. rl.arms=[surrogate] or rl.arms=[surrogate,real]), got "
                            "'surrogate'"),
    (("agent=ppo", "env=lunar_lander", "experiment=paper_lunar_lander", "agent.algo.n_epochs=0"),
     "agent.algo.n_epochs: an integer >= 1 is required, got 0"),
    # a bad-input audit (2026-11-30): SB3 refused these once the agent was built, after the fit
    (("agent.algo.policy=FooPolicy",),
     "agent.algo.policy: 'FooPolicy' is not a policy of SAC (its policies: MlpPolicy, CnnPolicy, MultiInputPolicy)"),
    (("agent.algo.policy_kwargs.net_arch=big",), "agent.algo.policy_kwargs.net_arch: a list of layer sizes ([64, 64]) "
                                                 "or a mapping of them ({pi: [64, 64], vf: [64, 64]}) is required, got 'big'"),
    (("agent.algo.policy_kwargs.net_arch=[64,0]",), "agent.algo.policy_kwargs.net_arch: a list of layer sizes"),
    (("~agent.algo.policy_kwargs.net_arch", "+agent.algo.policy_kwargs.net_arch={pi:[32],qf:[64,64]}"), None),
    (("agent.algo.device=cuda99",), "agent.algo.device: Invalid device string: 'cuda99'"),
    # values a target's defaults type (check_value_types): read as true, or a traceback deep inside
    (("env.sindy.normalize_columns=maybe",),
     "optimizer.normalize_columns (from env.sindy.normalize_columns): true or false is required, got 'maybe'"),
    (("env.sindy.threshold=small",), "optimizer.threshold (from env.sindy.threshold): a number is required, got 'small'"),
    (("optimizer.max_iter=lots",), "optimizer.max_iter: a number is required, got 'lots'"),
    (("optimizer=ensemble", "optimizer.bagging=perhaps"), "optimizer.bagging: true or false is required, got 'perhaps'"),
    (("env.poly_degree=two",),
     "library.parts[0].library.degree (from env.poly_degree): a number is required, got 'two'"),
    (("env.poly_degree=-2",), "library (poly_trig): degree must be a nonnegative integer"),  # pysindy's, at fit time
    (("env=lunar_lander", "experiment=paper_lunar_lander", "env.spec.terrain=maybe"),
     "env.spec.terrain: true or false is required, got 'maybe'"),  # was terrain on
    (("collector=expert", "collector.policy.progress_bar=expert_sac"), None),  # bool | str: a string names the bar
    (("collector=expert", "env.expert.agent.algo.learning_rate=fast"),  # named where it was set, not under collector
     "env.expert.agent.algo.learning_rate: a number is required, got 'fast'"),
    (("optimizer.threshold=???",), "optimizer: Missing mandatory value: threshold"),  # OmegaConf's, not 'got ???'
    (("agent.action_space=foo",), "agent.action_space: continuous, discrete or any is required, got 'foo'"),
    (("collector=expert", "env.expert.budget=lots"), "env.expert.budget (collector.policy.budget): a positive integer is required, got 'lots'"),
    (("collector=expert", "env.expert.budget=0"), "env.expert.budget (collector.policy.budget): a positive integer is required, got 0"),
    (("env.trig_frequencies=[fast]",), "env.trig_frequencies: a list of numbers is required, got ['fast']"),  # was library.parts[1]
    (("library.parts.1.library.frequencies=[1,true]",),  # float(True) was a frequency of 1
     "library.parts[1].library.frequencies: a list of numbers is required, got [1, True]"),
    (("optimizer=ensemble", "optimizer.n_models=0"), "optimizer.n_models must be >= 1, got 0"),  # pysindy: n_candidates_to_drop
    (("+env.spec.state_low=[-1.2,null]",), None),  # a null bound is unbounded: a list of numbers may hold it
])
def test_a_bad_setting_is_one_line_naming_its_key(overrides, line):
    if line is None:  # a value SB3 trains with: accepted
        check_job(compose_cfg(*QUICK, *overrides))
        return
    with pytest.raises(ConfigError) as err:
        check_job(compose_cfg(*QUICK, *overrides))
    assert str(err.value).startswith(line) and "\n" not in str(err.value)


def test_a_jax_cache_dir_that_is_a_file_is_refused(tmp_path):
    (tmp_path / "cache").write_text("")
    with pytest.raises(ConfigError, match=r"^jax_cache_dir: .*cache is a file, not a folder$"):
        check_job(compose_cfg(*QUICK, f"jax_cache_dir={tmp_path / 'cache'}"))


@pytest.mark.skipif(importlib.util.find_spec("jax") is None, reason="the compiled agents' own check needs the [jax] extra")
@pytest.mark.jax
def test_the_compiled_ppo_refuses_a_negative_learning_rate():
    with pytest.raises(ConfigError, match=r"^agent.algo.learning_rate: a number > 0 is required, got -1$"):
        check_job(compose_cfg("experiment=fast_mountain_car", "agent=ppo_jax", "agent.algo.learning_rate=-1"))


@pytest.mark.parametrize("pack", ["quick_mountain_car", "paper_mountain_car", "paper_lunar_lander", "fast_mountain_car",
                                  "fast_lunar_lander", "dyna_mountain_car", "dyna_lunar_lander", "real_cartpole_swingup_sac"])
def test_the_shipped_packs_pass_the_checks(pack):
    """The domains are not stricter than the recipes the harness ships."""
    check_job(compose_cfg(f"experiment={pack}"))


def test_a_sweep_reading_hydras_own_values_is_left_to_its_jobs(tmp_path, monkeypatch):
    """``${hydra:...}`` resolves inside the running app only: the command line's check neither
    refuses it nor checks such a job (a traceback, before), in a -m sweep or a single run."""
    from sdrl_bench.cli.precheck import check_command_line

    monkeypatch.chdir(tmp_path)
    uri = f"tracking.uri=sqlite:///{tmp_path / 't.db'}"
    check_command_line(["-m", "task=fit", "seed=${hydra:job.num}", uri], "config", "sdrl_bench.cli.build:check_job")
    check_command_line(["tracking.experiment=${hydra:runtime.choices.env}", uri], "config", "sdrl_bench.cli.build:check_job")
    with pytest.raises(ConfigError, match=r"^collector.epsilon must be within \[0.0, 1.0\], got 2$"):
        check_command_line(["-m", "seed=0,1", "collector.epsilon=2", uri], "config", "sdrl_bench.cli.build:check_job")


@pytest.mark.skipif(importlib.util.find_spec("jax") is None, reason="the pack's compiled agent needs the [jax] extra")
@pytest.mark.jax
def test_a_sweeps_pack_from_the_users_config_dir_is_checked_with_it(tmp_path, monkeypatch):
    """A fidelity study's clusters compose their surrogates' configs again: with the user's
    --config-dir on the search path (it was refused: the pack not found). The pack trains the
    compiled PPO: without the [jax] extra its check says so (CI runs this in its jax step)."""
    import shutil

    from sdrl_bench.cli.precheck import check_command_line

    monkeypatch.chdir(tmp_path)
    (tmp_path / "myconf" / "experiment").mkdir(parents=True)
    shutil.copyfile(ROOT / "sdrl_bench" / "conf" / "experiment" / "fidelity_pendulum.yaml",
                    tmp_path / "myconf" / "experiment" / "my_fid.yaml")
    uri = f"tracking.uri=sqlite:///{tmp_path / 't.db'}"
    check_command_line(["--config-dir", "myconf", "-m", "experiment=my_fid", "seed=0,1", uri], "config",
                       "sdrl_bench.cli.build:check_job")
    with pytest.raises(ConfigError, match=r"^fidelity.train_steps must be >= 1, got 0$"):
        check_command_line(["--config-dir", "myconf", "-m", "experiment=my_fid", "seed=0,1", "fidelity.train_steps=0", uri],
                           "config", "sdrl_bench.cli.build:check_job")


def test_the_config_dir_stays_on_the_search_path_beside_a_given_searchpath(tmp_path, monkeypatch):
    """Hydra searches --config-dir and a command line's ``hydra.searchpath`` both; the check
    composed with the latter alone and refused the user's pack in --config-dir."""
    import shutil

    from sdrl_bench.cli.precheck import check_command_line

    monkeypatch.chdir(tmp_path)
    (tmp_path / "my conf" / "experiment").mkdir(parents=True)
    (tmp_path / "other" / "library").mkdir(parents=True)
    shutil.copyfile(ROOT / "sdrl_bench" / "conf" / "experiment" / "quick_mountain_car.yaml",
                    tmp_path / "my conf" / "experiment" / "my_quick.yaml")
    shutil.copyfile(ROOT / "sdrl_bench" / "conf" / "library" / "poly_trig.yaml", tmp_path / "other" / "library" / "mine.yaml")
    uri = f"tracking.uri=sqlite:///{tmp_path / 't.db'}"
    both = ["--config-dir", "my conf", "experiment=my_quick", f"hydra.searchpath=[file://{tmp_path / 'other'}]", uri]
    check_command_line([*both, "library=mine"], "config")
    with pytest.raises(ConfigError, match=r"^library=nosuch: no such option of 'library' \(options: .*mine"):
        check_command_line([*both, "library=nosuch"], "config")


def test_a_searchs_pack_named_without_its_folder_gets_the_search_paths_hint(tmp_path, monkeypatch):
    """``experiment=<study>`` right after a search, without ``hydra.searchpath``: the pack is found
    where the search wrote it and the line says what to add; with the hint's override it composes."""
    import shutil

    from omegaconf import OmegaConf

    from sdrl_bench.cli.precheck import SEARCH_EXPORTS, check_command_line

    app = OmegaConf.load(ROOT / "sdrl_bench" / "conf" / "search_app.yaml")
    assert app.study.export_dir == SEARCH_EXPORTS  # the default the hint looks in
    monkeypatch.chdir(tmp_path)
    (tmp_path / SEARCH_EXPORTS / "experiment").mkdir(parents=True)
    shutil.copyfile(ROOT / "sdrl_bench" / "conf" / "experiment" / "quick_mountain_car.yaml",
                    tmp_path / SEARCH_EXPORTS / "experiment" / "mountain_car-tpe-s0.yaml")
    uri = f"tracking.uri=sqlite:///{tmp_path / 't.db'}"
    with pytest.raises(ConfigError) as err:
        check_command_line(["experiment=mountain_car-tpe-s0", uri], "config")
    assert str(err.value).endswith("; a search wrote mlruns/search/experiment/mountain_car-tpe-s0.yaml: add "
                                   "'hydra.searchpath=[file://mlruns/search]'")
    check_command_line(["experiment=mountain_car-tpe-s0", "hydra.searchpath=[file://mlruns/search]", uri], "config")


def test_an_expert_cache_dir_that_is_a_file_is_refused_before_its_training(tmp_path):
    """Before, the expert trained (minutes), then its save failed."""
    (tmp_path / "f").write_text("mine")
    with pytest.raises(ConfigError) as err:
        check_job(compose_cfg(*QUICK, "collector=expert", f"collector.policy.cache_dir={tmp_path}/f/experts"))
    assert str(err.value) == (f"collector.policy.cache_dir: {tmp_path}/f is a file, not a folder (the expert would be "
                              f"cached in {tmp_path}/f/experts/mountain_car-sac-s0-n50000.zip)")
