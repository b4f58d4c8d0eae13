"""studies/compiled_recipe.py --search: an Optuna study of the compiled loop's PPO recipe in the
surrogate. Its first trial is the pack's own recipe, a rerun adds trials to the same stored study,
a rerun with other settings is refused, and each trial records the seeds it solved and its
measured wall (real training in the surrogate, tiny budgets)."""

from __future__ import annotations

from argparse import Namespace

import pytest

from helpers import load_script

pytest.importorskip("jax")
pytest.importorskip("optax")
optuna = pytest.importorskip("optuna")
pytestmark = pytest.mark.jax


@pytest.fixture(scope="module")
def study_mod():
    return load_script("studies/compiled_recipe.py")


def test_a_search_starts_from_the_pack_and_a_rerun_adds_to_the_same_study(study_mod, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    bench = study_mod.Bench("fast_mountain_car", episodes=2, confirm=2, cache_dir=str(tmp_path / "jax_cache"))
    assert len(bench.fit.data.states) == 75 and bench.threshold == 90.0
    args = Namespace(storage=f"sqlite:///{tmp_path / 'optuna.db'}", study="t", sampler_seed=0,
                     experiment="fast_mountain_car", seeds="100", budget=4096, episodes=2, confirm=2, penalty=2.0,
                     calls=1, trials=1, total=False)
    study_mod.run_search(args, bench, [100])
    study = optuna.load_study(study_name="t", storage=args.storage)
    (first,) = study.trials
    assert first.params == study_mod.pack_params(bench.agent)  # the pack's own recipe, enqueued
    assert first.params["n_envs"] == 128 and first.params["n_minibatches"] == 4 and first.params["n_epochs"] == 4
    assert "agent.algo.batch_size=1024" in first.user_attrs["overrides"].split(",") and first.user_attrs["pack"]
    assert first.user_attrs["solved"] == 0  # one rollout of 4,096 steps does not solve MountainCar
    assert first.value >= 2000.0  # an unsolved seed counts the 2 s penalty at least
    assert first.user_attrs["iteration_ms"] > 0.0

    study_mod.run_search(args, bench, [100])  # a rerun: one more trial in the same study, sampled
    study = optuna.load_study(study_name="t", storage=args.storage)
    assert [t.number for t in study.trials] == [0, 1] and study.trials[1].state.is_finished()
    assert study.trials[1].params != first.params
    assert study.user_attrs["budget"] == 4096 and study.user_attrs["real_transitions"] == 75

    args.budget = 8192
    with pytest.raises(SystemExit, match="made with budget=4096"):
        study_mod.run_search(args, bench, [100])


def test_a_recipe_outside_the_search_space_is_not_enqueued(study_mod):
    from sdrl_bench.cli.build import compose

    assert study_mod.pack_params(compose(["experiment=fast_lunar_lander", "agent=ppo_jax"]).agent) is None  # 32 minibatches
    got = study_mod.pack_params(compose(["experiment=compiled_mountain_car"]).agent)
    assert got == {"n_envs": 64, "n_steps": 32, "n_minibatches": 4, "n_epochs": 3, "learning_rate": 1.04e-2,
                   "gamma": 0.995, "gae_lambda": 0.95, "clip_range": 0.1, "log_std_init": -0.259}
