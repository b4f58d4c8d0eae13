"""The surrogate's step as one JAX function (surrogate/jax_step.py) against ``ModelEnv.step``: for
every env whose task is plain functions (Pendulum, CartPole, the swing-up in both forms) and
MountainCar (a task its spec class builds), 10,000 random states and actions spanning the data, the
bounds and beyond (bounds, clips, circle projection, MountainCar's wall and goal, and rows whose
prediction diverges or is not finite), with the step noise off and fed in; jit against eager;
ModelEnv's noise draws reproduced; the task functions on jax keys; unsupported tasks refused in
one line; the package imports without jax."""

from __future__ import annotations

import copy
import dataclasses
import os
import subprocess
import sys

import numpy as np
import pytest

jax = pytest.importorskip("jax")
pytestmark = pytest.mark.jax

import jax.numpy as jnp  # noqa: E402

from helpers import compose_cfg  # noqa: E402
from sdrl_bench import ConfigError  # noqa: E402
from sdrl_bench.cli.build import build_fit_job  # noqa: E402
from sdrl_bench.envs.base import action_bounds  # noqa: E402
from sdrl_bench.envs.functional import resolve  # noqa: E402
from sdrl_bench.pipeline import fit_dynamics  # noqa: E402
from sdrl_bench.surrogate.jax_step import jax_reset, jax_step, step_noise  # noqa: E402
from sdrl_bench.surrogate.model_env import ModelEnv  # noqa: E402

ENVS = {"pendulum": 200, "cartpole": 200, "cartpole_swingup": 300, "cartpole_swingup_circle": 300, "mountain_car": 300}
"""Every env whose task is plain functions, and MountainCar's (its spec's class builds it), with
transitions for a quick fit (MountainCar: 300 random ones give its exact law)."""
PLAIN = [env for env in ENVS if env != "mountain_car"]
N, TOL = 10_000, 1e-12
_FITS: dict[str, tuple] = {}


def fitted(env: str) -> tuple:
    """(model, spec, the fit's states), fitted once per env from random transitions."""
    if env not in _FITS:
        res = fit_dynamics(build_fit_job(compose_cfg(f"env={env}", "collector=random", f"n_transitions={ENVS[env]}")))
        _FITS[env] = (res.model, res.job.spec, res.data.states)
    return _FITS[env]


def draw(spec, data: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """N states spanning the data's range and the spec's finite bounds, widened by that span on
    each side (past the bounds); 3% of them 1000 times larger (beyond the divergence limit), 0.5%
    with an inf or NaN entry (a non-finite prediction). Actions: indices, or 1.5 times the action
    space's range."""
    rng = np.random.default_rng(seed)
    lo, hi = data.min(axis=0), data.max(axis=0)
    for bound, side, pick in ((spec.state_low, lo, np.fmin), (spec.state_high, hi, np.fmax)):
        if bound is not None:  # fmin / fmax skip the NaN of an unbounded side
            side[:] = pick(side, np.where(np.isfinite(bound), bound, np.nan))
    span = np.where(hi > lo, hi - lo, 1.0)
    s = rng.uniform(lo - span, hi + span, size=(N, data.shape[1]))
    s[:300] *= 1e3
    s[300:350, 0] = np.inf
    s[350:360, -1] = np.nan
    if spec.n_discrete_actions:
        return s, rng.integers(spec.n_discrete_actions, size=(N, 1))
    low, high = action_bounds(spec)
    return s, rng.uniform(1.5 * low, 1.5 * high, size=(N, spec.raw_action_width))


def compare(got, ref) -> tuple[float, float]:
    """max |got - ref| over next states and rewards (NaN where both are NaN); terminated and
    diverged equal."""
    got = [np.asarray(x) for x in got]
    assert got[0].dtype == got[1].dtype == np.float64 and got[2].dtype == got[3].dtype == bool
    assert np.array_equal(got[2], ref[2]) and np.array_equal(got[3], ref[3])
    assert np.array_equal(np.isnan(got[0]), np.isnan(ref[0])) and np.array_equal(np.isinf(got[0]), np.isinf(ref[0]))
    diffs = []
    for g, r in ((got[0], ref[0]), (got[1], ref[1])):
        d = np.abs(np.where(np.isfinite(r), g, 0.0) - np.where(np.isfinite(r), r, 0.0))
        diffs.append(float(d.max()))
    assert max(diffs) <= TOL, diffs
    return diffs[0], diffs[1]


def check_exercised(menv, s, a, nxt, diverged) -> None:
    """The draw reaches what the step does: diverged rows (some non-finite) and live ones, the
    spec's box bounds, the observation space's clip, the circle projection, wrapped angles."""
    spec = menv.spec
    rows = menv._predict_rows(menv.model_inputs(s, a))
    assert 0 < diverged.sum() < N / 10 and not np.all(np.isfinite(rows))
    live = nxt[~diverged]
    for bound in (spec.state_low, spec.state_high):
        for j in np.flatnonzero(np.isfinite(bound if bound is not None else [np.nan])):
            at = spec.round_obs(np.asarray(bound, dtype=float))[j]  # the bound in the obs dtype
            assert np.mean(live[:, j] == at) > 0.01, (spec.state_names[j], bound[j])
    if menv._clip:
        j = np.flatnonzero(np.isfinite(menv.obs_high))
        assert not len(j) or np.any(live[:, j] == menv.obs_high[j])
    for c, si in ([spec.target_names.index(n) for n in p] for p in spec.circle_pairs):
        assert np.max(np.abs(np.hypot(live[:, c], live[:, si]) - 1.0)) < 1e-15
        assert np.max(np.abs(np.hypot(rows[c], rows[si])[~diverged] - 1.0)) > 1e-3
    if len(spec.angle_index):
        assert np.all(np.abs(live[:, spec.angle_index]) <= np.pi)


@pytest.mark.parametrize("env", list(ENVS))
def test_the_jax_step_is_the_model_envs_step(env):
    """No noise, then noise fed in (the reference: ModelEnv with the same rows added to its
    prediction; these envs' models have no step noise of their own), then jit vs eager."""
    model, spec, data = fitted(env)
    menv = ModelEnv(model, spec, noise=True, penalty=False, seed=0)
    s, a = draw(spec, data)
    assert not np.any(step_noise(menv, a))  # no noise of its own: zeros, nothing drawn
    step = jax_step(menv)
    ref = menv.step(s, a)
    off = compare(step(s, a), ref)
    check_exercised(menv, s, a, ref[0], ref[3])

    m = len(spec.target_names)
    noise = 0.1 * data[:, spec.target_index].std(axis=0) * np.random.default_rng(1).standard_normal((N, m))
    fed = ModelEnv(model, spec, noise=False, penalty=False, seed=0)
    predict = fed._predict_rows
    fed._predict_rows = lambda z: predict(z) + noise.T  # where ModelEnv adds its own draws
    ref_noise = fed.step(s, a)
    assert not np.array_equal(ref_noise[0], ref[0])
    on = compare(step(s, a, noise), ref_noise)

    jitted = jax.jit(step)
    jit = [compare(jitted(s, a, x), [np.asarray(v) for v in step(s, a, x)]) for x in (None, noise)]
    print(f"{env}: max |jax - numpy| next states, rewards: noise off {off}, noise fed {on}; jit vs eager {jit}")


def test_step_noise_is_the_model_envs_draw_and_unsupported_tasks_are_refused():
    """LunarLander (tests/surrogate/test_jax_step_lunar.py): ``jax_step`` refuses its per-row
    memory and learned events in one line (``jax_stepper`` steps them); composed without its
    kernels (exogenous states) and with an event model that is not a logistic regression,
    ``jax_stepper`` refuses in one line naming each.
    Its step noise (residual covariance per one-hot action): ``step_noise`` gives ModelEnv's
    draws bit for bit and advances the noise stream as a step does."""
    from sklearn.dummy import DummyClassifier  # noqa: PLC0415
    from sklearn.pipeline import make_pipeline  # noqa: PLC0415
    from sklearn.preprocessing import StandardScaler  # noqa: PLC0415

    from sdrl_bench.surrogate.events import EventModel  # noqa: PLC0415
    from sdrl_bench.surrogate.jax_step import jax_stepper  # noqa: PLC0415

    res = fit_dynamics(build_fit_job(compose_cfg("env=lunar_lander", "collector=random", "n_transitions=300")))
    a_env, b_env = (ModelEnv(res.model, res.job.spec, seed=0) for _ in range(2))
    with pytest.raises(NotImplementedError) as err:
        jax_step(a_env)
    assert str(err.value) == ("jax_step: env 'lunar_lander': its step keeps per-row memory (task.array_step) or draws "
                              "learned events: use jax_stepper")
    event = res.job.spec.task.events[0]
    dummy = make_pipeline(StandardScaler(), DummyClassifier(strategy="prior")).fit(np.zeros((2, 11)), [0, 1])
    coin = EventModel(event.name, event.outcome_names, event.feature_names, dummy, 2, {}, 0.5, 0.69)
    for menv, what in ((ModelEnv(res.model, res.job.spec, fused=False, seed=0), "exogenous states"),
                       (ModelEnv(res.model, res.job.spec, events={event.name: coin}, seed=0),
                        f"learned events whose model is not a scaler + logistic regression ({event.name})")):
        with pytest.raises(NotImplementedError) as err:
            jax_stepper(menv)
        msg = str(err.value)
        assert "\n" not in msg and msg.startswith("jax_step: env 'lunar_lander': not covered yet: ") and what in msg, msg

    n, m = 500, len(res.job.spec.target_names)
    actions = np.random.default_rng(0).integers(res.job.spec.n_discrete_actions, size=(n, 1))
    eps = copy.deepcopy(b_env.noise_rng).standard_normal((n, m))
    ref = b_env._add_noise(np.zeros((m, n)), actions).T
    assert np.any(ref) and np.array_equal(step_noise(a_env, actions, eps), ref)
    assert np.array_equal(step_noise(a_env, actions), ref)  # drawn from its own stream
    traced = jax.jit(lambda act, e: step_noise(a_env, act, e))(jnp.asarray(actions), jnp.asarray(eps))
    assert np.max(np.abs(np.asarray(traced) - ref)) <= TOL
    states = b_env.initial_states(n)
    b_env.step(states, actions)  # a step draws what step_noise drew: the streams stay together
    step_noise(a_env, actions)
    assert a_env.noise_rng.bit_generator.state == b_env.noise_rng.bit_generator.state


def test_the_float32_observation_is_one_op_xla_keeps_with_numpys_values():
    """The real env's float32 observation (``functional.round_through``, through
    ``EnvSpec.round_obs``) is one ``reduce_precision`` op in the compiled step, not a float64 ->
    float32 -> float64 pair of conversions, which XLA's GPU compiler drops inside jit (an H200,
    2026-11-30: the pair 4.8e-7 off numpy's, and the jitted steps 1.3e-7 to 1.4e-5 off ModelEnv's;
    with this op, 0: docs/compiled.md). Its values are numpy's pair's, eager and jitted, overflow
    and non-finite values included (float32's subnormals aside, which XLA's CPU flushes to zero,
    as its own pair did: none drawn here); float64 passes as it is; an integer type is refused."""
    from sdrl_bench.envs.functional import round_through  # noqa: PLC0415

    model, spec, data = fitted("mountain_car")
    step = jax_step(ModelEnv(model, spec, noise=False, penalty=False, seed=0))  # jax in float64 from here
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.standard_normal(N) * 10.0 ** rng.uniform(-30, 38, N), [np.inf, -np.inf, np.nan, 0.0, 4e38]])
    with np.errstate(over="ignore"):
        ref = x.astype(np.float32).astype(np.float64)
    assert np.isinf(ref[-1]) and np.mean(ref != x) > 0.99
    assert np.array_equal(round_through(x, np.float32), ref, equal_nan=True)
    for got in (round_through(jnp.asarray(x), np.float32), jax.jit(lambda v: round_through(v, np.float32))(x)):
        assert got.dtype == jnp.float64 and np.array_equal(np.asarray(got), ref, equal_nan=True)
    assert np.array_equal(np.asarray(round_through(jnp.asarray(x), np.float64)), x, equal_nan=True)
    kept = round_through(x, np.float64)
    assert kept is not x and np.array_equal(kept, x, equal_nan=True)
    with pytest.raises(TypeError, match="round_through: .* is not a float type"):
        round_through(x, np.int64)
    program = jax.jit(step).lower(*draw(spec, data)).as_text()
    assert program.count("reduce_precision") == 1 and "f32" not in program


def test_mountain_car_wall_velocity_clip_and_goal():
    """MountainCar's task (its spec class builds it) in jax: states crowded at the left wall, the
    goal and the speed limit, besides the generic draw's diverging rows, with its (near) exact law
    fitted from random data: every case is hit, and next states, rewards, terminated and diverged
    are ModelEnv's (jitted)."""
    model, spec, data = fitted("mountain_car")
    menv = ModelEnv(model, spec, noise=False, penalty=False, seed=0)
    s, a = draw(spec, data, seed=2)
    rng = np.random.default_rng(3)
    lo, hi = np.asarray(spec.state_low), np.asarray(spec.state_high)
    k = np.arange(1000, 9000)
    near_low = rng.uniform(lo, lo + 0.15 * (hi - lo), size=(len(k), 2))  # at the wall, moving left
    near_high = rng.uniform(hi - 0.15 * (hi - lo), hi, size=(len(k), 2))  # at the goal, fast
    s[k] = np.where((k % 3 == 0)[:, None], near_low, np.where((k % 3 == 1)[:, None], near_high, s[k]))
    s[k[k % 3 == 1], 1] *= rng.choice([-1.0, 1.0], size=int(np.sum(k % 3 == 1)))  # both speed limits
    ref = menv.step(s, a)
    got = jax.jit(jax_step(menv))(s, a)
    diffs = compare(got, ref)
    nxt, _, terminated, diverged = (np.asarray(x) for x in got)
    v_pred = menv._predict_rows(menv.model_inputs(s, a))[1]
    f32 = spec.round_obs(np.array([*lo, *hi, 0.45]))  # the bounds and the goal as the float32 state holds them
    wall = ~diverged & (nxt[:, 0] == f32[0]) & (np.clip(v_pred, lo[1], hi[1]) < 0)
    clip = ~diverged & (np.abs(v_pred) > hi[1])
    counts = {"wall": int(wall.sum()), "velocity clip": int(clip.sum()), "goal": int(terminated.sum()),
              "diverged": int(diverged.sum())}
    assert min(counts.values()) >= 100, counts
    assert np.all(nxt[wall, 1] == 0.0)
    assert np.all(np.isin(nxt[clip & ~wall, 1], f32[[1, 3]]))
    assert np.array_equal(terminated, ~diverged & (nxt[:, 0] >= f32[4]) & (nxt[:, 1] >= 0.0))
    print(f"mountain_car: max |jax - numpy| next states, rewards {diffs}; rows of {N}: {counts}")


def test_mountain_car_resets_from_a_jax_key():
    """``jax_reset`` draws from the task's own ``initial_states`` (no pool): x ~ U[-0.6, -0.4), v = 0."""
    model, spec, _ = fitted("mountain_car")
    menv = ModelEnv(model, spec, noise=False, penalty=False, seed=0)
    assert menv._pool is None
    got = np.asarray(jax.jit(jax_reset(menv), static_argnums=1)(jax.random.key(0), 4000))
    assert got.shape == (4000, 2) and got.dtype == np.float64
    assert np.all((got[:, 0] >= -0.6) & (got[:, 0] < -0.4)) and np.all(got[:, 1] == 0.0)
    assert abs(got[:, 0].mean() + 0.5) < 0.01 and abs(got[:, 0].std() - 0.2 / np.sqrt(12)) < 0.005


def numpy_only_reward_terminated(states, actions, next_states):
    return -np.asarray(actions)[:, 0] ** 2, np.asarray(next_states)[:, 0] > 0


def numpy_only_initial_states(rng, n):
    return np.stack([np.asarray(rng.uniform(-0.6, -0.4, n)), np.zeros(n)], axis=1)


def test_a_task_written_for_numpy_alone_is_one_line_naming_the_function():
    model, spec, _ = fitted("mountain_car")
    menv = ModelEnv(model, spec, noise=False, penalty=False, seed=0)
    menv.task = dataclasses.replace(menv.task, reward_terminated=numpy_only_reward_terminated,
                                    initial_states=numpy_only_initial_states)
    with pytest.raises(ConfigError, match=r"^jax_step: task.reward_terminated \(numpy_only_reward_terminated\) "
                                          r"does not run on jax arrays: ") as err:
        jax_step(menv)
    assert "\n" not in str(err.value) and str(err.value).endswith("envs.functional.array_namespace")
    with pytest.raises(ConfigError, match=r"^jax_reset: task.initial_states \(numpy_only_initial_states\) "
                                          r"does not draw from a jax key: ") as err:
        jax_reset(menv)
    assert "\n" not in str(err.value)


def numpy_only_reward(states, actions, next_states):
    return -np.asarray(states)[:, 0] ** 2


def test_a_reward_written_for_numpy_alone_is_one_line_naming_its_key():
    model, spec, _ = fitted("pendulum")
    menv = ModelEnv(model, dataclasses.replace(spec, reward_fn=numpy_only_reward), penalty=False, seed=0)
    with pytest.raises(ConfigError, match=r"^jax_step: env.spec.reward_fn \(.*\) does not run on jax arrays: .*") as err:
        jax_step(menv)
    assert "\n" not in str(err.value) and str(err.value).endswith("envs.functional.array_namespace")


def test_the_task_functions_draw_resets_from_a_jax_key():
    """The reset distributions from a jax PRNG key (jit-able), distributed as the numpy draws."""
    from sdrl_bench.models.jax_eval import jax_modules  # noqa: PLC0415

    jax_modules()  # float64 on, as every compiled program of the harness starts jax (whatever ran before here)
    for env in PLAIN:
        spec = fitted(env)[1]
        fn = resolve(spec.initial_state_fn, "env.spec.initial_state_fn")
        got = np.asarray(jax.jit(fn, static_argnums=1)(jax.random.key(0), 4000))
        ref = fn(np.random.default_rng(0), 4000)
        assert got.shape == ref.shape and got.dtype == np.float64 and np.all(np.isfinite(got))
        scale = ref.std(axis=0)
        assert np.all(np.abs(got.mean(axis=0) - ref.mean(axis=0)) <= 0.1 * scale + 1e-12), env
        assert np.all(np.abs(got.std(axis=0) - scale) <= 0.1 * scale + 1e-12), env


def test_the_package_imports_and_its_task_functions_run_without_jax():
    code = ("import sys\n"
            "sys.modules['jax'] = None\n"
            "import numpy as np\n"
            "import sdrl_bench.surrogate.jax_step\n"
            "from sdrl_bench.envs import classic, dmc\n"
            "s, a = np.zeros((3, 5)), np.ones((3, 1))\n"
            "print(classic.pendulum_reward(s, a, s).shape, dmc.swingup_reward_circle(s, a, s).shape,\n"
            "      dmc.swingup_initial_circle(np.random.default_rng(0), 3).shape)\n")
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["(3,)", "(3,)", "(3,", "5)"]
