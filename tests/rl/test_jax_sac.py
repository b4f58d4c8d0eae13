"""agent=sac_jax (rl/jax_sac.py, rl/jax_sac_agent.JaxSAC): SAC with its gradient steps compiled by jax.
Its gradient steps are SB3's: from the same weights, batches and noise, three steps of SB3's own
``SAC.train`` and of ``jax_sac.gradient_step`` give the same networks (gSDE with a fixed entropy
coefficient, as the package's recipe; plain Gaussian with a learned one, as SB3's default). The
agent collects as SB3's off-policy loop does (the callback after every vector step, every real
step counted), learns MountainCar's surrogate, saves and loads, and runs both arms from the CLI
with its compile recorded; a setting it lacks is one line before any run."""

from __future__ import annotations

import copy
import re
import zipfile
from collections import Counter

import numpy as np
import pytest

jax = pytest.importorskip("jax")
pytest.importorskip("optax")
pytestmark = pytest.mark.jax

import gymnasium as gym  # noqa: E402
import torch as th  # noqa: E402
from stable_baselines3 import SAC  # noqa: E402

from helpers import compose_cfg, held_sde_noise, run_cli, search  # noqa: E402
from sdrl_bench.cli.build import build_fit_job, instantiate_key  # noqa: E402
from sdrl_bench.pipeline import fit_dynamics  # noqa: E402
from sdrl_bench.rl import jax_sac  # noqa: E402
from sdrl_bench.rl.agents import RealEvalCallback, make_agent, real_vec_env, train  # noqa: E402
from sdrl_bench.rl.jax_sac_agent import JaxSAC  # noqa: E402
from sdrl_bench.rl.transfer import surrogate_vec_env  # noqa: E402

SMALL = ["experiment=quick_mountain_car", "agent=sac_jax", "agent.algo.batch_size=64"]
"""The README's main job with the compiled SAC, batches of 64."""

RECIPE = dict(ent_coef=0.1, train_freq=32, gradient_steps=32, gamma=0.9999, tau=0.01, use_sde=True,
              policy_kwargs={"log_std_init": -3.67, "net_arch": [64, 64]}, buffer_size=50000)
"""agent=sac's settings (gSDE, a fixed entropy coefficient)."""
DEFAULTS = dict(policy_kwargs={"net_arch": [32, 32]})
"""SB3's SAC defaults (plain Gaussian, ent_coef 'auto', tau 0.005), smaller networks."""
NO_ENTROPY = dict(ent_coef=0.0, policy_kwargs={"net_arch": [32, 32]})
"""A fixed coefficient of 0: no entropy term (SB3 takes it; its log would be -inf)."""


def _linear(m: th.nn.Linear) -> tuple[np.ndarray, np.ndarray]:
    return m.weight.detach().numpy().T.copy(), m.bias.detach().numpy().copy()


def _layers(seq: th.nn.Sequential) -> list:
    return [_linear(m) for m in seq if isinstance(m, th.nn.Linear)]


def nets_of(sac: SAC, cfg: jax_sac.SACConfig) -> jax_sac.Nets:
    """An SB3 SAC's networks as ``jax_sac.Nets``."""
    a = sac.actor
    mu = a.mu[0] if isinstance(a.mu, th.nn.Sequential) else a.mu  # gSDE: Linear then Hardtanh (clip_mean)
    actor = {"hidden": _layers(a.latent_pi), "mu": _linear(mu),
             "log_std": a.log_std.detach().numpy().copy() if cfg.use_sde else _linear(a.log_std)}
    fixed = cfg.alpha_init()
    log_alpha = (sac.log_ent_coef.detach().numpy()[0] if sac.log_ent_coef is not None
                 else np.log(fixed) if fixed > 0 else -np.inf)
    return jax_sac.Nets(actor, [_layers(q) for q in sac.critic.q_networks],
                        [_layers(q) for q in sac.critic_target.q_networks], np.float32(log_alpha))


@pytest.mark.parametrize("kwargs", [RECIPE, DEFAULTS, NO_ENTROPY],
                         ids=["gsde-fixed-alpha", "gaussian-auto-alpha", "gaussian-no-entropy"])
def test_three_gradient_steps_are_sb3s(kwargs):
    """SB3 fills its replay buffer without training (learning_starts beyond the steps), then takes
    three gradient steps (``SAC.train``), each with numpy's and torch's generators seeded. The same
    batches (SB3's draws, taken again from the same seed) and noise (gSDE: the exploration matrix
    SB3 drew, over its std; plain: torch's two draws again) go through ``jax_sac.gradient_step``
    from SB3's starting weights. Every parameter agrees to 1e-6 after steps that moved them by
    about 1e-3; the losses SB3 logs agree too."""
    batch, n_steps = 64, 3
    sac = SAC("MlpPolicy", gym.make("MountainCarContinuous-v0"), seed=0, device="cpu", batch_size=batch,
              **{**copy.deepcopy(kwargs), "learning_starts": 10**6})
    sac.learn(300)  # collection only
    cfg = jax_sac.SACConfig.from_kwargs({**kwargs, "batch_size": batch}, 1)
    start = nets_of(sac, cfg)
    step = jax.jit(lambda s, b, n: jax_sac.gradient_step(cfg, 1, s, b, n, True))
    state = jax_sac.init_state(cfg, start)
    rb = sac.replay_buffer
    for k in range(n_steps):
        seed = 11 + k
        np.random.seed(seed)
        rows, envs = np.random.randint(0, rb.pos, size=batch), np.random.randint(0, 1, size=batch)
        data = jax_sac.Batch(rb.observations[rows, envs], rb.actions[rows, envs], rb.rewards[rows, envs],
                             rb.next_observations[rows, envs], rb.dones[rows, envs] * (1 - rb.timeouts[rows, envs]))
        log_std = sac.actor.log_std.detach().numpy().copy() if cfg.use_sde else None
        if not cfg.use_sde:
            th.manual_seed(seed)
            draw = th.distributions.Normal(th.zeros(batch, 1), th.ones(batch, 1))
            noise = (draw.rsample().numpy(), draw.rsample().numpy())
        np.random.seed(seed)
        th.manual_seed(seed)
        sac.train(gradient_steps=1, batch_size=batch)
        if cfg.use_sde:
            m = sac.actor.action_dist.exploration_mat.detach().numpy() / np.exp(log_std)
            noise = (m, m)
        state, stats = step(state, data, noise)
        logged = sac.logger.name_to_value
        assert float(stats["critic_loss"]) == pytest.approx(logged["train/critic_loss"], rel=1e-5)
        assert float(stats["actor_loss"]) == pytest.approx(logged["train/actor_loss"], rel=1e-4, abs=1e-6)
        assert float(stats["ent_coef"]) == pytest.approx(logged["train/ent_coef"], rel=1e-6)
    ours = [np.asarray(x) for x in jax.tree_util.tree_leaves(state.nets)]
    sb3 = jax.tree_util.tree_leaves(nets_of(sac, cfg))
    moved = [np.abs(b - a).max() for a, b in zip(jax.tree_util.tree_leaves(start), sb3, strict=True)
             if np.isfinite(a).all()]  # not a fixed 0's log-alpha, -inf on both sides
    assert len(ours) == len(sb3) == (7 if cfg.use_sde else 8) + 2 * 12 + 1  # actor, critics, targets, log-alpha
    for x, y in zip(ours, sb3, strict=True):
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-6)
    assert max(moved) > 5e-4  # the steps moved the weights: agreement is not the starting point's
    if cfg.learns_alpha:
        assert abs(float(state.nets.log_alpha)) > 5e-4


@pytest.fixture(scope="module")
def fitted():
    cfg = compose_cfg(*SMALL)
    res = fit_dynamics(build_fit_job(cfg))
    return cfg, res.model, res.spec


def test_in_real_envs_it_collects_as_sb3_and_every_step_is_counted(fitted):
    """Two collections of 32 steps, a callback step after every env step, 32 gradient steps after
    each; the replay buffer holds the 64 transitions, actions in [-1, 1]."""
    cfg, _, spec = fitted
    agent = instantiate_key(cfg.agent, "agent")
    counts: Counter = Counter()
    venv = real_vec_env(spec, 1, seed=3, counts=counts)
    cb = RealEvalCallback(spec, every=32, episodes=1, seed=5, counts=counts)
    result = train(agent, venv, 64, seed=0, callback=cb)
    sac = result.model
    assert isinstance(sac, JaxSAC) and sac.num_timesteps == 64 and counts["train"] == 64
    assert sac.gradient_steps_done == 64 and sac.compile_programs == 1 and sac.rollout_compiles == 0
    assert cb.curve.steps == [0, 32, 64]  # at the start, then after each collection's last step
    assert sac._replay.size == 64 and np.abs(sac._replay.data["actions"][:64]).max() <= 1.0
    obs = sac._replay.data["obs"][1:64, 0]
    assert np.array_equal(obs, sac._replay.data["next_obs"][:63, 0])  # consecutive steps: no episode ended


def test_it_learns_the_surrogate_and_a_saved_agent_acts_the_same(fitted, tmp_path):
    """3,072 steps of the package's recipe (batches of 64) in MountainCar's surrogate: the critic's
    loss is finite, the actor's mean moved; the same seed trains the same networks, another seed
    others; a saved agent loads and acts the same, with its optimisers' states."""
    cfg, model, spec = fitted
    agent = instantiate_key(cfg.agent, "agent")

    def trained(seed: int) -> JaxSAC:
        sac = make_agent(agent, surrogate_vec_env(model, spec, 1, seed), seed)
        return sac.learn(3072)

    sac = trained(0)
    assert sac.num_timesteps == 3072 and sac.gradient_steps_done == 3072
    leaves = [np.asarray(x) for x in jax.tree_util.tree_leaves(sac.state.nets)]
    fresh = jax.tree_util.tree_leaves(jax_sac.init_nets(0, sac.cfg, 2, 1))
    assert all(np.isfinite(x).all() for x in leaves)
    assert max(np.abs(a - b).max() for a, b in zip(leaves, fresh, strict=True)) > 1e-2
    again = [np.asarray(x) for x in jax.tree_util.tree_leaves(trained(0).state.nets)]
    assert all(np.array_equal(a, b) for a, b in zip(leaves, again, strict=True))
    other = [np.asarray(x) for x in jax.tree_util.tree_leaves(trained(1).state.nets)]
    assert not np.array_equal(leaves[0], other[0])
    path = tmp_path / "sac.zip"
    sac.save(path)
    back = JaxSAC.load(path)
    obs = np.random.default_rng(0).uniform([-1.2, -0.07], [0.6, 0.07], (50, 2)).astype(np.float32)
    want, _ = sac.predict(obs, deterministic=True)
    got, _ = back.predict(obs, deterministic=True)
    assert np.array_equal(want, got) and back.num_timesteps == 3072
    # Adam's moments and step counts come back too (SB3's save keeps its optimisers)
    kept, loaded = (jax.tree_util.tree_leaves(a.state[1:]) for a in (sac, back))
    assert len(kept) == len(loaded) and all(np.array_equal(a, b) for a, b in zip(kept, loaded, strict=True))
    assert int(back.state.actor_opt[0].count) == 3072 and np.abs(np.asarray(back.state.critic_opt[0].nu[0][0][0])).max() > 0
    assert np.abs(want).max() <= 1.0 and want.shape == (50, 1)
    sampled, _ = sac.predict(obs)
    assert not np.array_equal(sampled, want) and np.abs(sampled).max() <= 1.0
    assert sac.cfg.use_sde
    held_sde_noise(back, obs[0], want[0], copies=5)  # the recipe has one env copy: drawn for five


def test_no_entropy_trains_and_a_loaded_agent_refuses_an_env_or_file_that_does_not_fit(fitted, tmp_path):
    """ent_coef=0 (SB3 takes it) builds and trains; loading to train on checks the env against
    the file (copies, observation size, action bounds, reward scaling) and the file itself (its
    parameters, a file cut short), each one error naming it; the callback's locals are SB3's
    (the absolute target, the actions by SB3's names)."""
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    from sdrl_bench import ConfigError

    cfg, model, spec = fitted
    seen: list = []

    class Locals(BaseCallback):
        def _on_training_start(self) -> None:
            seen.append(("start", self.locals["total_timesteps"]))

        def _on_step(self) -> bool:
            seen.append((self.locals["actions"].shape, self.locals["buffer_actions"].shape, len(self.locals["dones"])))
            return True

    env = surrogate_vec_env(model, spec, 1, 0)
    sac = JaxSAC(env=env, seed=0, ent_coef=0.0, learning_starts=0, train_freq=16, gradient_steps=16, batch_size=16,
                 policy_kwargs={"net_arch": [16, 16]})
    sac.learn(32, callback=Locals())
    sac.learn(32, callback=Locals(), reset_num_timesteps=False)
    assert sac.gradient_steps_done == 64 and float(sac.state.nets.log_alpha) == -np.inf
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree_util.tree_leaves(sac.state.nets.critics))
    assert [x for x in seen if x[0] == "start"] == [("start", 32), ("start", 64)]  # SB3's: the target, not the increment
    assert seen[1] == ((1, 1), (1, 1), 1)
    path = tmp_path / "sac.zip"
    sac.save(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sac.zip"]  # no temporary file left beside it
    assert JaxSAC.load(path, env=surrogate_vec_env(model, spec, 1, 1)).num_timesteps == 64
    wrong = {
        "trained with 1 env copies, the env has 2": surrogate_vec_env(model, spec, 2, 1),
        "observations of size 2, the env's are 3": make_vec_env("Pendulum-v1", n_envs=1, seed=0),
        "acts in a Box of size 1 between [-1.0] and [1.0]": make_vec_env(
            lambda: gym.wrappers.RescaleAction(gym.make("MountainCarContinuous-v0"), np.float32(-2), np.float32(2)), n_envs=1),
        "trained without reward scaling": VecNormalize(surrogate_vec_env(model, spec, 1, 1)),
    }
    for message, other in wrong.items():
        with pytest.raises(ConfigError, match=re.escape(message)):
            JaxSAC.load(path, env=other)
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(tmp_path / "bare.zip", "w") as dst:
        dst.writestr("config.json", src.read("config.json"))  # the parameters missing: not fresh weights
    with pytest.raises(ValueError, match="no params.npz in it"):
        JaxSAC.load(tmp_path / "bare.zip")
    data = path.read_bytes()
    (tmp_path / "cut.zip").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"cut\.zip: not a (whole|readable) JaxSAC agent file"):
        JaxSAC.load(tmp_path / "cut.zip")


def test_the_cli_runs_both_arms_with_it_and_records_the_compile(store, tmp_path):
    res = run_cli(*SMALL, "rl.surrogate_steps=512", "rl.real_steps=512", "rl.eval_every=512", "rl.eval_episodes=1",
                  "rl.final_episodes=1", "rl.stop_when_solved=false", "seed=0", "progress_bar=false",
                  f"tracking.uri={store}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    run = search(store, filter_string="tags.`sdrl.kind` = 'transfer'").iloc[0]
    assert run["tags.agent"] == "sac_jax" and run["status"] == "FINISHED"
    for arm in ("surrogate", "real"):
        assert 0 < run[f"metrics.{arm}/compile_wall_seconds"] < run[f"metrics.{arm}/train_wall_seconds"]
        assert run[f"metrics.{arm}/compile_programs"] == 1 and run[f"metrics.{arm}/rollout_compiles"] == 0
        assert run[f"metrics.{arm}/sb3/train/critic_loss"] >= 0
        assert run[f"metrics.{arm}/sb3/train/n_updates"] == 512
        assert run[f"metrics.{arm}/xla_pool_threads"] == 1
    assert run["metrics.real/real_transitions_train"] == 512
    from mlflow.tracking import MlflowClient

    path = MlflowClient(store).download_artifacts(run["run_id"], "agents/surrogate.zip", str(tmp_path))
    assert JaxSAC.load(path).num_timesteps == 512


@pytest.mark.parametrize("override,message", [
    ("agent.algo.gradient_steps=-1", "gradient_steps must be >= 0"),  # SB3's 'as many as collected'
    ("+agent.algo.replay_buffer_class=null", "agent.algo sets ['replay_buffer_class']"),
    ("+agent.normalize_reward=true", "agent.normalize_reward: the compiled SAC"),
    ("agent.algo.ent_coef=automatic", "ent_coef: a number, 'auto' or 'auto_<init>'"),
    ("agent.algo.ent_coef=-0.1", "agent.algo.ent_coef: a number >= 0 or 'auto' is required, got -0.1"),
])
def test_a_bad_compiled_sac_setting_is_one_line_before_any_run(store, tmp_path, override, message):
    res = run_cli(*SMALL, override, f"tracking.uri={store}", cwd=tmp_path)
    assert res.returncode == 2, res.stderr[-2000:]
    err = res.stderr.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert not (tmp_path / "mlruns" / "mlflow.db").exists() or search(store).empty


def test_dyna_trains_it_across_refits(store):
    """Dyna on MountainCar with the compiled SAC: each round's surrogate training continues the
    same agent (steps, gradient steps and replay buffer) on the refitted surrogate, with one
    compile in all."""
    from sdrl_bench.cli.build import build_dyna_job
    from sdrl_bench.rl.dyna import run_dyna

    cfg = compose_cfg("experiment=dyna_mountain_car", "agent=sac_jax", "agent.algo.batch_size=64",
                      "agent.algo.learning_rate=3e-4", "n_transitions=30", "rl.dyna.collect_per_round=20",
                      "rl.dyna.first_round_steps=256", "rl.dyna.surrogate_steps_per_round=256", "rl.dyna.max_rounds=2",
                      "rl.dyna.eval_episodes=1", "rl.dyna.final_episodes=1", "rl.dyna.audit_episodes=0",
                      "rl.dyna.max_real_transitions=100000", "progress_bar=false", f"tracking.uri={store}")
    job = build_dyna_job(cfg, build_fit_job(cfg))
    outcome = run_dyna(job, job.check(), None)
    sac = outcome.agent
    assert isinstance(sac, JaxSAC) and sac.compile_programs == 1
    assert [r.surrogate_steps for r in outcome.rounds] == [0, 256, 512] and sac.num_timesteps == 512
    assert sac.gradient_steps_done == 512 and sac._replay.size == 512
    assert outcome.summary["agent_compile_programs"] == 1
