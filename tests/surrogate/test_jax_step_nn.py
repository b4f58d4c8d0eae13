"""The NN surrogates in the compiled step (models/jax_nn.py through surrogate/jax_step.py
``jax_stepper``) against ``ModelEnv.step``: ``surrogate=nn`` (one float32 MLP; a float64 ensemble
of 3, whose disagreement is LunarLander's pessimism) and ``surrogate=pe`` (a probabilistic
ensemble: its elites' mean, and its own draws fed in), on MountainCar (ModelEnv's composition) and
LunarLander (the task's kernels in their array form), 5,000 states around the data, one step,
eager and jit (the states: the data's, moved); the weights an argument (another fit of the same architecture steps through the
same compiled program); the compiled rollout's step draws a probabilistic ensemble's steps with
ModelEnv's spread; and the compiled PPO trains in an NN surrogate with its rollout compiled."""

from __future__ import annotations

import copy

import numpy as np
import pytest

jax = pytest.importorskip("jax")
pytestmark = [pytest.mark.jax, pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")]

from helpers import compose_cfg  # noqa: E402
from sdrl_bench.cli.build import build_fit_job  # noqa: E402
from sdrl_bench.models.jax_eval import jax_model  # noqa: E402
from sdrl_bench.pipeline import fit_dynamics  # noqa: E402
from sdrl_bench.surrogate.jax_step import jax_stepper, unsupported  # noqa: E402
from sdrl_bench.surrogate.model_env import ModelEnv  # noqa: E402

N = 5_000
DATA = {"mountain_car": 300, "lunar_lander": 1000}
MODELS = {"nn32": ("nn", []), "nn64x3": ("nn", ["surrogate.model.ensemble_size=3", "surrogate.model.dtype=float64"]),
          "pe": ("pe", ["surrogate.model.width=32", "surrogate.model.max_steps=100"])}
_FITS: dict[tuple, object] = {}


def fitted(env: str, kind: str, seed: int = 0):
    """A quick fit (300 gradient steps) of ``kind`` on random transitions of ``env``."""
    if (env, kind, seed) not in _FITS:
        sur, extra = MODELS[kind]
        _FITS[env, kind, seed] = fit_dynamics(build_fit_job(compose_cfg(
            f"env={env}", "collector=random", f"n_transitions={DATA[env]}", f"surrogate={sur}",
            "surrogate.model.max_steps=300", *extra, f"seed={seed}")))
    return _FITS[env, kind, seed]


def states_actions(menv, res, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """N of the data's states, moved by a tenth of its spread, and random actions."""
    rng = np.random.default_rng(seed)
    spec = menv.spec
    data = res.data.states
    s = data[rng.integers(len(data), size=N)] + rng.normal(size=(N, data.shape[1])) * data.std(axis=0) * 0.1
    if spec.n_discrete_actions:
        return s, rng.integers(spec.n_discrete_actions, size=(N, 1))
    return s, rng.uniform(-1.5, 1.5, size=(N, spec.raw_action_width))


@pytest.mark.parametrize("kind", list(MODELS))
@pytest.mark.parametrize("env", list(DATA))
def test_the_jax_step_of_an_nn_surrogate_is_the_model_envs_step(env, kind):
    """Next states within the network dtype's rounding (float64: equal), rewards to the same,
    terminations and divergences identical, eager and under jit; the pessimism where the env
    has one and the model members (LunarLander's ensembles)."""
    res = fitted(env, kind)
    menv = ModelEnv(res.model, res.job.spec, noise=False, seed=0)
    assert unsupported(menv) == []
    if env == "lunar_lander" and kind != "nn32":
        assert menv.pessimism == "ensemble disagreement"
    stepper = jax_stepper(menv)
    s, a = states_actions(menv, res)
    ref = menv.step(s, a)
    aux = stepper.init_aux(N)
    for got in (stepper.step(s, a, aux), jax.jit(lambda s_, a_, x_: stepper.step(s_, a_, x_))(s, a, aux)):
        got = [np.asarray(x) for x in got]
        assert np.array_equal(got[2], ref[2]) and np.array_equal(got[3], ref[3])
        dx = float(np.max(np.abs(got[0] - ref[0])))
        dr = float(np.max(np.abs(got[1] - ref[1])))
        if kind == "nn64x3":
            assert dx == 0.0 and dr <= 1e-11, (dx, dr)  # rewards: the members' spread over the task's scale
        else:  # float32 networks: a rounding of the float32 observation, rewards to its rounding
            assert dx <= 2.5e-7 and dr <= 1e-4, (dx, dr)
    if env == "lunar_lander":  # landers that crash or leave, and landers that fly on
        assert ref[2].any() and not ref[2].all()
    # every product at full precision, asked for by the step itself whatever the process's default
    # (a GPU's default multiplies float32 in TF32: 1e-5 to 1e-4 off ModelEnv's on an H200, 2026-11-30)
    with jax.default_matmul_precision("default"):
        program = jax.jit(lambda s_, a_, x_: stepper.step(s_, a_, x_)).lower(s, a, aux).as_text()
    products = [line for line in program.splitlines() if "dot_general" in line]
    assert products and all("precision = [HIGHEST, HIGHEST]" in line for line in products), products


@pytest.mark.parametrize("env", list(DATA))
def test_a_probabilistic_ensembles_own_draw_is_the_model_envs_with_the_same_draws(env):
    """ModelEnv(noise=True) steps a ``pe`` model by its own draw (a random elite's Gaussian): the
    compiled step fed the same elite (as a uniform) and the same normals gives the same step."""
    res = fitted(env, "pe")
    menv = ModelEnv(res.model, res.job.spec, noise=True, seed=3)
    stepper = jax_stepper(menv)
    assert stepper.sampling and not jax_stepper(ModelEnv(res.model, res.job.spec, noise=False, seed=3)).sampling
    s, a = states_actions(menv, res, seed=1)
    rng = copy.deepcopy(menv.noise_rng)  # what ModelEnv's step will draw: the elite, then the normals
    k, m = len(res.model.elites_), len(res.job.spec.target_names)
    pick = rng.integers(k, size=N)
    eps = rng.standard_normal((N, m))
    ref = menv.step(s, a)
    got = [np.asarray(x) for x in stepper.step(s, a, stepper.init_aux(N), sample_draws=((pick + 0.5) / k, eps))]
    assert np.array_equal(got[2], ref[2]) and np.array_equal(got[3], ref[3])
    assert np.max(np.abs(got[0] - ref[0])) <= 2.5e-7
    mean = np.asarray(stepper.step(s, a, stepper.init_aux(N))[0])  # no draws: the elites' mean
    assert np.max(np.abs(mean - ref[0])) > 1e-3


def test_another_fit_of_the_same_architecture_steps_through_the_same_program():
    """The weights are an argument: two seeds' fits have equal keys and different numbers, and
    one jitted step given the second's numbers gives the second's step."""
    a, b = fitted("mountain_car", "nn32", 0), fitted("mountain_car", "nn32", 1)
    ja, jb = jax_model(a.model), jax_model(b.model)
    assert ja.key == jb.key and not np.array_equal(ja.params["w"][0], jb.params["w"][0])
    menv_a, menv_b = (ModelEnv(r.model, r.job.spec, noise=False, seed=0) for r in (a, b))
    sa, sb = jax_stepper(menv_a), jax_stepper(menv_b)
    assert sa.key == sb.key
    s, act = states_actions(menv_b, b)
    step = jax.jit(lambda s_, a_, p: sa.step(s_, a_, sa.init_aux(N), params=p))
    got = np.asarray(step(s, act, sb.params)[0])
    assert np.max(np.abs(got - menv_b.step(s, act)[0])) <= 2.5e-7
    assert step._cache_size() == 1


def test_the_compiled_ppo_trains_in_an_nn_surrogate_with_its_rollout_compiled():
    """``agent=ppo_jax`` in a ``surrogate=nn`` surrogate: the rollout is one compiled program (no
    fallback to stepping in Python), and the steps are the surrogate's (finite returns)."""
    from sdrl_bench.cli.build import instantiate_key  # noqa: PLC0415
    from sdrl_bench.rl.agents import make_agent  # noqa: PLC0415
    from sdrl_bench.rl.transfer import surrogate_vec_env  # noqa: PLC0415

    cfg = compose_cfg("experiment=fast_mountain_car", "agent=ppo_jax", "surrogate=nn", "collector=random",
                      "n_transitions=300", "surrogate.model.max_steps=300")
    res = fit_dynamics(build_fit_job(cfg))
    agent_cfg = instantiate_key(cfg.agent, "agent")
    model = make_agent(agent_cfg, surrogate_vec_env(res.model, res.job.spec, agent_cfg.n_envs, 0), 0)
    model.learn(2 * model.cfg.rollout_size)
    assert model.rollout_backend == "compiled" and model.rollout_compiles == 1
    assert model.num_timesteps == 2 * model.cfg.rollout_size
    action, _ = model.predict(model.env.reset(), deterministic=True)
    assert action.shape == (agent_cfg.n_envs, 1) and np.all(np.isfinite(action))


def test_the_compiled_rollouts_step_draws_a_probabilistic_ensembles_steps_as_model_env_does():
    """``rl.jax_ppo.surrogate``'s step draws the elite and the normals from its key: steps around
    the elites' mean with the spread of ModelEnv's own draws (per state, within 10% on 5,000
    rows), other keys other steps."""
    from sdrl_bench.rl import jax_ppo  # noqa: PLC0415

    res = fitted("mountain_car", "pe")
    menv = ModelEnv(res.model, res.job.spec, noise=True, seed=0)
    sur = jax_ppo.surrogate(menv)
    s, a = states_actions(menv, res, seed=2)
    aux = jax_stepper(menv).init_aux(N)
    mean = np.asarray(jax_stepper(ModelEnv(res.model, res.job.spec, noise=False, seed=0)).step(s, a, aux)[0])
    one, two = (np.asarray(sur.step(s, a, aux, jax.random.key(k), sur.params)[0]) for k in (0, 1))
    ref = menv.step(s, a)[0]  # ModelEnv's own draws
    assert not np.array_equal(one, two)
    for j in range(s.shape[1]):
        ratio = np.std(one[:, j] - mean[:, j]) / np.std(ref[:, j] - mean[:, j])
        assert 0.9 < ratio < 1.1, (j, ratio)
