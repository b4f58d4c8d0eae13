"""agent=ppo_jax (rl/jax_agent.py): the compiled PPO behind SB3's interface, on MountainCar. In
the surrogate it trains compiled (the vector env is never stepped) and the harness's callback
sees whole rollouts; in real envs it steps in Python and every real step is counted; a saved
agent loads and acts the same; the CLI runs both arms with it and records its compile time;
Dyna's refits are compiled again and trained on."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from collections import Counter

import numpy as np
import pytest

jax = pytest.importorskip("jax")
jnp = pytest.importorskip("jax.numpy")
pytest.importorskip("optax")
pytestmark = pytest.mark.jax

from helpers import ROOT, compose_cfg, held_sde_noise, run_cli, search  # noqa: E402
from sdrl_bench.cli.build import build_dyna_job, build_fit_job, instantiate_key  # noqa: E402
from sdrl_bench.pipeline import fit_dynamics  # noqa: E402
from sdrl_bench.rl.agents import RealEvalCallback, make_agent, real_vec_env, train  # noqa: E402
from sdrl_bench.rl import jax_compile, jax_nets  # noqa: E402
from sdrl_bench.rl.jax_agent import JaxPPO  # noqa: E402
from sdrl_bench.rl.transfer import surrogate_vec_env  # noqa: E402

SMALL = ["experiment=fast_mountain_car", "agent=ppo_jax", "agent.n_envs=16", "agent.algo.n_steps=32",
         "agent.algo.batch_size=128", "collector=heuristic", "n_transitions=75"]
"""The fast MountainCar pack with the compiled PPO, 16 copies x 32 steps (512 a rollout)."""


@pytest.fixture(scope="module")
def fitted():
    cfg = compose_cfg(*SMALL)
    res = fit_dynamics(build_fit_job(cfg))
    return cfg, res.model, res.spec


def test_in_the_surrogate_it_trains_compiled_and_the_callback_sees_whole_rollouts(fitted):
    cfg, model, spec = fitted
    agent = instantiate_key(cfg.agent, "agent")
    venv = surrogate_vec_env(model, spec, agent.n_envs, seed=0)
    counts = Counter()
    callback = RealEvalCallback(spec, every=1024, episodes=1, seed=1000, counts=counts)
    res = train(agent, venv, 2048, seed=0, callback=callback, env_seed=0)
    ppo = res.model
    assert isinstance(ppo, JaxPPO) and ppo.rollout_backend == "compiled" and ppo.rollout_compiles == 1
    assert ppo.compile_seconds > 0 and ppo.num_timesteps == 2048
    assert res.curve.steps == [0, 1024, 2048]  # the start, then after every second rollout of 512
    assert counts["train"] == 0 and counts["evaluate"] > 0 and counts["resets/evaluate"] == 3  # one episode a point
    assert venv.surrogate.real_resets == 0 and not np.any(venv.n_diverged)
    c = ppo.cfg  # the pack's recipe: gSDE from log-std -1, rewards scaled by the VecNormalize make_agent puts around
    assert c.use_sde and c.log_std_init == -1.0 and c.normalize_reward and c.learning_rate == 3e-3
    assert ppo.net["log_std"].shape == (64, 1)
    before = np.asarray(ppo.net["actor"][0][0]).copy()
    obs = np.random.default_rng(0).uniform([-1.2, -0.07], [0.6, 0.07], size=(50, 2)).astype(np.float32)
    acted, _ = ppo.predict(obs, deterministic=True)
    from stable_baselines3.common.callbacks import BaseCallback, StopTrainingOnMaxEpisodes

    seen = []

    class Locals(BaseCallback):  # one step for the rollout: its episode ends and task rewards
        def _on_step(self) -> bool:
            seen.append((self.locals["dones"].shape, self.locals["dones"].dtype, self.locals["rewards"].shape))
            ended.append(int(self.locals["dones"].sum()))
            return True

    ended: list[int] = []
    stop = StopTrainingOnMaxEpisodes(10**6)
    ppo.learn(512, reset_num_timesteps=False, callback=[Locals(), stop])  # trains on: one more rollout and update
    assert seen == [((32, 16), np.dtype(bool), (32, 16))] and stop.n_episodes == ended[0]  # SB3's count, whole
    assert ppo.num_timesteps == 2560 and ppo.rollout_compiles == 1 and not np.array_equal(before, ppo.net["actor"][0][0])
    # the deterministic action (on the host) is the trained net's: the jitted action's, not the one before
    now, _ = ppo.predict(obs, deterministic=True)
    jitted = np.asarray(jax_nets.deterministic_action(ppo.net, obs, *ppo._bounds))
    assert np.allclose(now, jitted, rtol=0, atol=1e-6) and not np.allclose(now, acted, rtol=0, atol=1e-6)
    ppo.learn(512)  # SB3's default: the count starts again, from fresh episodes, with the same program
    assert ppo.num_timesteps == 512 and ppo.rollout_compiles == 1


def test_in_real_envs_it_steps_in_python_and_every_step_is_counted(fitted):
    cfg, _, spec = fitted
    agent = instantiate_key(cfg.agent, "agent")
    counts = Counter()
    ppo = make_agent(agent, real_vec_env(spec, agent.n_envs, 5, counts), seed=0, env_seed=5)
    ppo.learn(1024)
    assert ppo.rollout_backend == "python" and ppo.rollout_compiles == 0
    assert counts["train"] == ppo.num_timesteps == 1024 and counts["resets/train"] == agent.n_envs
    from stable_baselines3.common.callbacks import BaseCallback, StopTrainingOnMaxEpisodes

    seen = []

    class Locals(BaseCallback):  # SB3's collect_rollouts locals, by SB3's names
        def _on_step(self) -> bool:
            seen.append((self.locals["actions"].shape, np.abs(self.locals["clipped_actions"]).max(), len(self.locals["dones"])))
            return True

    ppo.learn(512, callback=[Locals(), StopTrainingOnMaxEpisodes(10**6)], reset_num_timesteps=False)
    assert ppo.num_timesteps == 1536 and len(seen) == 32 and seen[0][0] == (agent.n_envs, 1)
    assert all(m <= 1.0 and n == agent.n_envs for _, m, n in seen)


def test_a_saved_agent_loads_and_acts_the_same(fitted, tmp_path):
    cfg, model, spec = fitted
    agent = instantiate_key(cfg.agent, "agent")
    ppo = make_agent(agent, surrogate_vec_env(model, spec, agent.n_envs, seed=0), seed=3)
    ppo.learn(1024)
    ppo.save(tmp_path / "a.zip")
    again = JaxPPO.load(tmp_path / "a.zip", device="cpu")
    from stable_baselines3.common.vec_env import VecNormalize

    from sdrl_bench import ConfigError

    with pytest.raises(ConfigError, match="trained with reward scaling .* the env is not in VecNormalize's"):
        JaxPPO.load(tmp_path / "a.zip", env=surrogate_vec_env(model, spec, agent.n_envs, seed=1))
    scaled = VecNormalize(surrogate_vec_env(model, spec, agent.n_envs, seed=1), norm_obs=False)
    assert JaxPPO.load(tmp_path / "a.zip", env=scaled).env is scaled
    obs = np.random.default_rng(0).uniform([-1.2, -0.07], [0.6, 0.07], size=(50, 2)).astype(np.float32)
    a, _ = ppo.predict(obs, deterministic=True)
    assert np.array_equal(a, again.predict(obs, deterministic=True)[0]) and again.num_timesteps == 1024
    assert again.cfg == ppo.cfg and np.abs(a).max() <= 1.0
    kept, loaded = (jax.tree_util.tree_leaves(x._opt) for x in (ppo, again))  # Adam's state, as SB3's save keeps it
    assert len(kept) == len(loaded) and all(np.array_equal(x, y) for x, y in zip(kept, loaded, strict=True))
    assert max(float(np.abs(x).max()) for x in loaded if np.asarray(x).dtype.kind == "f") > 0  # moments, not zeros
    with zipfile.ZipFile(tmp_path / "a.zip") as src, zipfile.ZipFile(tmp_path / "old.zip", "w") as dst:
        for part in ("config.json", "params.npz"):  # a file saved before the optimiser's state was kept
            dst.writestr(part, src.read(part))
    old = JaxPPO.load(tmp_path / "old.zip")
    assert np.array_equal(a, old.predict(obs, deterministic=True)[0])
    assert all(not np.asarray(x).any() for x in jax.tree_util.tree_leaves(old._opt))  # Adam starts afresh
    one, _ = again.predict(obs[0], deterministic=True)
    assert one.shape == (1,) and np.allclose(one, a[0], rtol=0, atol=1e-6)  # a batch of one: rounding apart
    sampled, _ = again.predict(obs, deterministic=False)
    assert sampled.shape == a.shape and not np.array_equal(sampled, a) and np.abs(sampled).max() <= 1.0
    mid = int(np.argmin(np.abs(a[:, 0])))  # an observation whose action is inside the bounds, not clipped
    held_sde_noise(again, obs[mid], a[mid])
    # the same seed trains the same networks (jax keys and the host's draws alike); another seed others
    twin = make_agent(agent, surrogate_vec_env(model, spec, agent.n_envs, seed=0), seed=3)
    twin.predict(obs, deterministic=False)  # sampling first moves none of training's draws
    other = make_agent(agent, surrogate_vec_env(model, spec, agent.n_envs, seed=0), seed=4)
    twin.learn(1024), other.learn(1024)
    leaves = lambda p: jax.tree_util.tree_leaves(p.net)  # noqa: E731
    assert all(np.array_equal(x, y) for x, y in zip(leaves(ppo), leaves(twin), strict=True))
    assert not np.array_equal(leaves(ppo)[0], leaves(other)[0])
    assert twin._noise is None  # learn dropped the matrices that sampling drew before it
    twin.predict(obs, deterministic=False)
    assert twin._noise is not None
    twin.learn(1, reset_num_timesteps=False)
    assert twin._noise is None  # the next stochastic predict draws anew, with the trained log-std


def test_a_bare_compiled_iteration_trains_what_a_learn_iteration_trains(fitted):
    """``compiled_iteration`` (the benchmarks' bare rollout and update) draws as ``learn`` does:
    one learn iteration and one bare one train the networks two learn iterations train, bit for
    bit; before any compiled learn it refuses."""
    cfg, model, spec = fitted
    agent = instantiate_key(cfg.agent, "agent")
    bare, ref = (make_agent(agent, surrogate_vec_env(model, spec, agent.n_envs, seed=0), seed=3) for _ in range(2))
    with pytest.raises(RuntimeError, match="no compiled rollout and update yet"):
        bare.compiled_iteration()
    n = bare.cfg.rollout_size
    bare.learn(n)
    bare.compiled_iteration()
    ref.learn(2 * n)
    assert bare.num_timesteps == ref.num_timesteps == 2 * n
    leaves = lambda p: jax.tree_util.tree_leaves(p.net)  # noqa: E731
    assert all(np.array_equal(x, y) for x, y in zip(leaves(bare), leaves(ref), strict=True))
    assert not np.array_equal(leaves(bare)[0], jax.tree_util.tree_leaves(make_agent(
        agent, surrogate_vec_env(model, spec, agent.n_envs, seed=0), seed=3).net)[0])  # it trained


def test_the_lowering_key_changes_with_the_program_its_constants_shapes_and_options():
    from sdrl_bench.rl.jax_compile import lowering_key

    jax_nets.modules()  # the harness's XLA flags, should this be the process's first jax computation

    def scaled(c, shift=1.0):
        c = jnp.asarray(c)
        return jax.jit(lambda v: v * c + shift)

    x = jnp.ones(3)
    key = lowering_key(scaled(np.arange(3.0)).trace(x), {})
    assert len(key) == 64 and key == lowering_key(scaled(np.arange(3.0)).trace(x), {})  # another closure, the same program
    assert key != lowering_key(scaled(np.arange(3.0) + 1).trace(x), {})  # a captured constant's value
    assert key != lowering_key(scaled(np.arange(3.0), 2.0).trace(x), {})  # a literal
    assert key != lowering_key(scaled(np.arange(4.0)).trace(jnp.ones(4)), {})  # the shapes
    assert key != lowering_key(scaled(np.arange(3.0)).trace(x), {"xla_backend_optimization_level": 2})

    def nested(c):  # a constant captured inside a jit inside a scan: the printed jaxpr names it, without its value
        inner = scaled(c, 0.0)
        return jax.jit(lambda v: jax.lax.scan(lambda s, _: (inner(s), None), v, None, length=2)[0])

    deep = lowering_key(nested(np.arange(3.0)).trace(x), {})
    assert deep == lowering_key(nested(np.arange(3.0)).trace(x), {})
    assert deep != lowering_key(nested(np.arange(3.0) + 1).trace(x), {})


_LEARN = """
import sys, json
if {block}:
    sys.modules["flatbuffers"] = None  # jax.export's serialization missing: its import fails
import numpy as np
sys.path.insert(0, {tests!r})
from helpers import compose_cfg
from sdrl_bench.cli.build import build_fit_job, instantiate_key
from sdrl_bench.pipeline import fit_dynamics
from sdrl_bench.rl import jax_compile
from sdrl_bench.rl.agents import make_agent
from sdrl_bench.rl.transfer import surrogate_vec_env
jax_compile.use_compilation_cache({cache!r})
cfg = compose_cfg(*{small!r})
res = fit_dynamics(build_fit_job(cfg))
agent = instantiate_key(cfg.agent, "agent")
ppo = make_agent(agent, surrogate_vec_env(res.model, res.spec, agent.n_envs, seed=0), seed=3)
ppo.learn(1024)
import jax
np.savez({out!r}, *[np.asarray(x) for x in jax.tree_util.tree_leaves(ppo.net)])
print(json.dumps({{"programs": ppo.compile_programs, "lowered": ppo.lowering_cache_hits, "jax": ppo.compile_cache_hits}}))
"""


def test_through_the_lowering_cache_training_is_what_it_is_compiled_directly(fitted, tmp_path):
    """Two fresh processes with the persistent cache on (the first exports its programs'
    lowerings, the second loads them, one of them cut short in between), and a third without
    jax.export's serialization (no lowering cache, one warning), train the networks this
    process trains without the cache, bit for bit."""
    from pathlib import Path

    cfg, model, spec = fitted
    agent = instantiate_key(cfg.agent, "agent")
    ppo = make_agent(agent, surrogate_vec_env(model, spec, agent.n_envs, seed=0), seed=3)
    ppo.learn(1024)
    assert ppo.lowering_cache_hits == 0  # no cache in this process: compiled directly
    want = [np.asarray(x) for x in jax.tree_util.tree_leaves(ppo.net)]
    tests, runs = str(Path(__file__).resolve().parents[1]), []
    for i in range(3):
        out = tmp_path / f"net{i}.npz"
        code = _LEARN.format(tests=tests, cache=str(tmp_path / "cache"), small=SMALL, out=str(out), block=i == 2)
        res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
        assert res.returncode == 0, res.stderr[-2000:]
        runs.append(json.loads(res.stdout.strip().splitlines()[-1]))
        got = np.load(out)
        assert len(got.files) == len(want) and all(np.array_equal(got[f"arr_{k}"], w) for k, w in enumerate(want))
        lowered = sorted((tmp_path / "cache" / "lowered").iterdir())
        assert len(lowered) == 3
        if i == 0:  # a lowering cut short (a full disk, a killed write elsewhere): exported again, not a failure
            cut, size = lowered[0], lowered[0].stat().st_size
            cut.write_bytes(cut.read_bytes()[: size // 2])
    assert runs[0] == {"programs": 3, "lowered": 0, "jax": 0}  # cold: traced, exported, compiled
    assert runs[1] == {"programs": 3, "lowered": 2, "jax": 3}  # traced; two lowerings and all the code from the caches
    assert runs[2]["programs"] == 3 and runs[2]["lowered"] == 0  # lowered and compiled directly
    assert "the lowering cache is off" in res.stderr and "flatbuffers" in res.stderr
    # a cache whose lowerings cannot be written (its folder's name taken by a file): warned, trained all the same
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "lowered").write_text("not a folder")
    out = tmp_path / "net3.npz"
    code = _LEARN.format(tests=tests, cache=str(tmp_path / "full"), small=SMALL, out=str(out), block=False)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    assert json.loads(res.stdout.strip().splitlines()[-1])["lowered"] == 0 and "could not keep" in res.stderr
    got = np.load(out)
    assert all(np.array_equal(got[f"arr_{k}"], w) for k, w in enumerate(want))
    assert cut.stat().st_size > size // 2  # the cut one written whole again: it loads
    assert jax.export.deserialize(bytearray(cut.read_bytes())).in_avals


def test_the_cli_runs_both_arms_with_it_and_records_the_compile(store, tmp_path):
    res = run_cli(*SMALL, "rl.surrogate_steps=1024", "rl.real_steps=1024", "rl.eval_every=1024", "rl.eval_episodes=1",
                  "rl.final_episodes=1", "rl.stop_when_solved=false", "seed=0", "progress_bar=false",
                  f"tracking.uri={store}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "tpu" not in (res.stdout + res.stderr).lower()  # jax's backend probe stays quiet
    run = search(store, filter_string="tags.`sdrl.kind` = 'transfer'").iloc[0]
    assert run["tags.agent"] == "ppo_jax" and run["status"] == "FINISHED"
    for arm in ("surrogate", "real"):
        # a part within its whole, not a speed claim: the compiles are inside the training's wall (rl.transfer)
        assert 0 < run[f"metrics.{arm}/compile_wall_seconds"] < run[f"metrics.{arm}/train_wall_seconds"]
        assert run[f"metrics.{arm}/sb3/train/value_loss"] >= 0
        assert run[f"metrics.{arm}/xla_pool_threads"] == 1  # jax_threads' default
    assert run["metrics.real/real_transitions_train"] == 1024
    assert any((tmp_path / "mlruns" / "jax_cache").iterdir())  # jax_cache_dir: the compiled programs, for the next run
    # the first run compiled its surrogate arm cold (the real arm, after it, may find an update of
    # the same shape in the cache); a second run, another seed, in another folder with a copy of the
    # cache (the cache's path is not in its keys), loads every program from it
    assert run["metrics.surrogate/compile_programs"] == 3 and run["metrics.surrogate/compile_cache_hits"] == 0
    assert run["metrics.real/compile_programs"] == 1
    assert run["metrics.surrogate/rollout_compiles"] == 1 and run["metrics.real/rollout_compiles"] == 0
    moved = tmp_path / "moved"
    shutil.copytree(tmp_path / "mlruns" / "jax_cache", moved / "mlruns" / "jax_cache")
    again = run_cli(*SMALL, "rl.surrogate_steps=1024", "rl.real_steps=1024", "rl.eval_every=1024", "rl.eval_episodes=1",
                    "rl.final_episodes=1", "rl.stop_when_solved=false", "seed=1", "progress_bar=false",
                    f"tracking.uri={store}", cwd=moved)
    assert again.returncode == 0, again.stderr[-2000:]
    second = search(store, filter_string="tags.`sdrl.kind` = 'transfer' and params.seed = '1'").iloc[0]
    for arm, programs in (("surrogate", 3), ("real", 1)):
        assert second[f"metrics.{arm}/compile_programs"] == second[f"metrics.{arm}/compile_cache_hits"] == programs
        assert second[f"metrics.{arm}/lowering_cache_hits"] == programs  # traced, their lowerings loaded
    assert run["metrics.surrogate/lowering_cache_hits"] == 0
    from mlflow.tracking import MlflowClient

    path = MlflowClient(store).download_artifacts(run["run_id"], "agents/surrogate.zip", str(tmp_path))
    assert JaxPPO.load(path).num_timesteps == 1024


def test_the_compiled_pack_validates_and_trains_its_own_recipe(fitted):
    """experiment=compiled_mountain_car: its recipe passes the compiled PPO's config check and is
    the one it trains (the clip, gamma, minibatches and gSDE's log-std of the search's choice)."""
    from sdrl_bench.cli.train import build_transfer_job

    cfg = compose_cfg("experiment=compiled_mountain_car")
    job = build_transfer_job(cfg, build_fit_job(cfg))
    job.check()
    assert job.agent.name == "ppo_jax" and job.agent.tuning_real_steps == 711_075
    _, model, spec = fitted
    agent = make_agent(job.agent, surrogate_vec_env(model, spec, job.agent.n_envs, 0), 0)
    c = agent.cfg
    assert (c.n_envs, c.n_steps, c.batch_size, c.n_epochs, c.gamma, c.clip_range) == (64, 32, 512, 3, 0.995, 0.1)
    assert (c.learning_rate, c.log_std_init, c.use_sde, c.normalize_reward) == (1.04e-2, -0.259, True, True)
    agent.learn(2048)  # one compiled rollout and update in the surrogate
    assert agent.rollout_backend == "compiled" and agent.num_timesteps == 2048


@pytest.mark.parametrize("override,message", [
    ("+agent.algo.target_kl=0.01", "agent.algo sets ['target_kl']"),  # a setting the compiled PPO lacks
    ("jax_threads=-1", "jax_threads must be >= 0, got -1"),
])
def test_a_bad_compiled_ppo_setting_is_one_line_before_any_run(store, tmp_path, override, message):
    res = run_cli(*SMALL, "task=train", override, f"tracking.uri={store}", cwd=tmp_path)
    assert res.returncode == 2, res.stderr[-2000:]
    err = res.stderr.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not (tmp_path / "mlruns" / "mlflow.db").exists() or search(store).empty  # no run was started


def test_dyna_refits_are_compiled_again_and_trained_on(store):
    from sdrl_bench.rl.dyna import run_dyna

    cfg = compose_cfg("experiment=dyna_mountain_car", "agent=ppo_jax", "agent.n_envs=16", "agent.algo.n_steps=32",
                      "agent.algo.batch_size=128", "n_transitions=30", "rl.dyna.collect_per_round=20",
                      "rl.dyna.first_round_steps=512", "rl.dyna.surrogate_steps_per_round=512", "rl.dyna.max_rounds=2",
                      "rl.dyna.eval_episodes=1", "rl.dyna.final_episodes=1", "rl.dyna.audit_episodes=0",
                      "rl.dyna.max_real_transitions=100000", "progress_bar=false", f"tracking.uri={store}")
    job = build_dyna_job(cfg, build_fit_job(cfg))
    outcome = run_dyna(job, job.check(), None)
    ppo = outcome.agent
    assert isinstance(ppo, JaxPPO) and ppo.rollout_backend == "compiled"
    assert [r.surrogate_steps for r in outcome.rounds] == [0, 512, 1024] and ppo.num_timesteps == 1024
    # round 2 trains in round 1's refit: through the program compiled for round 1 when the refit has
    # the same structure (its numbers an argument), else compiled again
    assert outcome.rounds[1].refit and ppo.rollout_compiles + ppo.rollout_swaps == 2 and ppo.rollout_compiles >= 1
    s = outcome.summary  # recorded with the run's metrics
    assert (s["agent_rollout_compiles"], s["agent_rollout_swaps"]) == (ppo.rollout_compiles, ppo.rollout_swaps)
    assert 0 < s["agent_compile_seconds"] <= s["train_wall_seconds"]
    assert s["agent_pool_threads"] == ppo.pool_threads >= 1  # XLA's CPU pool that ran its programs


def test_discrete_actions_get_a_categorical_policy_that_learns_cartpole(tmp_path):
    """CartPole (discrete): 100k compiled steps in its SINDy surrogate lift the real return well
    above a random policy's (~22); the real-env control steps integer actions; save/load keeps it."""
    from sdrl_bench.rl.agents import evaluate_real

    cfg = compose_cfg("env=cartpole", "agent=ppo_jax", "collector=random", "n_transitions=300")
    res = fit_dynamics(build_fit_job(cfg))
    agent = instantiate_key(cfg.agent, "agent")
    ppo = make_agent(agent, surrogate_vec_env(res.model, res.spec, agent.n_envs, seed=0), seed=0)
    ppo.learn(100_000)
    assert ppo.rollout_backend == "compiled" and ppo.discrete and "log_std" not in ppo.net
    real = evaluate_real(ppo, res.spec, 5, seed=0)
    print(f"CartPole, 100k compiled surrogate steps: real returns {real.returns.tolist()}")
    assert real.mean > 100
    a, _ = ppo.predict(np.zeros((3, 4), np.float32), deterministic=True)
    assert a.shape == (3,) and a.dtype.kind == "i"
    ppo.save(tmp_path / "cp.zip")
    again = JaxPPO.load(tmp_path / "cp.zip")
    assert again.discrete and np.array_equal(again.predict(np.zeros((3, 4), np.float32), deterministic=True)[0], a)
    counts = Counter()
    control = make_agent(agent, real_vec_env(res.spec, agent.n_envs, 7, counts), seed=0, env_seed=7)
    control.learn(4096)
    assert control.rollout_backend == "python" and counts["train"] == 4096


def test_compiled_rollout_false_steps_the_surrogate_in_python_with_the_same_update(fitted, store, tmp_path):
    """``agent.algo.compiled_rollout=false``: the ablation that keeps the compiled update and
    steps the surrogate's vector env in Python, as in a real env; a value that is not a bool is
    one line naming the key, before any run."""
    cfg, model, spec = fitted
    agent = instantiate_key(compose_cfg(*SMALL, "agent.algo.compiled_rollout=false").agent, "agent")
    venv = surrogate_vec_env(model, spec, agent.n_envs, seed=0)
    ppo = make_agent(agent, venv, seed=0, env_seed=0)
    before = np.asarray(ppo.net["actor"][0][0]).copy()
    ppo.learn(1024)
    assert ppo.compiled_rollout is False and ppo.rollout_backend == "python" and ppo.rollout_compiles == 0
    assert ppo.num_timesteps == 1024 and not np.array_equal(before, ppo.net["actor"][0][0])
    # the surrogate's vector env was stepped (its step counters moved), which the compiled path never does
    assert np.all(np.asarray(venv.get_attr("elapsed_steps")) > 0)
    ppo.save(tmp_path / "agent.zip")
    loaded = JaxPPO.load(tmp_path / "agent.zip", env=ppo.env)  # with the VecNormalize make_agent put around venv
    assert loaded.compiled_rollout is False  # a saved agent keeps where it steps
    loaded.learn(512, reset_num_timesteps=False)
    assert loaded.rollout_backend == "python" and loaded.num_timesteps == 1536
    res = run_cli(*SMALL, "task=train", "agent.algo.compiled_rollout=maybe", f"tracking.uri={store}", cwd=tmp_path)
    assert res.returncode == 2, res.stderr[-2000:]
    err = res.stderr.strip().splitlines()
    assert len(err) == 1 and "agent.algo.compiled_rollout: true or false, got 'maybe'" in err[0]
    assert not (tmp_path / "mlruns" / "mlflow.db").exists() or search(store).empty  # no run was started


def test_jax_threads_sizes_xlas_cpu_pool_without_pinning_a_thread(tmp_path):
    # a fresh interpreter: the pool is made with JAX's backend, once per process
    code = ("import json, os\n"
            "from sdrl_bench.rl import jax_compile\n"
            "cpus = os.sched_getaffinity(0)\n"
            "before = jax_compile.cpu_pool_threads()\n"
            "got = jax_compile.size_cpu_pool(1)\n"
            "aff = {os.sched_getaffinity(int(t)) == cpus for t in os.listdir('/proc/self/task')}\n"
            "import jax, jax.numpy as jnp\n"
            "x = float(jax.jit(lambda a: (a @ a).sum())(jnp.ones((64, 64))))\n"
            "print(json.dumps([before, got, jax_compile.cpu_pool_threads(), sorted(aff), x]))\n")
    res = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                         env={**os.environ, "JAX_PLATFORMS": "cpu"})  # the CPU's pool, and no GPU note, on any host
    assert res.returncode == 0, res.stderr[-2000:]
    before, got, after, aff, x = json.loads(res.stdout.strip().splitlines()[-1])
    assert (before, got, after) == (0, 1, 1)  # no pool before the backend, one thread in it after
    assert aff == [True]  # every thread, the pool's too, may run on every CPU the process may
    assert x == 64.0 * 64 * 64
    assert "default backend" not in res.stderr  # on the CPU, where the step is tested: no note


def test_training_off_the_cpu_is_one_line_saying_what_was_measured_there():
    assert jax_compile.backend_note("cpu") is None
    note = jax_compile.backend_note("gpu")
    assert "\n" not in note and note.startswith("JAX's default backend is gpu: the compiled agents train there")
    assert "matched ModelEnv's (at most 1.5e-12)" in note and note.endswith("JAX_PLATFORMS=cpu keeps them on the CPU")
    assert "'On a GPU'" in note and "### On a GPU" in (ROOT / "docs" / "compiled.md").read_text()
