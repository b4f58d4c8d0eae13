"""Envs from YAML and plain functions: action encodings, angle maps, the worked examples'
laws, and the one-line errors a user's env gets before any collection."""

from __future__ import annotations

import sys

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.env_checker import check_env

from helpers import compose_cfg
from sdrl_bench import ConfigError
from sdrl_bench.cli.build import build_fit_job, build_transfer_job
from sdrl_bench.envs import EnvSpec
from sdrl_bench.pipeline import fit_dynamics
from sdrl_bench.surrogate.env import SurrogateEnv
from sdrl_bench.surrogate.vec import SurrogateVecEnv
from user_env import write_user_dir

PEND = dict(name="p", gym_id="Pendulum-v1", state_names=["th", "thdot"], observation_names=["cos_th", "sin_th", "thdot"],
            angles={"th": ["cos_th", "sin_th"]}, action_names=["torque"])


@pytest.fixture
def user_dir(tmp_path, monkeypatch):
    """The user's package on sys.path and their config dir on Hydra's search path."""
    src, conf = write_user_dir(tmp_path / "user")
    monkeypatch.syspath_prepend(str(src))
    yield src, conf
    for mod in [m for m in sys.modules if m == "my_envs" or m.startswith("my_envs.") or m == "bad_task"]:
        del sys.modules[mod]


def user_cfg(conf, *overrides):
    return compose_cfg(f"hydra.searchpath=[file://{conf}]", "env=oscillator", "collector=random", *overrides)


# ---------------------------------------------------------------------- encodings and maps
def test_action_encodings():
    a = np.array([[0], [1], [1]])
    one_hot = EnvSpec(name="c", gym_id="CartPole-v1", state_names=["x", "xd", "t", "td"], n_discrete_actions=2,
                      action_names=["left", "right"])
    np.testing.assert_array_equal(one_hot.encode_actions(a), [[1, 0], [0, 1], [0, 1]])
    index = EnvSpec(name="c", gym_id="CartPole-v1", state_names=["x", "xd", "t", "td"], n_discrete_actions=2,
                    action_names=["a"], action_encoding="index")
    np.testing.assert_array_equal(index.encode_actions(a), [[0], [1], [1]])
    force = EnvSpec(name="c", gym_id="CartPole-v1", state_names=["x", "xd", "t", "td"], n_discrete_actions=2,
                    action_names=["force"], action_encoding="values", action_values=[-1.0, 1.0])
    np.testing.assert_array_equal(force.encode_actions(a), [[-1], [1], [1]])
    assert force.discrete_action_labels() == ("force=-1", "force=1")
    clip = EnvSpec(**PEND, action_encoding="clip")
    np.testing.assert_array_equal(clip.encode_actions([[3.0], [-0.5]]), [[2.0], [-0.5]])
    with pytest.raises(ConfigError, match=r"env.spec.action_values: need 2 entries"):
        EnvSpec(name="c", gym_id="CartPole-v1", state_names=["x"], n_discrete_actions=2, action_names=["force"],
                action_encoding="values", action_values=[1.0])
    with pytest.raises(ConfigError, match=r"env.spec.action_encoding: 'values' for continuous actions"):
        EnvSpec(**PEND, action_encoding="values")


def test_angle_map_round_trip_and_unwrapping():
    spec = EnvSpec(**PEND)
    states = np.array([[3.1, 1.0], [-3.1, -2.0]])
    obs = spec.observe(states)
    np.testing.assert_allclose(obs, [[np.cos(3.1), np.sin(3.1), 1.0], [np.cos(-3.1), np.sin(-3.1), -2.0]])
    np.testing.assert_allclose(spec.coordinates(obs), states)
    # a step across +-pi: the next angle stays next to the current one
    nxt = spec.coordinates(spec.observe(np.array([[3.1 + 0.1, 1.0]])), reference=np.array([[3.1, 1.0]]))
    np.testing.assert_allclose(nxt[0, 0], 3.2)
    with pytest.raises(ConfigError, match=r"env.spec.angles.th: expected \[cos name, sin name\]"):
        EnvSpec(**{**PEND, "angles": {"th": ["cos_th", "nope"]}})
    with pytest.raises(ConfigError, match=r"env.spec.state_names: \['w'\] are neither observed nor angles"):
        EnvSpec(**{**PEND, "state_names": ["th", "thdot", "w"]})


def test_pendulum_exact_law_and_a_surrogate_on_the_circle():
    """The shipped example: 200 random transitions give the exact law (th from the *clipped*
    next velocity); the surrogate's observations stay on the unit circle and pass the checkers."""
    res = fit_dynamics(build_fit_job(compose_cfg("env=pendulum", "collector=random")))
    assert set(res.model.describe().splitlines()) == {"th' = th +0.05 thdot'", "thdot' = thdot +0.75 sin(th) +0.15 torque"}
    assert res.model.clipped_ == {"thdot": (-8.0, 8.0)}
    env = SurrogateEnv(res.model, res.job.spec)
    check_env(env)
    obs, _ = env.reset(seed=0)
    for _ in range(200):
        obs, *_ = env.step(env.action_space.sample())
        assert obs.shape == (3,) and abs(np.hypot(obs[0], obs[1]) - 1) < 1e-6
    venv = SurrogateVecEnv(res.model, res.job.spec, n_envs=16, seed=0)
    venv.reset()
    for _ in range(50):
        obs, *_ = venv.step(np.ones((16, 1), dtype=np.float32))
    assert obs.shape == (16, 3) and np.all(np.abs(np.hypot(obs[:, 0], obs[:, 1]) - 1) < 1e-6)


@pytest.mark.parametrize("seed", range(5))
def test_pendulum_clipped_velocity_reaches_the_angle_exactly(seed, tmp_path):
    """Pendulum-v1 clips thdot' to +-8 and then moves th by the clipped value. The per-equation
    law reads thdot' after the env's bound: held-out one-step MSE <= 1e-10 on every state (and
    on the observation's cos and sin) from 200 random transitions, on the rows where the clip is
    active too; the compiled evaluators (one state, batched) and a saved-and-loaded model agree."""
    res = fit_dynamics(build_fit_job(compose_cfg("env=pendulum", "collector=random", f"seed={seed}", "n_transitions=200")))
    m, test, spec = res.fidelity.metrics, res.test, res.job.spec
    assert m["mse/th"] <= 1e-10 and m["mse/thdot"] <= 1e-10
    clip = np.abs(test.next_states[:, 1]) >= 8.0
    assert clip.sum() >= 3  # the held-out set holds clipped steps
    from sdrl_bench.fidelity import step

    pred = step(res.model, spec, test.states, test.actions)
    err = (pred - test.next_states[:, spec.target_index]) ** 2
    assert err[clip].mean(axis=0).max() <= 1e-10
    obs_err = (spec.observe(pred) - spec.observe(test.next_states)) ** 2
    assert obs_err.mean(axis=0).max() <= 1e-10
    # the same model unclipped (the bound left out of the primed term) misses exactly those rows
    from sdrl_bench.models.fast import batch_predictor, scalar_predictor
    from sdrl_bench.models.per_equation import PerEquationModel

    x, u = spec.model_inputs(test.states, test.actions)
    ref = res.model.predict(x, u)
    z = np.concatenate([x, u], axis=1)
    np.testing.assert_allclose(batch_predictor(res.model)(z.T).T, ref, rtol=0, atol=1e-12)
    one = scalar_predictor(res.model)
    np.testing.assert_allclose([one(row) for row in z.tolist()], ref, rtol=0, atol=1e-12)
    loaded = PerEquationModel.load(res.model.save(tmp_path / "p.json"))
    np.testing.assert_array_equal(loaded.predict(x, u), ref)
    free = PerEquationModel.from_dict({**res.model.to_dict(), "bounds": {}})
    gap = (free.predict(x, u)[:, 0] - ref[:, 0]) ** 2
    assert gap[clip].min() > 1e-8 and gap[~clip].max() < 1e-20


def test_cartpole_force_encoding_gives_a_sparse_law():
    res = fit_dynamics(build_fit_job(compose_cfg("env=cartpole", "collector=random")))
    assert res.model.summary_metrics()["n_parameters"] <= 20
    coef = res.model.coefficients_by_name()
    assert {t: c for t, c in coef["x"].items() if c} == {"x": 1.0, "xdot": 0.02}
    assert {t: c for t, c in coef["th"].items() if c} == {"th": 1.0, "thdot": 0.02}


# ---------------------------------------------------------------------- one-line errors, before collection
def test_user_env_by_name_for_gym_make(user_dir, tmp_path):
    src, conf = user_dir
    spec = build_fit_job(user_cfg(conf)).spec
    from sdrl_bench.envs.base import find_spec

    assert find_spec("oscillator", [str(conf)]) == spec
    assert find_spec("cartpole").action_encoding == "values"  # the package's own YAML
    with pytest.raises(ConfigError, match=r"spec: unknown env 'nowhere': no env/nowhere.yaml"):
        gym.make("sdrl/Surrogate-v0", model=None, spec="nowhere")


def test_spec_class_in_a_missing_module_names_the_cause(user_dir):
    with pytest.raises(ConfigError) as err:
        build_fit_job(user_cfg(user_dir[1], "env.spec._target_=my_missing.CartPoleSpec"))
    assert str(err.value) == ("env.spec: cannot import 'my_missing.CartPoleSpec': ModuleNotFoundError: "
                              "No module named 'my_missing'")


def test_task_module_that_fails_to_import_names_file_and_cause(user_dir):
    src, conf = user_dir
    (src / "bad_task.py").write_text("import numpy as np\nfrom scipy import no_such_thing\n")
    with pytest.raises(ConfigError) as err:
        build_fit_job(user_cfg(conf, "env.spec.reward_fn=bad_task.reward"))
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith("env.spec.reward_fn: cannot import module 'bad_task'")
    assert "ImportError: cannot import name 'no_such_thing'" in msg and "bad_task.py:2" in msg


@pytest.mark.parametrize("body,line", [
    ("    raise RuntimeError('reward table missing')", r"env.spec.reward_fn: RuntimeError: reward table missing \(at .*bad_task.py:3\) \(called on two real reset states\)"),
    ("    return np.zeros((len(states), 3))", r"env.spec.reward_fn: returned shape \(2, 3\) for 2 states; expected \(2,\)"),
    ("    return states.sum()", r"env.spec.reward_fn: returned shape \(\) for 2 states; expected \(2,\)"),
])
def test_a_broken_reward_fails_before_the_first_real_step(user_dir, body, line):
    """The task's functions run once on two real reset states when the job is checked: a reward
    that raises or returns the wrong shape is one line naming its key, and no real step is taken."""
    from sdrl_bench.pipeline import check

    src, conf = user_dir
    (src / "bad_task.py").write_text(f"import numpy as np\ndef reward(states, actions, next_states):\n{body}\n")
    job = build_fit_job(user_cfg(conf, "env.spec.reward_fn=bad_task.reward"))
    import my_envs

    before = my_envs.Oscillator.steps
    with pytest.raises(ConfigError, match="^" + line):
        check(job)
    assert my_envs.Oscillator.steps == before  # resets only: no real step


def test_an_env_without_an_agent_trains_the_fast_ppo_recipe(user_dir):
    """A user's env that names no agent gets ppo_fast (any action space, many envs); the shipped
    envs name their tuned ones; agent= on the command line wins."""
    assert user_cfg(user_dir[1]).agent.name == "ppo_fast"
    assert {e: compose_cfg(f"env={e}").agent.name for e in ("mountain_car", "lunar_lander", "cartpole")} == {
        "mountain_car": "sac", "lunar_lander": "ppo", "cartpole": "ppo"}
    assert compose_cfg("env=lunar_lander", "agent=dqn").agent.name == "dqn"
    cfg = user_cfg(user_dir[1], "task=train")
    build_transfer_job(cfg, build_fit_job(cfg)).agent.check(build_fit_job(cfg).spec)


def test_unregistered_gym_id_fails_before_collection(user_dir):
    with pytest.raises(ConfigError, match=r"env.spec.gym_id: 'Nope-v0' is not registered with gymnasium"):
        build_fit_job(user_cfg(user_dir[1], "env.spec.gym_id=Nope-v0"))
    with pytest.raises(ConfigError, match=r"env.spec.gym_id \('nomod:X-v0'\): cannot import module 'nomod'"):
        build_fit_job(user_cfg(user_dir[1], "env.spec.gym_id=nomod:X-v0"))
    # the module imports but registers another id: the line says so, not "name it module:Env" again,
    # and gymnasium's guess at another env ("Did you mean: ...") is left out
    with pytest.raises(ConfigError) as err:
        build_fit_job(user_cfg(user_dir[1], "env.spec.gym_id=json:Hoper-v5"))
    assert str(err.value).endswith("module 'json' imported, but it registers no 'Hoper-v5': check the id its "
                                   "gymnasium.register call gives")
    assert "Did you mean" not in str(err.value) and "\n" not in str(err.value)


def test_expert_collector_without_an_expert_names_the_key(user_dir):
    with pytest.raises(ConfigError, match=r"collector=expert: env 'oscillator' names no expert \(Interpolation key "
                                          r"'env.expert.agent' not found\)"):
        build_fit_job(user_cfg(user_dir[1], "collector=expert"))


def test_transfer_without_reward_fails_at_check(user_dir):
    cfg = user_cfg(user_dir[1], "~env.spec.reward_fn")
    job = build_transfer_job(cfg, build_fit_job(cfg))
    with pytest.raises(ConfigError, match=r"env.spec.reward_fn: env 'oscillator' defines no reward"):
        job.check()  # config time: no env step, no fit


def test_policy_map_slices_fall_back_to_the_first_two_states(user_dir):
    spec = build_fit_job(user_cfg(user_dir[1])).spec
    assert spec.map_slices() == (("x", (-1.0, 1.0), "v", (-1.0, 1.0)),)
    one = EnvSpec(name="one", gym_id="Oscillator-v0", state_names=["x"])
    with pytest.raises(ConfigError, match=r"env.spec.policy_map_slices: 'one' has fewer than two regressed states"):
        one.map_slices()
