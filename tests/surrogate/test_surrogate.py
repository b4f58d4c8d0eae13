"""Surrogate envs: checkers, the MountainCar replay, the VecEnv contract, divergence, bad input."""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import pickle
import warnings

import gymnasium as gym
import numpy as np
import pysindy as ps
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env
from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

import sdrl_bench  # noqa: F401  (registers sdrl/Surrogate-v0)
from sdrl_bench import ConfigError
from sdrl_bench.data import collect, heuristic_policy, random_policy
from sdrl_bench.envs import EnvSpec
from sdrl_bench.envs.lunar_lander import LunarLanderContinuousSpec, LunarLanderSpec
from sdrl_bench.envs.mountain_car import MountainCarSpec
from sdrl_bench.models.fast import batch_predictor, scalar_predictor
from sdrl_bench.models.libraries import LibraryPart, TrigLibrary, build_library
from sdrl_bench.models.sindy import SindyModel
from sdrl_bench.surrogate.env import SurrogateEnv
from sdrl_bench.surrogate.model_env import ModelEnv
from sdrl_bench.surrogate.fidelity import surrogate_fidelity
from sdrl_bench.surrogate.vec import RUNNING_INFO, SurrogateVecEnv


def fit(spec: EnvSpec, parts, threshold: float, n: int, policy, normalize: bool) -> SindyModel:
    """A SINDy fit as the pipeline does it (bound transitions dropped), without tracking."""
    data = collect(spec, policy, n, epsilon=0.2, seed=0)
    x, u = spec.model_inputs(data.states, data.actions)
    keep = ~spec.at_bound(data.next_states)
    lib = build_library(parts, spec.target_names, spec.control_names)
    opt = ps.STLSQ(threshold=threshold, alpha=0.0, normalize_columns=normalize)
    return SindyModel(lib, opt).fit(x[keep], u[keep], data.next_states[keep][:, spec.target_index],
                                    state_names=spec.target_names, control_names=spec.control_names)


@pytest.fixture(scope="module")
def mc_model() -> SindyModel:
    """conf/env/mountain_car.yaml + library poly_trig + STLSQ: 75 heuristic transitions."""
    parts = (LibraryPart(ps.PolynomialLibrary(degree=2)), LibraryPart(TrigLibrary([3.0]), "states"))
    return fit(MountainCarSpec(), parts, 0.003, 75, heuristic_policy, True)


@pytest.fixture(scope="module")
def ll_model() -> SindyModel:
    """conf/env/lunar_lander.yaml + library poly_trig: 1000 heuristic transitions."""
    parts = (LibraryPart(ps.PolynomialLibrary(degree=1)), LibraryPart(TrigLibrary([1.0]), ("angle",)))
    return fit(LunarLanderSpec(), parts, 0.001, 1000, heuristic_policy, False)


@pytest.fixture(scope="module")
def llc_model() -> SindyModel:
    parts = (LibraryPart(ps.PolynomialLibrary(degree=1)),)
    return fit(LunarLanderContinuousSpec(), parts, 0.001, 400, random_policy, False)


@pytest.fixture(scope="module")
def models(mc_model, ll_model, llc_model):
    return {"mountain_car": mc_model, "lunar_lander": ll_model, "lunar_lander_continuous": llc_model}


# ---------------------------------------------------------------------- checkers, registration
@pytest.mark.parametrize("spec", ["mountain_car", "lunar_lander", "lunar_lander_continuous"])
def test_gymnasium_and_sb3_checkers_pass_without_warnings(models, spec):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        gym_check_env(gym.make("sdrl/Surrogate-v0", model=models[spec], spec=spec).unwrapped)
        sb3_check_env(SurrogateEnv(models[spec], spec), warn=True)


def test_gym_make_with_model_path_or_object(mc_model, tmp_path):
    path = mc_model.save(tmp_path / "mc.json")
    runs = []
    for model in (mc_model, str(path), path):
        env = gym.make("sdrl/Surrogate-v0", model=model, spec="mountain_car")
        obs = [env.reset(seed=3)[0]] + [env.step(np.array([0.7], np.float32))[0] for _ in range(20)]
        runs.append(np.array(obs))
    assert np.array_equal(runs[0], runs[1]) and np.array_equal(runs[0], runs[2])
    assert env.observation_space == gym.make("MountainCarContinuous-v0").observation_space
    clone = pickle.loads(pickle.dumps(env.unwrapped))  # compiled steps are rebuilt, not pickled
    action = np.array([-0.3], np.float32)
    assert np.array_equal(clone.step(action)[0], env.unwrapped.step(action)[0])


# ---------------------------------------------------------------------- evaluators agree
@pytest.mark.parametrize("spec", ["mountain_car", "lunar_lander"])
def test_fast_evaluators_match_sindy_predict(models, spec):
    model, rng = models[spec], np.random.default_rng(1)
    z = rng.normal(size=(200, model.n_inputs))
    ref = model.predict(z[:, : len(model.state_names_)], z[:, len(model.state_names_):])
    one = scalar_predictor(model)
    assert np.allclose([one(row) for row in z.tolist()], ref, rtol=1e-12, atol=1e-12)
    assert np.allclose(batch_predictor(model)(z.T).T, ref, rtol=1e-12, atol=1e-12)
    fixed = {model.n_inputs - 1: 1.0}  # e.g. a one-hot action held at 1: partial evaluation
    z[:, -1] = 1.0
    ref = model.predict(z[:, : len(model.state_names_)], z[:, len(model.state_names_):])
    part = scalar_predictor(model, fixed)
    assert np.allclose([part(row[:-1]) for row in z.tolist()], ref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("spec", ["mountain_car", "lunar_lander", "lunar_lander_continuous"])
def test_one_state_step_agrees_with_batched_step(models, spec):
    sur, rng = ModelEnv(models[spec], spec), np.random.default_rng(2)
    states = sur.initial_states(300, rng)
    if spec == "mountain_car":
        states[:, 0] = rng.uniform(-1.2, 0.6, 300)
        states[:, 1] = rng.uniform(-0.07, 0.07, 300)
        actions = rng.uniform(-1.5, 1.5, (300, 1))
    else:  # near the ground, legs touching or not: every branch of the contact rules
        states[:, 1] = rng.uniform(-0.1, 0.2, 300)
        states[:, 2:6] = rng.normal(0, 0.3, (300, 4))
        states[:, 6:8] = rng.integers(0, 2, (300, 2))
        actions = rng.integers(0, 4, (300, 1)) if spec == "lunar_lander" else rng.uniform(-1.2, 1.2, (300, 2))
    nxt, rewards, terminated, diverged = sur.step(states, actions.astype(float))
    for i in range(300):
        a = int(actions[i, 0]) if spec == "lunar_lander" else actions[i]
        obs, n1, r1, t1, d1 = sur.step_one(states[i].tolist(), a)
        assert np.allclose(n1, nxt[i], rtol=0, atol=1e-6) and obs.dtype == np.float32
        assert abs(r1 - rewards[i]) < 1e-3 and (t1, d1) == (terminated[i], diverged[i])
    assert terminated.any() and not terminated.all()


@pytest.mark.parametrize("spec", ["lunar_lander", "lunar_lander_continuous"])
def test_fused_batched_step_agrees_with_the_composed_task_functions(models, spec):
    """LunarLander's compiled step (``make_step_batch``) against the numpy composition of the
    spec's pure functions (apply_bounds, exogenous, clipping, reward_terminated), on states near
    the ground and predictions that include NaN, inf and out-of-limit values."""
    sur, rng = ModelEnv(models[spec], spec), np.random.default_rng(3)
    n, spec_ = 400, sur.spec
    states = sur.initial_states(n, rng)
    states[:, 1] = rng.uniform(-0.1, 0.2, n)
    states[:, 2:6] = rng.normal(0, 0.3, (n, 4))
    states[:, 6:8] = rng.integers(0, 2, (n, 2))
    actions = rng.integers(0, 4, (n, 1)) if spec == "lunar_lander" else rng.uniform(-1.2, 1.2, (n, 2))
    pred = states[:, :6] + rng.normal(0, 0.05, (n, 6))
    pred[:20, 4] = rng.uniform(-8, 8, 20)  # beyond the observation space's angle bounds: clipped
    pred[20, 0], pred[21, 3], pred[22, 5] = np.nan, np.inf, 1e6  # diverged
    nxt, rewards, terminated, diverged = sur._step_batch(states, actions, pred.T.copy())

    ok = np.ones(n, dtype=bool)
    ok[20:23] = False
    assert np.array_equal(diverged, ~ok)
    ref = states.copy()
    ref[:, :6] = spec_.apply_bounds(states, pred)
    ref[:, 6:8] = spec_.task.exogenous(states, actions, ref)
    ref = np.clip(ref, sur.obs_low, sur.obs_high)
    ref_r, ref_t = spec_.task.reward_terminated(states, actions, ref)
    assert np.array_equal(nxt[ok], ref[ok]) and np.array_equal(nxt[~ok], states[~ok])
    assert np.allclose(rewards[ok], ref_r[ok], rtol=0, atol=1e-9)
    assert np.array_equal(terminated[ok], ref_t[ok])
    assert np.all(rewards[~ok] == 0) and not terminated[~ok].any()
    assert 0 < terminated.sum() < n and np.any(nxt[:20, 4] == sur.obs_high[4])
    # the whole transition (model included), fused and composed
    fused, composed = sur.step(states, actions), ModelEnv(models[spec], spec, fused=False).step(states, actions)
    assert np.array_equal(fused[0], composed[0]) and np.allclose(fused[1], composed[1], rtol=0, atol=1e-9)
    assert np.array_equal(fused[2], composed[2]) and np.array_equal(fused[3], composed[3])


# ---------------------------------------------------------------------- MountainCar exactness
def test_mountain_car_task_is_exact_on_real_transitions():
    spec = MountainCarSpec()
    data = collect(spec, heuristic_policy, 400, epsilon=0.2, seed=5)
    assert data.terminated.any()
    reward, terminated = spec.reward_terminated(data.states, data.actions, data.next_states)
    assert np.array_equal(reward, data.rewards) and np.array_equal(terminated, data.terminated)
    m = surrogate_fidelity(fit_mc_exact_law(), spec, data)
    assert m["surrogate/reward_mse"] == 0.0 and m["surrogate/terminated_recall"] == 1.0
    assert m["surrogate/terminated_precision"] == 1.0


def fit_mc_exact_law() -> SindyModel:
    """The real law as a model file (used where the test is about the task, not the fit)."""
    return SindyModel.from_dict({
        "format": "sdrl-bench/sindy-model-v1", "kind": "sindy", "state_names": ["x", "v"],
        "control_names": ["u"], "feature_names": ["x", "v", "u", "cos(3 x)"],
        "terms": [[[0, "pow", 1]], [[1, "pow", 1]], [[2, "pow", 1]], [[0, "cos", 3.0]]],
        "coefficients": [[1, 1, 0.0015, -0.0025], [0, 1, 0.0015, -0.0025]]})


def play(env: gym.Env, seed: int, actions: list | None = None, policy=None, start=None):
    """One episode; ``start`` (x, v) puts both envs in that float64 state after the reset."""
    obs, _ = env.reset(seed=seed)
    if start is not None:
        if isinstance(env.unwrapped, SurrogateEnv):
            obs, _ = env.reset(seed=seed, options={"state": start})
        else:  # gymnasium keeps its reset state as a float64 array
            env.unwrapped.state = np.array(start, dtype=np.float64)
            obs = np.array(start, dtype=np.float32)
    states, acts, rewards, flags, rng = [obs], [], [], [], np.random.default_rng(seed)
    for t in range(999):
        a = actions[t] if actions is not None else policy(obs, rng)
        obs, r, terminated, truncated, _ = env.step(a)
        states.append(obs), acts.append(a), rewards.append(r), flags.append((terminated, truncated))
        if terminated or truncated:
            break
    return np.array(states, dtype=float), acts, rewards, flags


def mountain_car_law(x: float, v: float, a: float) -> tuple[float, float]:
    """gymnasium's MountainCarContinuous law in float64, the state rounded to float32 after each
    step as the real env stores it; written from its source, independently of the package."""
    force = min(max(a, -1.0), 1.0)
    v = min(max(v + force * 0.0015 - 0.0025 * math.cos(3 * x), -0.07), 0.07)
    x = min(max(x + v, -1.2), 0.6)
    v = 0.0 if x == -1.2 and v < 0 else v
    return float(np.float32(x)), float(np.float32(v))


@pytest.fixture(scope="module")
def mc_default_fit():
    """The model the product fits by default: ``sdrl-bench`` (env=mountain_car, poly_trig,
    STLSQ, 75 heuristic eps-0.2 transitions, seed 0), composed from conf/ as the CLI does."""
    from helpers import compose_cfg  # noqa: PLC0415

    from sdrl_bench.cli.build import build_fit_job  # noqa: PLC0415
    from sdrl_bench.pipeline import fit_dynamics  # noqa: PLC0415

    return fit_dynamics(build_fit_job(compose_cfg()))


def _uniform(dtype):
    return lambda obs, rng: rng.uniform(-1.2, 1.2, 1).astype(dtype)


def _greedy(obs, rng):  # push with the velocity's sign, eps 0.2
    return np.array([1.0 if obs[1] >= 0 else -1.0], np.float32) if rng.random() > 0.2 else _uniform(np.float32)(obs, rng)


REPLAYS = {  # name: (reset seed, policy, forced start)
    "uniform float32 actions, 999 steps": (4, _uniform(np.float32), None),
    "uniform float64 actions, 999 steps": (5, _uniform(np.float64), None),
    "greedy: left wall, then the goal": (6, _greedy, None),
    "full push from 0.069: velocity clipped at +0.07": (7, lambda obs, rng: np.array([1.0], np.float32), (-0.5, 0.069)),
    "full push from -0.069: clipped at -0.07, then the wall": (8, lambda obs, rng: np.array([-1.0], np.float32), (-0.6, -0.069)),
}


@pytest.mark.parametrize("case", sorted(REPLAYS))
def test_mountain_car_replay_is_bit_identical(mc_default_fit, case):
    """The surrogate of the default 75-transition fit replays real episodes (same start, same
    actions): every state equal (0 difference, so within 1e-9), every reward, termination and
    truncation equal.

    Two things make that possible, and each is checked to matter. (1) The fit snaps the law's
    coefficients to the decimals the data cannot reject (0.0015, not 0.0014999988). (2) The
    single env computes in the real env's arithmetic (float32 numpy scalars, the position moved
    by the new velocity): the exact law evaluated in float64 and rounded to float32 afterwards
    drifts from the real env within the episode.
    """
    seed, policy, start = REPLAYS[case]
    model = mc_default_fit.model
    assert model.snap_digits_ == [2, 2] and model.coefficients_by_name() == {
        "x": {"x": 1.0, "v": 1.0, "u": 0.0015, "cos(3 x)": -0.0025},
        "v": {"v": 1.0, "u": 0.0015, "cos(3 x)": -0.0025}}
    s_real, acts, r_real, f_real = play(gym.make("MountainCarContinuous-v0"), seed, policy=policy, start=start)
    s_sur, _, r_sur, f_sur = play(gym.make("sdrl/Surrogate-v0", model=model, spec="mountain_car"), seed,
                                  actions=acts, start=start)
    assert len(s_sur) == len(s_real) and np.abs(s_sur - s_real).max() == 0.0
    assert r_sur == r_real and f_sur == f_real
    x, v = s_real[:, 0], s_real[:, 1]
    if "goal" in case:
        assert f_real[-1] == (True, False) and r_real[-1] > 99.0
    if "wall" in case:
        assert np.any((x == np.float32(-1.2)) & (v == 0.0))
    if "+0.07" in case or "-0.07" in case:
        assert np.any(np.abs(v) == np.float32(0.07))
    if "999 steps" in case:
        assert len(acts) == 999 and f_real[-1] == (False, True)
        # (2): the law in float64, rounded afterwards, from the real env's own float64 start,
        # drifts off by float32 ulps (not more: the start and the law are right)
        real = gym.make("MountainCarContinuous-v0")
        real.reset(seed=seed)
        law = [tuple(float(c) for c in real.unwrapped.state)]
        for a in acts:
            law.append(mountain_car_law(*law[-1], float(a[0])))
        assert 1e-9 < np.abs(np.array(law) - s_real).max() < 1e-4


def test_checkers_pass_on_the_exact_law_surrogate(mc_default_fit):
    """The numpy-scalar step (snapped, semi-implicit model) passes both checkers without warnings."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        gym_check_env(gym.make("sdrl/Surrogate-v0", model=mc_default_fit.model, spec="mountain_car").unwrapped)
        sb3_check_env(SurrogateEnv(mc_default_fit.model, "mountain_car"), warn=True)


def test_unsnapped_coefficients_drift_from_the_real_env(mc_default_fit):
    """(1) above: the same fit without snapping (coefficients a few ulps off) loses bit-identity
    over a 999-step episode, though it stays within 1e-4 and keeps every reward."""
    from sdrl_bench.pipeline import fit_dynamics  # noqa: PLC0415

    job = dataclasses.replace(mc_default_fit.job, model_factory=functools.partial(SindyModel, snap_alpha=None))
    raw = fit_dynamics(job).model
    assert raw.snap_digits_ == [0, 0] and raw.coefficients_by_name()["v"]["u"] != 0.0015
    seed, policy, _ = REPLAYS["uniform float32 actions, 999 steps"]
    s_real, acts, r_real, _ = play(gym.make("MountainCarContinuous-v0"), seed, policy=policy)
    s_sur, _, r_sur, _ = play(SurrogateEnv(raw, "mountain_car"), seed, actions=acts)
    gap = np.abs(s_sur - s_real).max()
    assert 1e-9 < gap < 1e-4 and r_sur == r_real


# ---------------------------------------------------------------------- the VecEnv contract
def test_vecenv_auto_reset_terminal_observation_and_truncation(mc_model):
    spec = dataclasses.replace(MountainCarSpec(), max_episode_steps=5)
    venv = SurrogateVecEnv(mc_model, spec, 4, seed=0)
    obs0 = venv.reset()
    venv.set_attr("state", [0.44, 0.07], indices=[2])  # about to reach the goal
    actions = np.zeros((4, 1), np.float32)
    obs, rewards, dones, infos = venv.step(actions)
    assert dones.tolist() == [False, False, True, False] and rewards.dtype == np.float32
    assert infos[2]["terminal_observation"][0] >= 0.45 and infos[2]["TimeLimit.truncated"] is False
    assert rewards[2] == pytest.approx(100.0) and obs[2][1] == 0 and -0.6 <= obs[2][0] <= -0.4
    assert infos[0] is RUNNING_INFO and not infos[0]
    with pytest.raises(TypeError):
        infos[0]["x"] = 1
    for _ in range(4):
        obs, rewards, dones, infos = venv.step(actions)
    assert dones.tolist() == [True, True, False, True]  # the step limit (5), env 2 restarted
    for i in (0, 1, 3):
        assert infos[i]["TimeLimit.truncated"] is True and infos[i]["terminal_observation"].shape == (2,)
        assert not np.array_equal(infos[i]["terminal_observation"], obs[i])
    assert venv.get_attr("elapsed_steps") == [0, 0, 4, 0]
    assert obs0.dtype == np.float32 and obs.flags.c_contiguous


def test_vecenv_is_reproducible_under_a_seed_and_has_the_attribute_api(ll_model):
    def run(venv):
        venv.seed(7)
        out = [venv.reset()]
        rng = np.random.default_rng(0)
        for _ in range(60):
            obs, rew, done, _ = venv.step(rng.integers(0, 4, venv.num_envs))
            out += [obs, rew, done]
        return out
    a, b = SurrogateVecEnv(ll_model, "lunar_lander", 16), SurrogateVecEnv(ll_model, "lunar_lander", 16)
    assert all(np.array_equal(x, y) for x, y in zip(run(a), run(b), strict=True))
    assert any(x.any() for x in run(a)[3::3])  # some episodes ended and were reset
    assert a.get_attr("render_mode") == [None] * 16 and a.env_is_wrapped(gym.Wrapper) == [False] * 16
    assert a.get_attr("env_spec", 0)[0].name == "lunar_lander" and len(a.get_attr("n_diverged")) == 16
    obs, info = a.env_method("reset", indices=[3], options={"state": np.zeros(8)})[0]
    assert np.array_equal(obs, np.zeros(8, np.float32)) and a.get_attr("elapsed_steps", 3) == [0]
    a.set_attr("custom", 5, indices=[1])
    assert a.get_attr("custom", [1]) == [5]
    a.close()


def test_vecenv_works_under_vecmonitor_and_vecnormalize(mc_model, ll_model):
    for model, spec, n in ((mc_model, "mountain_car", 64), (ll_model, "lunar_lander", 8)):
        venv = VecNormalize(VecMonitor(SurrogateVecEnv(model, spec, n, seed=1)))
        venv.reset()
        episodes = []
        for _ in range(150):
            actions = np.array([venv.action_space.sample() for _ in range(n)])
            obs, rewards, dones, infos = venv.step(actions)
            episodes += [info["episode"] for info in infos if "episode" in info]
            assert np.all(np.isfinite(obs)) and np.all(np.isfinite(rewards))
        assert spec == "mountain_car" or episodes  # LunarLander episodes end within 150 steps
        assert all(set(ep) >= {"r", "l"} for ep in episodes)


# ---------------------------------------------------------------------- divergence guard
def unstable_mc_model(growth: float = 3.0) -> SindyModel:
    """x' = growth * x, v' = growth * v + 0.01: leaves any bound in a few steps."""
    return SindyModel.from_dict({
        "format": "sdrl-bench/sindy-model-v1", "kind": "sindy", "state_names": ["x", "v"],
        "control_names": ["u"], "feature_names": ["1", "x", "v", "x v"],
        "terms": [[], [[0, "pow", 1]], [[1, "pow", 1]], [[0, "pow", 1], [1, "pow", 1]]],
        "coefficients": [[0, growth, 0, 1e308], [0.01, 0, growth, 0]]})


def test_divergence_guard_truncates_without_nan_single_and_vectorized():
    env = SurrogateEnv(unstable_mc_model(), "mountain_car")
    obs, _ = env.reset(seed=0)
    for t in range(50):  # noqa: B007 (the step it broke at is read after the loop)
        nxt, reward, terminated, truncated, info = env.step(np.array([0.0], np.float32))
        assert np.all(np.isfinite(nxt)) and np.isfinite(reward)
        if truncated:
            break
    assert info == {"surrogate_diverged": True} and not terminated and reward == 0.0
    assert env.n_diverged == 1 and t < 10
    venv = SurrogateVecEnv(unstable_mc_model(), "mountain_car", 32, seed=0)
    venv.reset()
    for _ in range(10):
        obs, rewards, dones, infos = venv.step(np.zeros((32, 1)))
        assert np.all(np.isfinite(obs)) and np.all(np.isfinite(rewards))
    assert venv.n_diverged.sum() >= 32 and all(np.isfinite(x).all() for x in obs)
    flagged = [info for info in infos if info.get("surrogate_diverged")]
    assert all(info["TimeLimit.truncated"] and np.isfinite(info["terminal_observation"]).all() for info in flagged)


# ---------------------------------------------------------------------- bad input
def test_bad_models_and_specs_fail_at_construction_naming_the_culprit(mc_model, ll_model, tmp_path):
    with pytest.raises(ConfigError, match=r"model regresses states \['x', 'y'.*needs \['x', 'v'\]"):
        SurrogateEnv(ll_model, "mountain_car")
    with pytest.raises(ConfigError, match="model file not found: .*nope.json"):
        gym.make("sdrl/Surrogate-v0", model=tmp_path / "nope.json", spec="mountain_car")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ConfigError, match="bad.json: not a valid model file"):
        SurrogateEnv(tmp_path / "bad.json", "mountain_car")
    broken = mc_model.to_dict()
    broken["coefficients"] = broken["coefficients"][:1]
    (tmp_path / "broken.json").write_text(json.dumps(broken))
    with pytest.raises(ConfigError, match="broken.json: not a valid SINDy model file"):
        SurrogateEnv(tmp_path / "broken.json", "mountain_car")
    with pytest.raises(ConfigError, match="state_low must be below"):
        MountainCarSpec(state_low=(0.6, -0.07), state_high=(-1.2, 0.07))
    for bad in ("int32", "floot32"):  # the observation's dtype: a float type, else one line naming the key
        with pytest.raises(ConfigError, match=rf"^env.spec.obs_dtype: a float type \(float32, float64\) is required, got '{bad}'$"):
            MountainCarSpec(obs_dtype=bad)
    assert MountainCarSpec(obs_dtype="float64").round_obs(np.array([0.1]))[0] == 0.1
    with pytest.raises(ConfigError, match=r"env.spec.state_low\[0\] = -5.0 \(x\) lies outside"):
        SurrogateEnv(mc_model, MountainCarSpec(state_low=(-5.0, -0.07)))
    with pytest.raises(ConfigError, match="defines no reward"):
        SurrogateEnv(mc_model, EnvSpec(name="mc", gym_id="MountainCarContinuous-v0", state_names=("x", "v")))
    with pytest.raises(ConfigError, match="unknown env 'acrobot'"):
        SurrogateEnv(mc_model, "acrobot")
    with pytest.raises(ConfigError, match=r"but env.spec 'cartpole' needs \['x', 'xdot', 'th', 'thdot'\]"):
        SurrogateEnv(mc_model, "cartpole")  # found by name in the config tree (conf/env/cartpole.yaml)


# ---------------------------------------------------------------------- LunarLander task fidelity
def test_lunar_lander_fidelity_metrics_on_real_transitions(ll_model):
    spec = LunarLanderSpec()
    test = collect(spec, heuristic_policy, 1500, epsilon=0.2, seed=31_000)
    m = surrogate_fidelity(ll_model, spec, test)
    for key in ("surrogate/reward_mse", "surrogate/terminated_precision", "surrogate/terminated_recall",
                "surrogate/leg_left_accuracy", "surrogate/leg_right_accuracy", "surrogate/one_step/reward_mse"):
        assert np.isfinite(m[key]), key
    assert m["surrogate/leg_left_accuracy"] > 0.85 and m["surrogate/leg_right_accuracy"] > 0.85
    for prefix in ("surrogate/", "surrogate/one_step/"):  # per cause, for LunarLander
        assert {f"{prefix}crash_recall", f"{prefix}rest_recall"} <= set(m)
    assert m["surrogate/reward_mse_running"] < 100  # shaping and engine costs: leg flips cost +-10
    assert all(type(v) is float for v in m.values())
    env = SurrogateEnv(ll_model, spec)
    first = [env.reset(seed=s)[0] for s in (1, 2, 1)]
    assert np.array_equal(first[0], first[2]) and not np.array_equal(first[0], first[1])
    assert 1.3 < first[0][1] < 1.5 and first[0][6] == first[0][7] == 0  # observed real starts


def test_an_nn_model_by_path_drives_both_envs(tmp_path):
    """Any fitted model with predict(x, u) and names works (generic evaluators), by path too."""
    from sdrl_bench.models.nn import MLPDynamics

    spec = MountainCarSpec()
    data = collect(spec, heuristic_policy, 75, epsilon=0.2, seed=0)
    x, u = spec.model_inputs(data.states, data.actions)
    model = MLPDynamics(width=16, max_steps=50).fit(x, u, data.next_states, state_names=spec.target_names,
                                                    control_names=spec.control_names)
    path = model.save(tmp_path / "nn" / "model.json")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sb3_check_env(SurrogateEnv(path, "mountain_car"), warn=True)
    venv = SurrogateVecEnv(path, "mountain_car", 16, seed=0)
    venv.reset()
    start = np.array(venv.get_attr("state"))  # float64: MountainCar starts unrounded, as the real env
    obs, rewards, dones, _ = venv.step(np.ones((16, 1)))
    expected = spec.apply_bounds(start, model.predict(*spec.model_inputs(start, np.ones((16, 1)))))
    assert not dones.any() and np.array_equal(obs, expected.astype(np.float32))
    assert np.array_equal(rewards, np.full(16, -0.1, np.float32))
