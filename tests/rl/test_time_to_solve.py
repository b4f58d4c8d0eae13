"""Time-to-solve runs: the fast recipes on tiny budgets, stop-when-solved, and the accounting that
keeps evaluation time out of the training time (checked with clocks that count env steps)."""

from __future__ import annotations

import dataclasses
from collections import Counter
from functools import partial

import pytest
from mlflow.tracking import MlflowClient
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecNormalize

from helpers import compose_cfg, search
from sdrl_bench import ConfigError
from sdrl_bench.cli.build import build_fit_job
from sdrl_bench.cli.train import run_train
from sdrl_bench.envs.mountain_car import MountainCarSpec
from sdrl_bench.rl.agents import AgentConfig, RealEvalCallback, evaluate_real, real_vec_env, train

TINY_FAST = [
    "collector=heuristic", "agent.n_envs=4", "agent.algo.n_steps=16", "agent.algo.batch_size=32",
    "agent.algo.n_epochs=1", "rl.surrogate_steps=64", "rl.real_steps=64", "rl.eval_every=64",
    "rl.eval_episodes=1", "rl.final_episodes=2", "progress_bar=false",
]


def tiny_ppo(n_envs: int = 2) -> AgentConfig:
    algo = partial(PPO, policy="MlpPolicy", n_steps=16, batch_size=32, n_epochs=1, gamma=0.95,
                   policy_kwargs={"net_arch": [8]}, device="cpu")
    return AgentConfig(name="ppo", algo=algo, n_envs=n_envs, normalize_reward=True)


@pytest.mark.parametrize("pack,sde", [("fast_mountain_car", "True"), ("fast_lunar_lander", None)])
def test_fast_recipes_compose_and_train_both_arms_on_tiny_budgets(store, pack, sde):
    cfg = compose_cfg(f"experiment={pack}", f"tracking.uri={store}", *TINY_FAST)
    summary = run_train(cfg, build_fit_job(cfg), None)
    run = search(store).iloc[0]
    assert run["status"] == "FINISHED" and run["tags.agent"] == "ppo_fast"
    assert run["params.agent.normalize_reward"] == "True" and run["params.rl.stop_when_solved"] == "True"
    assert run.get("params.agent.algo.use_sde") == sde  # gSDE for continuous actions only
    # 4 envs x 16 steps: the budgets are whole rollouts, counted by the real env's own counter
    assert run["metrics.real/real_transitions_train"] == 64 and run["metrics.surrogate/surrogate_steps"] == 64
    assert run["metrics.surrogate/real_transitions_train"] == 0
    assert run["metrics.surrogate/real_transitions_model"] == cfg.n_transitions
    threshold = 90 if "mountain" in pack else 200
    for arm in ("surrogate", "real"):
        assert summary[f"{arm}/final_eval_episodes"] == 2
        curve = [m.value for m in MlflowClient(store).get_metric_history(run["run_id"], f"{arm}/curve_return_mean")]
        assert len(curve) >= 2  # before training and at its end
        # solved figures exist exactly when a learning-curve point reached the threshold
        assert (f"{arm}/solved_wall_seconds" in summary) == any(v >= threshold for v in curve)


def test_training_time_excludes_evaluation_time():
    """Clocks that count env steps: a training step costs 1 ms, an evaluation step 1 s of wall
    (2 ms and 3 s of CPU), recording a point (``on_point``, an MLflow write in a run) 5 s of
    both. Every training-time figure must be the training steps' share alone."""
    spec = MountainCarSpec()
    counts: Counter = Counter()
    wall = lambda: 0.001 * counts["train"] + 1.0 * counts["evaluate"] + 5.0 * counts["record"]  # noqa: E731
    cpu = lambda: 0.002 * counts["train"] + 3.0 * counts["evaluate"] + 5.0 * counts["record"]  # noqa: E731
    venv = real_vec_env(spec, 2, 0, counts, "train")
    callback = RealEvalCallback(spec, every=32, episodes=2, seed=0, counts=counts, clock=wall, cpu_clock=cpu,
                                on_point=lambda *_: counts.update(["record"]))
    result = train(tiny_ppo(), venv, 96, 0, callback)
    curve = callback.curve
    assert curve.steps == [0, 32, 64, 96] and counts["train"] == 96 and counts["record"] == 4
    assert counts["evaluate"] >= 4 * 2  # 4 evaluations of 2 episodes were played and counted apart
    assert result.wall_seconds == pytest.approx(0.001 * 96)
    assert result.cpu_seconds == pytest.approx(0.002 * 96)
    assert result.eval_wall_seconds == pytest.approx(1.0 * counts["evaluate"] + 5.0 * 4)
    assert curve.wall == pytest.approx([0.001 * s for s in curve.steps])
    # the fake clock moves only on env steps, so all training time is rollout time (updates: 0 s)
    assert result.rollout_wall_seconds == pytest.approx(0.001 * 96)
    # the agent trained on normalized rewards, the policy acts on raw observations
    env = result.model.get_env()
    assert isinstance(env, VecNormalize) and env.norm_reward and not env.norm_obs


def test_stop_when_solved_ends_training_at_the_first_solved_evaluation():
    spec = dataclasses.replace(MountainCarSpec(), solved_threshold=-1e9)  # any policy "solves" it
    counts: Counter = Counter()
    wall = lambda: 0.001 * counts["train"] + 1.0 * counts["evaluate"]  # noqa: E731
    callback = RealEvalCallback(spec, every=32, episodes=2, seed=0, counts=counts, stop_when_solved=True,
                                clock=wall, cpu_clock=wall)
    result = train(tiny_ppo(), real_vec_env(spec, 2, 0, counts, "train"), 10_000, 0, callback)
    assert callback.curve.first_solved_step == 0 and callback.curve.first_solved_wall == 0.0
    assert result.model.num_timesteps == 2  # one vector step, then stopped (budget: 10,000)
    assert counts["train"] == 2

    # and without the switch the same run trains on
    counts.clear()
    callback = RealEvalCallback(spec, every=32, episodes=1, seed=0, counts=counts, clock=wall, cpu_clock=wall)
    result = train(tiny_ppo(), real_vec_env(spec, 2, 0, counts, "train"), 64, 0, callback)
    assert result.model.num_timesteps == 64 and callback.curve.first_solved_step == 0


@pytest.mark.parametrize("value", ["maybe", "1"])
def test_a_bad_stop_when_solved_is_one_line_naming_the_key(store, value):
    cfg = compose_cfg("task=train", f"tracking.uri={store}", f"rl.stop_when_solved={value}")
    with pytest.raises(ConfigError, match=r"^rl\.stop_when_solved: true or false, got"):
        run_train(cfg, build_fit_job(cfg), None)


def test_a_confirmation_on_fresh_episodes_decides_whether_an_evaluation_at_the_threshold_counts():
    """``confirm_episodes``: an evaluation at the threshold stops training only if that many more
    real episodes, from reset seeds of their own, reach it too. The untrained policy's returns
    differ a little from start to start (its action costs), so a threshold between its curve
    mean and its confirmation mean makes the first hit fail its confirmation."""
    spec = dataclasses.replace(MountainCarSpec(), solved_threshold=-1e9)
    counts: Counter = Counter()
    wall = lambda: 0.001 * counts["train"] + 1.0 * counts["evaluate"]  # noqa: E731

    def run(spec, confirm_seed, budget=64):
        counts.clear()
        cb = RealEvalCallback(spec, every=10**6, episodes=2, seed=0, counts=counts, stop_when_solved=True,
                              clock=wall, cpu_clock=wall, confirm_episodes=3, confirm_seed=confirm_seed)
        res = train(tiny_ppo(), real_vec_env(spec, 2, 0, counts, "train"), budget, 0, cb)
        return cb, res

    # any policy solves: the step-0 evaluation is confirmed on 3 more episodes and stops training
    cb, res = run(spec, 1000)
    assert cb.curve.first_solved_step == 0 and res.model.num_timesteps == 2 and len(cb.curve.confirm_means) == 1
    # 2 curve + 3 confirmation episodes at step 0, 2 at the training's end (step 2: no confirmation
    # once solved), each to MountainCar's time limit
    assert counts["evaluate"] == 7 * 999 and len(cb.curve.means) == 2
    assert res.wall_seconds == pytest.approx(0.001 * 2)  # the confirmation's time is evaluation time
    # a confirmation start where the untrained policy does worse than on the curve's own two starts
    curve_mean = cb.curve.means[0]
    confirm_seed = next(s for s in range(1000, 1100, 3) if run(spec, s)[0].curve.confirm_means[0] < curve_mean)
    low = run(spec, confirm_seed)[0].curve.confirm_means[0]
    threshold = (curve_mean + low) / 2
    cb, res = run(dataclasses.replace(spec, solved_threshold=threshold), confirm_seed)
    assert cb.curve.means[0] >= threshold > cb.curve.confirm_means[0]  # a hit, not confirmed
    assert res.model.num_timesteps == 64  # so training went on to its budget
    # the point at the budget's end (trained: its actions, so their costs, shrink) hits and is confirmed
    assert len(cb.curve.confirm_means) == 2 and cb.curve.confirm_means[1] >= threshold
    assert cb.curve.first_solved_step == 64
    # the k-th confirmation plays its own starts: the second one begins 3 seeds further on
    again = evaluate_real(res.model, spec, 3, confirm_seed + 3).mean
    assert again == pytest.approx(cb.curve.confirm_means[1], abs=1e-9)


def test_confirm_episodes_reaches_the_run_and_a_bad_value_is_one_line(store):
    from sdrl_bench.cli.build import build_transfer_job, config_key, real_arm_key

    cfg = compose_cfg("experiment=fast_mountain_car", f"tracking.uri={store}", *TINY_FAST, "rl.confirm_episodes=2")
    assert build_transfer_job(cfg, build_fit_job(cfg)).confirm_episodes == 2
    plain = compose_cfg("experiment=fast_mountain_car", f"tracking.uri={store}", *TINY_FAST)
    # the default leaves every earlier run's keys as they were; a confirmation makes other runs
    assert config_key(plain) != config_key(cfg) and real_arm_key(plain) != real_arm_key(cfg)
    stripped = compose_cfg("experiment=fast_mountain_car", f"tracking.uri={store}", *TINY_FAST, "~rl.confirm_episodes")
    assert config_key(stripped) == config_key(plain) and real_arm_key(stripped) == real_arm_key(plain)
    run_train(cfg, build_fit_job(cfg), None)
    run = search(store).iloc[0]
    assert run["status"] == "FINISHED" and run["params.rl.confirm_episodes"] == "2"
    bad = compose_cfg("experiment=fast_mountain_car", f"tracking.uri={store}", *TINY_FAST, "rl.confirm_episodes=-1")
    with pytest.raises(ConfigError, match=r"^rl\.confirm_episodes must be >= 0, got -1$"):
        build_transfer_job(bad, build_fit_job(bad))
