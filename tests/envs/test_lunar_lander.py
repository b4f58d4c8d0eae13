"""LunarLander's surrogate: the flight law from a small fixed dataset, the touchdown event
against hand-built impacts, the sleep counter, seeded noise in the step."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from sdrl_bench.data import collect, heuristic_policy
from sdrl_bench.envs.lunar_lander import LunarLanderSpec
from sdrl_bench.envs.lunar_lander import task
from sdrl_bench.envs.lunar_lander.task import LanderRules
from sdrl_bench.models.per_equation import PerEquationLibrary, PerEquationModel
from sdrl_bench.surrogate.env import SurrogateEnv
from sdrl_bench.surrogate.vec import SurrogateVecEnv

import pysindy as ps

FLIGHT_YAML = Path(__file__).resolve().parents[2] / "sdrl_bench" / "conf" / "library" / "lunar_lander_flight.yaml"
SPEC = LunarLanderSpec(fit_regime="flight")


@pytest.fixture(scope="module")
def flight_model() -> PerEquationModel:
    """The flight library (its YAML, ensemble 3) on the flight rows of 600 heuristic transitions, 100 per episode
    (eps 0.2, seed 0: a small fixed dataset)."""
    part = yaml.safe_load(FLIGHT_YAML.read_text())["parts"][0]["library"]
    lib = PerEquationLibrary(equations=part["equations"], form=part["form"], threshold=part["threshold"],
                             noise_by=part["noise_by"], ensemble=3)
    data = collect(SPEC, heuristic_policy, 600, epsilon=0.2, seed=0, max_steps_per_episode=100)
    rows = SPEC.fit_rows(data.episode, data.states, data.rewards, data.next_states)
    x, u = SPEC.model_inputs(data.states, data.actions)
    return PerEquationModel(lib, ps.STLSQ(threshold=0.0, alpha=0.0)).fit(
        x[rows], u[rows], data.next_states[rows][:, SPEC.target_index], state_names=SPEC.target_names,
        control_names=SPEC.control_names)


def test_flight_law_recovered_from_a_small_dataset(flight_model):
    c, eqs = flight_model.eq_coef_, flight_model.library.parsed
    first = {s: float(c[s][0]) for s in ("x", "y", "vy", "angle")}  # vx', vy', bias, angvel'
    assert [str(eqs[s][0]) for s in ("x", "vy")] and first["x"] == pytest.approx(0.0100, abs=2e-4)
    assert first["y"] == pytest.approx(0.0225, abs=5e-4)  # 0.02 s x (2/15) / 0.2 x (obs scale ratio)
    assert first["vy"] == pytest.approx(-10 * 0.02 * 2 / 15, abs=1e-3)  # gravity: -0.02667
    assert first["angle"] == pytest.approx(0.05, abs=1e-3)  # 0.02 s / 0.4
    assert flight_model.n_fit_samples_ > 200 and set(flight_model.noise_) == {"a_left", "a_main", "a_right"}
    assert np.diag(flight_model.noise_["a_main"])[3] > 10 * np.diag(flight_model.noise_["a_left"])[3]


def state(y=0.0, vy=-0.1, angle=0.0, legs=0.0, vx=0.0, w=0.0):
    return np.array([0.0, y, vx, vy, angle, w, legs, legs])


@pytest.mark.parametrize("pre, crash", [
    (state(vy=-0.1), False),              # soft, vertical: survives, stands on its legs
    (state(vy=-0.25), False),
    (state(vy=-0.6), True),               # 4.5 m/s down: the hull hits the ground
    (state(vy=-0.1, angle=1.1), True),    # lying on its side
])
def test_touchdown_event_from_the_pre_impact_state(flight_model, pre, crash):
    env = SurrogateEnv(flight_model, SPEC)
    obs = env.reset(seed=0, options={"state": pre})[0]
    for _ in range(5):  # free fall (no-op: no noise) to the ground
        obs, r, term, trunc, _ = env.step(0)
        if obs[6] or obs[7] or term:
            break
    assert max(obs[6], obs[7]) == 1.0 and term == crash and not trunc
    assert (r == -100.0) == crash


def test_sleep_counter_rests_after_25_quiet_steps_and_restarts_after_motion(flight_model):
    env = SurrogateEnv(flight_model, SPEC)
    env.reset(seed=0, options={"state": state(y=0.0, vy=0.0, legs=1.0)})
    rewards = [env.step(0)[1] for _ in range(10)]
    assert max(rewards) < 100
    env.step(2)  # the main engine: not quiet (Box2D keeps the body awake)
    out = [env.step(0) for _ in range(25)]
    assert [o[2] for o in out] == [False] * 24 + [True] and out[-1][1] == 100.0
    # the same rule along recorded rows: counts reset by an engine step and by a new episode
    ns = np.tile(state(y=0.0, vy=0.0, legs=1.0), (6, 1))
    counts = task.sleep_counts(LanderRules(), [0, 0, 0, 0, 1, 1], ns, np.array([[0], [0], [2], [0], [0], [0]]))
    assert counts.tolist() == [1, 2, 0, 1, 1, 2]


def test_step_noise_is_seeded_and_reproducible(flight_model):
    env = SurrogateEnv(flight_model, SPEC)
    actions = [2, 2, 0, 1, 3, 2] * 5

    def run(seed):
        env.reset(seed=seed)
        return np.array([env.step(a)[0] for a in actions])

    a, b, c = run(3), run(3), run(4)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    det = SurrogateEnv(flight_model, SPEC)  # the noise is the main engine's: a no-op step has none
    det.surrogate._chol = None
    s0 = det.reset(seed=3)[0]
    assert np.array_equal(det.step(0)[0], (env.reset(seed=3)[0], env.step(0)[0])[1]) and s0[1] > 1.0
    v1, v2 = SurrogateVecEnv(flight_model, SPEC, 16, seed=5), SurrogateVecEnv(flight_model, SPEC, 16, seed=5)
    acts = np.full((16, 1), 2)
    v1.reset(), v2.reset()
    assert all(np.array_equal(v1.step(acts)[0], v2.step(acts)[0]) for _ in range(20))


def test_regimes_split_episodes_at_the_first_touchdown():
    ns = np.zeros((6, 8))
    ns[2, 6] = 1.0  # episode 0 touches down at its third row
    rewards = np.array([0, 0, 0, 0, 0, -100.0])
    ns[5, 0] = 0.5  # episode 1 crashes (inside the screen) at its second row
    reg = SPEC.regimes(np.array([0, 0, 0, 0, 1, 1]), ns, rewards, ns)
    assert reg["flight"].tolist() == [True, True, False, False, True, False]


def test_one_state_step_agrees_with_the_batched_step_with_the_penalty(flight_model):
    """Flight, touchdowns and the settle step, with the ensemble penalty on (noise off)."""
    from sdrl_bench.surrogate.model_env import ModelEnv

    spec = LunarLanderSpec(fit_regime="flight", uncertainty={"penalty": 1.0, "free": 0.0})
    sur, rng = ModelEnv(flight_model, spec, noise=False), np.random.default_rng(2)
    states = sur.initial_states(200, rng)
    states[:, 1] = rng.uniform(-0.03, 0.1, 200)
    states[:, 2:6] = rng.normal(0, 0.3, (200, 4))
    states[:, 6:8] = rng.integers(0, 2, (200, 1))
    actions = rng.integers(0, 4, (200, 1))
    nxt, rewards, terminated, diverged = sur.step(states, actions)
    one = [sur.step_one(states[i].tolist(), int(actions[i, 0])) for i in range(200)]
    assert np.allclose([o[1] for o in one], nxt, rtol=0, atol=1e-6)
    assert np.allclose([o[2] for o in one], rewards, rtol=0, atol=1e-6)
    assert [o[3] for o in one] == terminated.tolist() and 0 < terminated.sum() < 200
    plain = ModelEnv(flight_model, LunarLanderSpec(), noise=False).step(states, actions)[1]
    flight = (states[:, 6] == 0) & ~terminated
    assert np.all(rewards[flight] < plain[flight]) and np.array_equal(rewards[~flight], plain[~flight])


# ------------------------------------------------------------------ terrain
@pytest.mark.parametrize("seed", [0, 1, 7])
def test_terrain_is_drawn_as_the_real_env_draws_it(seed):
    """``draw_terrain`` from the generator the real env is seeded with gives the real env's
    ground: its terrain polygons' edge heights, converted to observation units."""
    import gymnasium as gym

    env = gym.make("LunarLander-v3").unwrapped
    env.reset(seed=seed)
    h = 400 / 30
    real = np.array([p[0][1] for p in env.sky_polys] + [env.sky_polys[-1][1][1]])  # 11 edge heights (m)
    ours = task.draw_terrain(np.random.default_rng(seed), 1)[0]
    assert np.allclose(ours * (h / 2) + 0.99 * h / 4, real, rtol=0, atol=1e-9)
    assert np.all(ours[4:7] == 0.0) and np.ptp(ours) > 0.05  # flat on the pad, hills off it
    env.close()


@pytest.mark.parametrize("seed", [0, 3])
def test_the_slope_rule_reads_the_real_grounds_slope_in_metres(seed):
    """``kernels.slope_crash`` on the ground the real env draws (``draw_terrain`` from its seed)
    fires exactly where the real terrain's polygons rise more than ``slope_crash`` m per m
    between the legs, for an upright lander across the screen."""
    import gymnasium as gym

    from sdrl_bench.envs.lunar_lander.kernels import LEG_X, ground_at, slope_crash

    env = gym.make("LunarLander-v3").unwrapped
    env.reset(seed=seed)
    edges = [p[0] for p in env.sky_polys] + [env.sky_polys[-1][1]]  # (x, y) in metres
    wx, wy = np.array([e[0] for e in edges]), np.array([e[1] for e in edges])
    g = task.draw_terrain(np.random.default_rng(seed), 1)[0]
    k = task.rules_vector(task.LanderRules(slope_crash=0.1))
    fired, slopes = [], []
    for x in np.linspace(-0.9, 0.9, 181):
        xl, xr = x - LEG_X, x + LEG_X
        real = abs(np.interp(10 * xr + 10, wx, wy) - np.interp(10 * xl + 10, wx, wy)) / (10 * (xr - xl))
        if abs(real - 0.1) > 1e-6:  # off the threshold itself
            fired.append(slope_crash(ground_at(g, xl), ground_at(g, xr), 0.0, k))
            slopes.append(real)
    assert fired == [v > 0.1 for v in slopes] and any(fired) and not all(fired)
    off = task.rules_vector(task.LanderRules())  # the default: the slope is ignored
    assert not any(slope_crash(ground_at(g, x - LEG_X), ground_at(g, x + LEG_X), 0.0, off) for x in np.linspace(-0.9, 0.9, 19))
    env.close()


def test_with_terrain_a_lander_touches_down_on_the_ground_under_its_legs(flight_model):
    """A lander sinking slowly at x = -0.6 (off the pad) touches down at the ground's height
    there, stands on it (the floor follows the ground), and a new episode draws new ground;
    the same seed draws the same ground."""
    from sdrl_bench.envs.lunar_lander.kernels import LEG_X, ground_at
    from sdrl_bench.surrogate.model_env import ModelEnv

    spec = LunarLanderSpec(fit_regime="flight", terrain=True)

    def ground(seed):  # a surrogate seeded like an env reset, one step to draw the row's terrain
        sur = ModelEnv(flight_model, spec)
        sur.seed(seed)
        s = np.array([[-0.6, 1.0, 0, 0, 0, 0, 0, 0]])
        nxt = sur._step_batch(s, np.zeros((1, 1)), s[:, :6].T.copy())[0]
        return sur, sur._step_batch.memory["ground"][0].copy(), nxt

    seed = next(sd for sd in range(50) if ground(sd)[1][2] > 0.15)  # a hill at x = -0.6
    sur, g, s = ground(seed)
    assert np.array_equal(g, ground(seed)[1]) and not np.array_equal(g, ground(seed + 1)[1])
    gl, gr = ground_at(g, -0.6 - LEG_X), ground_at(g, -0.6 + LEG_X)
    under = 0.5 * (gl + gr)
    pred = s[:, :6].T.copy()
    pred[1] = max(gl, gr) + 0.03  # down to just above the hill (the episode goes on: same terrain)
    s = sur._step_batch(s, np.zeros((1, 1)), pred)[0]
    assert np.array_equal(sur._step_batch.memory["ground"][0], g)
    heights = []
    for _ in range(20):  # sink 0.004 per step (a soft touchdown), legs up
        pred = s[:, :6].T.copy()
        pred[1] -= 0.004
        s, r, term, _ = sur._step_batch(s, np.zeros((1, 1)), pred)
        heights.append(s[0, 1])
        if s[0, 6] or s[0, 7]:
            break
    assert max(s[0, 6], s[0, 7]) == 1.0 and not term[0] and heights[-1] > 0.1  # far above the pad's height
    g_leg = gl if s[0, 6] else gr  # the leg that touched, on the ground under it
    assert heights[-1] - g_leg <= spec.rules.touch_height < heights[-2] - g_leg
    legs = s.copy()
    pred = legs[:, :6].T.copy()
    pred[1] = -0.3  # the model sinks it: the ground holds it up
    s, _, _, _ = sur._step_batch(legs, np.zeros((1, 1)), pred)
    assert s[0, 1] == pytest.approx(under + spec.rules.floor, abs=1e-6)
    fresh = np.array([[0.3, 1.2, 0, 0, 0, 0, 0, 0]])  # a state the step did not return: a new episode
    sur._step_batch(fresh, np.zeros((1, 1)), fresh[:, :6].T.copy())
    assert not np.array_equal(sur._step_batch.memory["ground"][0], g)


@pytest.mark.parametrize("x0", [-0.6, 0.0])
def test_with_the_slope_rule_a_touchdown_on_a_hill_crashes(flight_model, x0):
    """With ``slope_crash`` set, the slow touchdown that survives on a hill above (x = -0.6)
    ends the episode with -100 there, and still survives on the flat pad (x = 0); the same
    states and the same terrain, only the rule differs."""
    from sdrl_bench.envs.lunar_lander.kernels import LEG_X, ground_at
    from sdrl_bench.surrogate.model_env import ModelEnv

    def touchdown(rules, seed):
        sur = ModelEnv(flight_model, LunarLanderSpec(fit_regime="flight", terrain=True, rules=rules))
        sur.seed(seed)
        s = np.array([[x0, 1.0, 0, 0, 0, 0, 0, 0]])
        s = sur._step_batch(s, np.zeros((1, 1)), s[:, :6].T.copy())[0]  # draws the episode's ground
        g = sur._step_batch.memory["ground"][0].copy()
        pred = s[:, :6].T.copy()
        pred[1] = max(ground_at(g, x0 - LEG_X), ground_at(g, x0 + LEG_X)) + 0.03
        s = sur._step_batch(s, np.zeros((1, 1)), pred)[0]
        for _ in range(20):
            pred = s[:, :6].T.copy()
            pred[1] -= 0.004
            s, r, term, _ = sur._step_batch(s, np.zeros((1, 1)), pred)
            if s[0, 6] or s[0, 7] or term[0]:
                assert np.array_equal(sur._step_batch.memory["ground"][0], g)  # the same episode
                return g, float(r[0]), bool(term[0])
        raise AssertionError("no touchdown")

    def hill(seed):  # ground that slopes over 0.1 (metres) under the legs at x = -0.6
        g = touchdown(task.LanderRules(), seed)[0]
        return abs(ground_at(g, -0.6 + LEG_X) - ground_at(g, -0.6 - LEG_X)) / (2 * LEG_X) / 1.5 > 0.1

    seed = next(sd for sd in range(50) if hill(sd))
    g, r, term = touchdown(task.LanderRules(slope_crash=0.1), seed)
    g0, r0, term0 = touchdown(task.LanderRules(), seed)
    assert np.array_equal(g, g0) and not term0 and r0 > -100.0
    if x0 == 0.0:  # the pad is flat: the rule does not fire
        assert not term and r == r0
    else:
        assert term and r == -100.0
