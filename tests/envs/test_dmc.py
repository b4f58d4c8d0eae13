"""The DeepMind Control Suite's cartpole swing-up (conf/env/cartpole_swingup.yaml), added from
YAML and the plain functions of sdrl_bench/envs/dmc.py: the real env through shimmy with its
Dict observation flattened and its 32-bit seeds, the task functions against the real env, a
SINDy fit from random data, and the surrogate on the circle."""

from __future__ import annotations

import numpy as np
import pytest
from stable_baselines3.common.env_checker import check_env

from helpers import compose_cfg
from sdrl_bench import seeds
from sdrl_bench.cli.build import build_fit_job
from sdrl_bench.envs.functional import import_object
from sdrl_bench.pipeline import fit_dynamics
from sdrl_bench.surrogate.env import SurrogateEnv


@pytest.fixture(scope="module")
def spec():
    return build_fit_job(compose_cfg("env=cartpole_swingup", "collector=random")).spec


def _rollout(spec, seed: int, n: int):
    env = spec.make_env()
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seeds.reset_seed(seed, "collect"))
    rows = []
    for _ in range(n):
        a = rng.uniform(-1, 1, size=1)
        nxt, r, term, trunc, _ = env.step(a)
        rows.append((obs, a, r, nxt))
        obs = nxt
    return [np.array(c) for c in zip(*rows, strict=True)]


def test_the_real_env_is_flattened_and_takes_the_harness_seeds(spec):
    """shimmy's Dict observation becomes (x, cos, sin, xdot, thdot); a 64-bit harness reset seed
    reaches the env hashed to 32 bits: the same seed gives the same start, another seed another."""
    env = spec.make_env()
    assert env.observation_space.shape == (5,)
    a, _ = env.reset(seed=seeds.reset_seed(0, "collect"))
    b, _ = env.reset(seed=seeds.reset_seed(0, "collect"))
    c, _ = env.reset(seed=seeds.reset_seed(1, "collect"))
    assert seeds.reset_seed(0, "collect") >= 2**32
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert np.hypot(a[1], a[2]) == pytest.approx(1.0) and a[1] < -0.99  # hanging


@pytest.mark.parametrize("bits", [8, 65, "32"])
def test_a_bad_seed_width_is_one_line_naming_the_key(bits):
    from sdrl_bench import ConfigError

    with pytest.raises(ConfigError, match=r"^env.spec.reset_seed_bits: an integer in \[16, 64\] is required"):
        build_fit_job(compose_cfg("env=cartpole_swingup", "collector=random", f"env.spec.reset_seed_bits={bits!r}"))


def test_the_reward_function_is_the_suites(spec):
    obs, act, rew, nxt = _rollout(spec, 3, 400)
    s, s2 = spec.coordinates(obs), spec.coordinates(nxt, spec.coordinates(obs))
    mine = import_object(spec.reward_fn, "env.spec.reward_fn")(s, act, s2)
    assert np.max(np.abs(mine - rew)) <= 1e-12
    assert rew.min() >= 0.0 and rew.max() <= 1.0


def test_the_initial_states_match_the_real_resets(spec):
    env = spec.make_env()
    real = spec.coordinates(np.array([env.reset(seed=seeds.reset_seed(s, "reset_pool"))[0] for s in range(200)]))
    mine = import_object(spec.initial_state_fn, "env.spec.initial_state_fn")(np.random.default_rng(0), 200)
    real[:, 1] = np.mod(real[:, 1], 2 * np.pi)  # th near pi from either side
    for j in range(4):
        assert abs(real[:, j].mean() - mine[:, j].mean()) < 0.004
        assert real[:, j].std() == pytest.approx(0.01, rel=0.25) and mine[:, j].std() == pytest.approx(0.01, rel=0.25)


def test_a_fit_from_random_transitions_and_a_surrogate_on_the_circle():
    """2,000 random transitions: the positions move by the mean of the velocities (MuJoCo's RK4)
    to 1e-7; the velocities' laws explain the held-out steps (R^2 > 0.99); the surrogate passes
    SB3's checker and keeps cos and sin on the circle."""
    res = fit_dynamics(build_fit_job(compose_cfg("env=cartpole_swingup", "collector=random", "n_transitions=2000")))
    m = res.fidelity.metrics
    assert m["mse/x"] < 1e-7 and m["mse/th"] < 1e-7
    assert m["r2/xdot"] > 0.99 and m["r2/thdot"] > 0.99
    lines = dict(line.split(" = ", 1) for line in res.model.describe().splitlines())
    assert lines["x'"].startswith("x +0.00") and "xdot'" in lines["x'"]
    env = SurrogateEnv(res.model, res.job.spec)
    check_env(env)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (5,) and obs[1] < -0.99
    for _ in range(300):
        obs, r, term, trunc, _ = env.step(env.action_space.sample())
        assert abs(np.hypot(obs[1], obs[2]) - 1) < 1e-6 and 0.0 <= r <= 1.0


# ---------------------------------------------------------------- SINDy-RL's model form
@pytest.fixture(scope="module")
def circle_spec():
    return build_fit_job(compose_cfg("env=cartpole_swingup_circle", "collector=random")).spec


def test_the_circle_form_observes_its_states_and_its_task_is_the_suites(spec, circle_spec):
    """cartpole_swingup_circle's states are the real observations (no map); its reward equals the
    suite's on real transitions, and its resets are the angle form's draws in observation form."""
    assert not circle_spec.maps_observations and circle_spec.circle_pairs == (("cos_th", "sin_th"),)
    obs, act, rew, nxt = _rollout(circle_spec, 4, 400)
    mine = import_object(circle_spec.reward_fn, "env.spec.reward_fn")(obs, act, nxt)
    assert np.max(np.abs(mine - rew)) <= 1e-12
    a = import_object(circle_spec.initial_state_fn, "")(np.random.default_rng(5), 50)
    b = import_object(spec.initial_state_fn, "")(np.random.default_rng(5), 50)
    assert np.allclose(a, spec.observe(b), atol=0, rtol=0)


def test_the_circle_pairs_are_projected_back_onto_the_circle(circle_spec):
    """apply_bounds divides each predicted (cos, sin) pair by its norm; other states pass as they are;
    a pair at the origin stays (no division by zero)."""
    pred = np.array([[0.3, -1.1, 0.2, 0.5, -2.0], [0.0, 0.0, 0.0, 1.0, 1.0], [1.0, 0.6, 0.8, 0.0, 0.0]])
    out = circle_spec.apply_bounds(pred, pred)
    r = np.hypot(-1.1, 0.2)
    assert np.array_equal(out[0], [0.3, -1.1 / r, 0.2 / r, 0.5, -2.0])
    assert np.array_equal(out[1], pred[1]) and np.array_equal(out[2], pred[2])


@pytest.mark.parametrize("pairs, match", [
    ("[[cos_th]]", r"circle_pairs\[0\]: expected \[cos name, sin name\]"),
    ("[[cos_th,cos_th]]", r"circle_pairs\[0\]: expected \[cos name, sin name\]"),
    ("[[cos_th,th]]", r"circle_pairs\[0\]: \['th'\] are not regressed states"),
    ("[[cos_th,sin_th],[sin_th,x]]", r"circle_pairs\[1\]: \['sin_th'\] already in another pair"),
])
def test_a_bad_circle_pair_is_one_line_naming_the_key(pairs, match):
    from sdrl_bench import ConfigError

    with pytest.raises(ConfigError, match=r"^env.spec." + match):
        build_fit_job(compose_cfg("env=cartpole_swingup_circle", "collector=random", f"env.spec.circle_pairs={pairs}"))


def test_sindy_rls_library_fits_the_circle_form():
    """SINDy-RL's 41 terms on 2,000 random transitions, 20 bagged STLSQ fits (median): the cart's
    position law x' = x + 0.01 xdot and the pole's rotation cos' = cos - 0.01 sin thdot are found
    to 1e-3 relative, the velocities explain the held-out steps, and a surrogate episode keeps the
    angle's pair on the circle."""
    res = fit_dynamics(build_fit_job(compose_cfg("env=cartpole_swingup_circle", "collector=random",
                                                 "n_transitions=2000")))
    m, model = res.fidelity.metrics, res.model
    from sdrl_bench.models.per_equation import term_text

    coef = {s: {term_text(t): c for t, c in zip(model.library.parsed[s], model.eq_coef_[s], strict=True)}
            for s in model.state_names_}
    assert len(model.library.parsed["xdot"]) == 41 and all("bias" not in k and k for k in coef["xdot"])
    assert coef["x"]["x"] == pytest.approx(1.0, abs=1e-3) and coef["x"]["xdot"] == pytest.approx(0.01, rel=1e-2)
    assert coef["cos_th"]["cos_th"] == pytest.approx(1.0, abs=1e-3)
    assert coef["cos_th"]["sin_th*thdot"] == pytest.approx(-0.01, rel=1e-2)
    assert m["r2/xdot"] > 0.99 and m["r2/thdot"] > 0.99
    env = SurrogateEnv(model, res.job.spec)
    check_env(env)
    obs, _ = env.reset(seed=0)
    for _ in range(300):
        obs, r, term, trunc, _ = env.step(env.action_space.sample())
        assert abs(np.hypot(obs[1], obs[2]) - 1) < 1e-12 and 0.0 <= r <= 1.0
