"""RL transfer runs with tiny budgets, end to end into a temp MLflow store."""

from __future__ import annotations

import pandas as pd
import pytest
from mlflow.tracking import MlflowClient

from helpers import ROOT, compose_cfg, search
from sdrl_bench import ConfigError
from sdrl_bench.cli.build import build_fit_job
from sdrl_bench.cli.train import run_train

TINY_SAC = [
    "agent.algo.batch_size=32", "agent.algo.train_freq=16", "agent.algo.gradient_steps=4",
    "agent.algo.policy_kwargs.net_arch=[16]", "rl.eval_every=64", "rl.eval_episodes=1",
    "rl.final_episodes=2", "progress_bar=false",
]


def train(store, *overrides):
    cfg = compose_cfg("task=train", f"tracking.uri={store}", *TINY_SAC, *overrides)
    return run_train(cfg, build_fit_job(cfg), None)


def test_real_arm_accounting_adds_up(store, tmp_path):
    summary = train(store, "rl.arms=[real]", "rl.real_steps=64")
    run = search(store).iloc[0]
    assert run["status"] == "FINISHED" and run["tags.sdrl.kind"] == "transfer"
    assert run["metrics.real/real_transitions_train"] == 64  # SB3 stepped the counted env 64 times
    assert run["metrics.real/real_transitions_model"] == 0 and run["metrics.real/surrogate_steps"] == 0
    assert run["metrics.real/total_steps"] == 64
    client = MlflowClient(store)
    final = pd.read_csv(client.download_artifacts(run["run_id"], "final_eval/real.csv", str(tmp_path)))
    curve = pd.read_csv(client.download_artifacts(run["run_id"], "curves/real.csv", str(tmp_path)))
    assert len(final) == 2 and run["metrics.real/final_return_mean"] == pytest.approx(final["return"].mean())
    assert list(curve["train_steps"]) == [0, 64]  # before training and at the end
    # evaluation episodes are kept apart from training interactions
    assert run["metrics.real/eval_episodes"] == 2 and run["metrics.real/eval_steps"] >= 2
    assert run["metrics.real/final_eval_steps"] >= 2
    history = client.get_metric_history(run["run_id"], "real/curve_return_mean")
    assert [m.step for m in history] == [0, 64]
    assert summary["real/success_rate"] == run["metrics.real/success_rate"]
    listed = {a.path for d in ("agents", "figures") for a in client.list_artifacts(run["run_id"], d)}
    assert {"agents/real.zip", "figures/learning_curves.png", "figures/policy_maps.png"} <= listed


def test_real_arm_is_reused_by_a_later_run_with_the_same_key(store, capsys):
    train(store, "rl.arms=[real]", "rl.real_steps=32")
    assert "note:" not in capsys.readouterr().out  # trained, to its budget: nothing to add
    train(store, "rl.arms=[real]", "rl.real_steps=32", "library=polynomial")  # another surrogate variant
    runs = search(store).sort_values("start_time")
    first, second = runs.iloc[0], runs.iloc[1]
    printed = " ".join(capsys.readouterr().out.split())
    assert (f"note: the real arm is reused from run {first['run_id']} (the same env, agent, budgets and seed), not "
            "trained again; rl.reuse_real_arm=false trains it") in printed
    assert second["tags.real_arm_reused_from"] == first["run_id"]
    assert second["metrics.real/final_return_mean"] == first["metrics.real/final_return_mean"]
    assert second["tags.real_arm_key"] == first["tags.real_arm_key"]
    listed = {a.path for d in ("curves", "figures") for a in MlflowClient(store).list_artifacts(second["run_id"], d)}
    assert {"curves/real.csv", "figures/learning_curves.png", "figures/policy_maps.png"} <= listed


def test_a_budget_the_agent_rounds_up_is_said_beside_the_table(store, capsys):
    """SAC collects in steps of ``train_freq`` (16 here): a budget of 40 real steps trains 48, all
    counted; the console says so instead of leaving 40 in the banner as the story."""
    summary = train(store, "rl.arms=[real]", "rl.real_steps=40")
    assert summary["real/real_transitions_train"] == 48
    printed = " ".join(capsys.readouterr().out.split())
    assert ("note: the real arm trained 48 steps for rl.real_steps=40: the agent rounds a budget up to whole "
            "rollouts or training intervals, and every step is counted above") in printed


@pytest.mark.parametrize("overrides,message", [
    (["agent=dqn"], "agent=dqn: DQN needs discrete actions but env 'mountain_car' has continuous"),
    (["env=lunar_lander", "agent=sac"], "agent=sac: SAC needs continuous actions but env 'lunar_lander' has discrete"),
    (["rl.surrogate_steps=0"], "rl.surrogate_steps must be positive, got 0"),
    (["rl.real_steps=-5"], "rl.real_steps must be positive, got -5"),
    (["rl.arms=[simulator]"], "rl.arms: ['simulator']"),
])
def test_bad_rl_config_fails_before_training(store, overrides, message):
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("]", r"\]")):
        train(store, *overrides)
    try:
        assert len(search(store)) == 0  # nothing started
    except Exception:
        pass  # the experiment was never even created


def test_expert_is_trained_once_then_reused(tmp_path):
    from sdrl_bench.envs.mountain_car import MountainCarSpec

    cfg = compose_cfg("collector=expert", "env.expert.budget=64", f"collector.policy.cache_dir={tmp_path}",
                      "progress_bar=false", *[o.replace("agent.", "env.expert.agent.") for o in TINY_SAC[:4]])
    spec = MountainCarSpec()
    expert = build_fit_job(cfg).policy
    model, cached = expert.load_or_train(spec)
    assert not cached and model.num_timesteps == 64
    path = expert.path(spec)
    assert path.name == "mountain_car-sac-s0-n64.zip"
    stamp = path.stat().st_mtime_ns
    again = build_fit_job(cfg).policy
    model2, cached2 = again.load_or_train(spec)
    assert cached2 and path.stat().st_mtime_ns == stamp
    obs = spec.make_env().reset(seed=0)[0]
    assert (model.predict(obs, deterministic=True)[0] == model2.predict(obs, deterministic=True)[0]).all()


def test_expert_collector_rejects_an_agent_the_env_cannot_use():
    cfg = compose_cfg("collector=expert", "env=lunar_lander", "agent@env.expert.agent=sac")
    from sdrl_bench.pipeline import check

    with pytest.raises(ConfigError, match="SAC needs continuous actions"):
        check(build_fit_job(cfg))


def test_both_arms_end_to_end_with_accounting_and_policy_maps(store, tmp_path):
    summary = train(store, "rl.surrogate_steps=64", "rl.real_steps=64")
    run = search(store).iloc[0]
    assert run["status"] == "FINISHED"
    # surrogate arm: the model's real transitions are what the collector's counted envs stepped
    assert run["metrics.surrogate/real_transitions_model"] == 75 == run["metrics.n_transitions"]
    assert run["metrics.surrogate/real_transitions_train"] == 0
    assert run["metrics.surrogate/surrogate_steps"] == 64
    assert run["metrics.surrogate/total_steps"] == 75 + 64  # as the paper counts (65,075 = 75 + 65,000)
    assert run["metrics.real/real_transitions_train"] == 64 and run["metrics.real/total_steps"] == 64
    assert run["metrics.surrogate/surrogate_diverged_episodes"] == 0
    assert run["metrics.mse/v"] < 2e-18  # the surrogate was the exact law
    assert 0.0 <= summary["policy_map_agreement"] <= 2.0
    assert run["metrics.policy_map_agreement"] == pytest.approx(summary["policy_map_agreement"])
    client = MlflowClient(store)
    listed = {a.path for d in ("agents", "model", "data", "curves") for a in client.list_artifacts(run["run_id"], d)}
    assert {"agents/surrogate.zip", "agents/real.zip", "model/model.json", "curves/surrogate.csv",
            "curves/real.csv", "data/mountain_car_transitions.csv"} <= listed
    for name in ("fit_wall_seconds", "train_wall_seconds", "evaluate_wall_seconds", "collect_wall_seconds"):
        assert run[f"metrics.surrogate/{name}"] >= 0


def test_ppo_in_a_vectorized_surrogate_logs_sb3_metrics_through_the_kvwriter(store):
    cfg = compose_cfg("task=train", f"tracking.uri={store}", "agent=ppo", "agent.n_envs=4", "agent.algo.n_steps=16",
                      "agent.algo.batch_size=32", "+agent.algo.policy_kwargs={net_arch:[16]}", "rl.arms=[surrogate]",
                      "rl.surrogate_steps=128", "rl.eval_every=64", "rl.eval_episodes=1", "rl.final_episodes=1",
                      "progress_bar=false")
    run_train(cfg, build_fit_job(cfg), None)
    run = search(store).iloc[0]
    assert run["metrics.surrogate/surrogate_steps"] == 128
    client = MlflowClient(store)
    history = client.get_metric_history(run["run_id"], "surrogate/sb3/time/total_timesteps")
    assert [m.value for m in history] == [64, 128]  # one rollout of 4 envs x 16 steps per dump
    assert "metrics.surrogate/sb3/train/value_loss" in run.index


def test_surrogate_steps_count_what_sac_took_and_the_fit_shares_names_with_fit_runs(store):
    """SAC with train_freq 32 and a budget of 100 steps takes 128 (whole rounds of 32): the
    accounting counts 128. The fit inside the transfer run is logged under the names (and
    values) a fit run of the same config logs: ``mse/x``, not ``fit/mse/x``; only its real-step
    accounting goes under ``fit/`` (the run's headlines are its arms')."""
    from sdrl_bench.cli.main import run_fit
    from sdrl_bench.tracking import fit_metrics
    from sdrl_bench.rl.accounting import PREFIXES

    summary = train(store, "rl.arms=[surrogate]", "rl.surrogate_steps=100", "agent.algo.train_freq=32",
                    "rl.eval_every=100")
    assert summary["surrogate/surrogate_steps"] == 128 and summary["surrogate/total_steps"] == 75 + 128
    fit = run_fit(compose_cfg(f"tracking.uri={store}"))
    runs = search(store).set_index("tags.sdrl.kind")
    transfer, fitrun = runs.loc["transfer"], runs.loc["fit"]
    assert transfer["metrics.surrogate/surrogate_steps"] == 128
    names = fit_metrics(fit)
    accounting = [k for k in names if k.startswith(PREFIXES)]
    assert "real_steps/this_run" in accounting
    assert sorted(c for c in runs.columns if c.startswith("metrics.fit/")) == sorted(f"metrics.fit/{k}" for k in accounting)
    for k, v in names.items():
        if not k.endswith("_seconds"):
            there = f"metrics.fit/{k}" if k in accounting else f"metrics.{k}"
            assert transfer[there] == fitrun[f"metrics.{k}"] == pytest.approx(v, rel=1e-12, abs=0), k
    client = MlflowClient(store)
    run = client.get_run(transfer["run_id"])
    assert {i.tags[0].value for i in run.inputs.dataset_inputs} == {"training", "testing", "prior:knowledge"}
    assert len(run.outputs.model_outputs) == 1 and "cos(3 x)" in run.data.tags["mlflow.note.content"]
    assert len(run.data.params) <= 40 and run.data.params["agent.algo.train_freq"] == "32"
    assert run.data.params["tracking.uri"] == store


def test_sigterm_during_training_leaves_a_killed_run_that_keeps_its_fit(store, tmp_path):
    """The fit is logged before the agent trains: a run stopped by SIGTERM mid-training ends
    KILLED and still holds the fit's datasets, model and equations (and system metrics)."""
    import os
    import signal
    import subprocess
    import sys
    import time

    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p)}
    env.pop("MLFLOW_TRACKING_URI", None)
    proc = subprocess.Popen([sys.executable, "-m", "sdrl_bench.cli.main", "task=train", f"tracking.uri={store}",
                             "rl.arms=[surrogate]", "rl.surrogate_steps=1000000", "rl.eval_every=500000", *TINY_SAC[:4],
                             "progress_bar=false"], cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    client = MlflowClient(store)
    deadline, run = time.monotonic() + 120, None
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            time.sleep(1)
            try:
                runs = search(store)
            except Exception:
                continue
            if len(runs):
                run = client.get_run(runs.iloc[0]["run_id"])
                if run.outputs.model_outputs and "system/cpu_utilization_percentage" in run.data.metrics:
                    break
        assert proc.poll() is None, proc.stdout.read()[-2000:]
        proc.send_signal(signal.SIGTERM)
        out = proc.communicate(timeout=60)[0]
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode != 0
    assert "MLflow run " in out.splitlines()[1]  # the run id came first, before any training
    run = client.get_run(run.info.run_id)
    assert run.info.status == "KILLED"
    assert {i.tags[0].value for i in run.inputs.dataset_inputs} == {"training", "testing", "prior:knowledge"}
    assert len(run.outputs.model_outputs) == 1
    assert "cos(3 x)" in run.data.tags["mlflow.note.content"] and run.data.metrics["mse/v"] < 2e-18
    assert "surrogate/final_return_mean" not in run.data.metrics  # training never finished


@pytest.mark.slow
def test_sac_learns_mountain_car_from_the_sindy_surrogate_alone(store):
    """Learnability: SAC (zoo settings) trained 20,000 steps only inside the surrogate fitted
    from 75 heuristic transitions reaches the goal in the real env (the quick pack, seed 0)."""
    cfg = compose_cfg("experiment=quick_mountain_car", f"tracking.uri={store}", "rl.arms=[surrogate]",
                      "rl.eval_every=20000", "rl.eval_episodes=1", "progress_bar=false")
    summary = run_train(cfg, build_fit_job(cfg), None)
    assert summary["surrogate/real_transitions_model"] == 75
    assert summary["surrogate/final_return_mean"] >= 90
    assert summary["surrogate/success_rate"] == 1.0
