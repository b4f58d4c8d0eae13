"""LunarLander's surrogate step in JAX (surrogate/jax_step.py ``jax_stepper``) against ``ModelEnv.step``
with the default config: the flight law with its 5 bootstrap members (pessimism), the engines' step
noise, the settle step on the legs, the task's kernels in their array form (envs/lunar_lander/
array_rules.py: divergence guard, float32 observation, leg flags with hysteresis, the touchdown
prior, clipping, Box2D's sleep counter as per-row memory, crash, out, rest, shaped reward) and the
touchdown event's model learned from the fit's own data. 10,000 random states reaching every case,
one step, eager and jit; 64 landers settling for 200 steps to rest; the event probabilities and
draws; the array rules on numpy against the compiled kernels; the continuous lander."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest

jax = pytest.importorskip("jax")
pytestmark = [pytest.mark.jax,  # ModelEnv's pessimism evaluates its members on the non-finite rows too
              pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")]

from sklearn.linear_model import LogisticRegression  # noqa: E402
from sklearn.pipeline import make_pipeline  # noqa: E402
from sklearn.preprocessing import StandardScaler  # noqa: E402

from helpers import compose_cfg  # noqa: E402
from sdrl_bench.cli.build import build_fit_job  # noqa: E402
from sdrl_bench.envs.lunar_lander import array_rules, events, kernels, task  # noqa: E402
from sdrl_bench.models.jax_eval import jax_modules  # noqa: E402
from sdrl_bench.pipeline import fit_dynamics  # noqa: E402
from sdrl_bench.surrogate.events import (EventModel, draw_outcomes, fit_event_model, logistic_numbers,  # noqa: E402
                                         outcome_probabilities)
from sdrl_bench.surrogate.jax_step import jax_stepper, step_noise, unsupported  # noqa: E402
from sdrl_bench.surrogate.model_env import ModelEnv  # noqa: E402

N, TOL = 10_000, 1e-12
TOL_PENALTY = 1e-11
"""Rewards with the disagreement penalty on: the members' standard deviation over the scale
(the flight noise floor's, down to 7.6e-5) carries their rounding (numpy and jax sum a member's
terms in other orders) times 1/scale: ~5e-17 x the largest prediction / the smallest scale."""


@pytest.fixture(scope="module")
def fit():
    """(fit result, the touchdown event's model): the default flight-law fit on 4000 heuristic
    transitions (eps 0.3, seed 0), whose touchdowns the prior leaves open (3 survived, 1 crashed)
    give the event model (``min_events=2``: the default 8 needs a longer collection)."""
    res = fit_dynamics(build_fit_job(compose_cfg("env=lunar_lander", "collector=heuristic", "collector.epsilon=0.3",
                                                 "n_transitions=4000")))
    event = res.job.spec.task.events[0]
    model = fit_event_model(event, res.data, min_events=2)
    assert model is not None and len(res.model.members_) == 5
    return res, model


def lander_states(data: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(states, actions, sleep counts) for N rows: flight over the data's range widened by its span
    each side; on one or both legs (a fifth quiet: engines off, speeds under Box2D's sleep
    tolerances; some tipped over); just above the ground in flight, descending slowly or fast,
    upright or tilted (touchdowns the prior crashes or leaves open); anything; 3% 1000 times
    larger, 0.5% with an inf or NaN entry. Counts 0..30 (rest at 25)."""
    rng = np.random.default_rng(seed)
    lo, hi = data.min(axis=0), data.max(axis=0)
    span = np.where(hi > lo, hi - lo, 1.0)
    s = rng.uniform(lo - span, hi + span, size=(N, 8))
    s[:, 6:] = 0.0
    legs = np.arange(3000, 5000)
    s[legs, 1] = rng.uniform(-0.05, 0.1, len(legs))
    s[legs, 2:4] = rng.uniform(-0.5, 0.5, (len(legs), 2))
    s[legs, 4] = rng.uniform(-1.2, 1.2, len(legs))
    s[legs, 6:] = np.where(rng.random((len(legs), 1)) < 0.5, 1.0, np.eye(2)[rng.integers(2, size=len(legs))])
    quiet = legs[:400]
    s[quiet, 2:4] = rng.uniform(-1e-3, 1e-3, (len(quiet), 2))
    s[quiet, 4:6] = rng.uniform(-0.05, 0.05, (len(quiet), 2)) * [1.0, 0.01]
    low = np.arange(5000, 8000)
    s[low, 1] = rng.uniform(-0.02, 0.08, len(low))
    s[low, 3] = rng.uniform(-0.8, 0.1, len(low))
    s[low, 4] = rng.uniform(-1.2, 1.2, len(low))
    anything = np.arange(8000, N)
    s[anything, 6:] = rng.random((len(anything), 2)) < 0.3
    s = s.astype(np.float32).astype(float)
    s[:300] *= 1e3
    s[300:350, 0] = np.inf
    s[350:360, 5] = np.nan
    a = rng.integers(4, size=(N, 1))
    a[quiet] = 0
    return s, a, rng.integers(0, 31, size=N)


def prime(menv: ModelEnv, s: np.ndarray, counts: np.ndarray, ground: np.ndarray | None = None) -> None:
    """The ModelEnv's kernel memory as if it had returned ``s`` with these sleep counts (and,
    with terrain, these grounds)."""
    menv._step_batch.memory.update(last=s.copy(), count=counts.copy(),
                                   ground=np.zeros((len(s), 0)) if ground is None else ground.copy())


def model_env_step(menv: ModelEnv, s, a, counts, ground=None):
    """``menv.step`` from primed memory -> (its outputs and counts, the noise and the event
    uniforms it drew, the event rows and outcomes)."""
    prime(menv, s, counts, ground)
    eps = copy.deepcopy(menv.noise_rng).standard_normal((len(s), 6))
    erng = copy.deepcopy(menv._rngs["events"])
    menv.last_events = {}
    out = menv.step(s, a)
    idx, drawn = menv.last_events.get("touchdown", (np.zeros(0, int), np.zeros(0, int)))
    u = np.zeros((len(s), 1))
    u[idx, 0] = erng.random(len(idx))
    return (*out, menv._step_batch.memory["count"].copy()), step_noise(menv, a, eps), u, idx, drawn


def compare(got, ref, ok_aux, tol: float = TOL) -> tuple[float, float]:
    """max |got - ref| of next states (<= TOL) and rewards (<= ``tol``), NaN where NaN;
    terminated, diverged and the counts (rows without NaN: the kernel restarts those) identical."""
    got = [np.asarray(x) for x in got]
    assert got[0].dtype == got[1].dtype == np.float64 and got[2].dtype == got[3].dtype == bool
    assert np.array_equal(got[2], ref[2]) and np.array_equal(got[3], ref[3])
    assert np.array_equal(got[4][ok_aux], ref[4][ok_aux])
    assert np.array_equal(np.isnan(got[0]), np.isnan(ref[0]))
    diffs = []
    for g, r in ((got[0], ref[0]), (got[1], ref[1])):
        fin = np.isfinite(r)
        assert np.array_equal(g[~fin], r[~fin], equal_nan=True)
        diffs.append(float(np.max(np.abs(g[fin] - r[fin]))))
    assert diffs[0] <= TOL and diffs[1] <= tol, diffs
    return diffs[0], diffs[1]


def test_the_jax_stepper_is_the_model_envs_step(fit):
    """Noise off, then ModelEnv's own noise and event draws fed in; pessimism and the learned
    event on; eager and jit. Every case the step has is reached by hundreds of rows."""
    res, em = fit
    spec, model = res.job.spec, res.model
    s, a, counts = lander_states(res.data.states)
    ok_aux = ~np.isnan(s).any(axis=1)
    diffs = {}
    for noise in (False, True):
        menv = ModelEnv(model, spec, noise=noise, events={"touchdown": em}, seed=0)
        assert unsupported(menv) == [] and menv.pessimism == "ensemble disagreement"
        stepper = jax_stepper(menv)
        assert stepper.n_event_draws == 1 and np.array_equal(stepper.init_aux(3), [0, 0, 0])
        ref, eps, u, idx, drawn = model_env_step(menv, s, a, counts)
        fed = eps if noise else None
        diffs[f"noise {noise}, eager"] = compare(stepper.step(s, a, counts, fed, u), ref, ok_aux)
        diffs[f"noise {noise}, jit"] = compare(jax.jit(stepper.step)(s, a, counts, fed, u), ref, ok_aux)
    nxt, rewards, terminated, diverged, after = ref
    live = ~diverged
    down = live & (s[:, 6] < 0.5) & (s[:, 7] < 0.5) & ((nxt[:, 6] > 0.5) | (nxt[:, 7] > 0.5))
    prior = np.asarray(events.touchdown_prior(s, spec))
    cases = {"touchdown crash (prior)": down & (prior == 1), "touchdown open (prior)": down & (prior == 0),
             "event survive": np.isin(np.arange(N), idx[drawn == 0]), "event crash": np.isin(np.arange(N), idx[drawn == 1]),
             "rest": live & (rewards == 100.0), "quiet, counting": live & (after > 0) & (rewards != 100.0),
             "out of bounds": live & (np.abs(nxt[:, 0]) >= 1.0),
             "tipped on the legs": live & ~down & ((nxt[:, 6] > 0.5) | (nxt[:, 7] > 0.5)) & (np.abs(nxt[:, 4]) > 1.0),
             "lift-off": live & ((s[:, 6] > 0.5) | (s[:, 7] > 0.5)) & (nxt[:, 6] < 0.5) & (nxt[:, 7] < 0.5),
             "diverged": diverged, "non-finite": ~np.isfinite(s).all(axis=1)}
    counts_of = {k: int(v.sum()) for k, v in cases.items()}
    assert min(counts_of.values()) >= 10, counts_of
    assert np.all(terminated[cases["event crash"]]) and np.all(rewards[cases["event crash"]] == -100.0)
    print(f"lunar_lander: max |jax - numpy| (next states, rewards): {diffs}; rows of {N}: {counts_of}")


def test_with_terrain_and_the_slope_rule_the_jax_stepper_is_the_model_envs_step(fit):
    """Terrain on (``env.spec.terrain``) and the slope rule set: each row stands on its own
    ground (drawn as the real env draws it), its height taken over the ground under it, so that
    the touchdowns, the legs and the floor meet hills; ModelEnv's kernel primed with those
    grounds. Noise and event draws fed in, pessimism on, eager and jit; the ground comes back
    unchanged, and the slope rule ends dozens of touchdowns, alike in both."""
    res, em = fit
    base = res.job.spec
    spec = dataclasses.replace(base, terrain=True, rules=dataclasses.replace(base.rules, slope_crash=0.1))
    s, a, counts = lander_states(res.data.states, seed=1)
    ground = task.draw_terrain(np.random.default_rng(5), N)
    under = np.array([kernels.ground_at(ground[i], float(np.clip(np.nan_to_num(x), -2.0, 2.0))) for i, x in enumerate(s[:, 0])])
    s[:, 1] += under
    ok_aux = ~np.isnan(s).any(axis=1)
    menv = ModelEnv(res.model, spec, noise=True, events={"touchdown": em}, seed=0)
    assert unsupported(menv) == []
    stepper = jax_stepper(menv)
    fresh = stepper.init_aux(4, jax.random.key(0))
    assert fresh[0].dtype == np.int64 and np.array_equal(fresh[0], np.zeros(4)) and fresh[1].shape == (4, 11)
    assert np.all(np.asarray(fresh[1])[:, 4:7] == 0.0) and np.ptp(np.asarray(fresh[1])) > 0.05  # the pad, hills off it
    with pytest.raises(ValueError, match="a key is needed"):
        stepper.init_aux(4)
    ref, eps, u, _, _ = model_env_step(menv, s, a, counts, ground)
    diffs = {}
    for name, fn in (("eager", stepper.step), ("jit", jax.jit(stepper.step))):
        nxt, rewards, terminated, diverged, (after, g) = fn(s, a, (counts, ground), eps, u)
        diffs[name] = compare((nxt, rewards, terminated, diverged, after), ref, ok_aux)
        assert np.array_equal(np.asarray(g), ground)
    no_rule = ModelEnv(res.model, dataclasses.replace(spec, rules=base.rules), noise=True, events={"touchdown": em}, seed=0)
    plain = model_env_step(no_rule, s, a, counts, ground)[0]
    slope = ref[2] & ~plain[2]  # ended by the slope rule alone
    assert slope.sum() >= 20 and np.all(ref[1][slope] == -100.0)
    down = ~ref[3] & (s[:, 6] < 0.5) & (s[:, 7] < 0.5) & ((ref[0][:, 6] > 0.5) | (ref[0][:, 7] > 0.5))
    on_hills = down & (np.abs(under) > 0.02)
    assert (on_hills & ~ref[2]).sum() >= 5  # touchdowns off the pad that the rule lets survive (gentle slopes)
    print(f"lunar_lander with terrain: max |jax - numpy| {diffs}; {int(down.sum())} touchdowns, "
          f"{int(slope.sum())} ended by the slope rule")


def test_the_float32_observation_is_one_reduce_precision_op(fit):
    """The array rules round the prediction to the float32 observation with one op XLA keeps
    (``functional.round_through``; a pair of conversions is dropped by its GPU compiler inside
    jit): the compiled step has no float32 value in it."""
    res, em = fit
    stepper = jax_stepper(ModelEnv(res.model, res.job.spec, noise=False, events={"touchdown": em}, seed=0))
    s, a, counts = lander_states(res.data.states)
    program = jax.jit(stepper.step).lower(s, a, counts).as_text()
    assert program.count("reduce_precision") == 1 and "f32" not in program


def test_the_pessimism_penalty_and_limit(fit):
    """No free band (the default's 0.35 exceeds the disagreement of every flight row the step
    leaves alive here) and a finite ``uncertainty.limit`` (the median disagreement in flight): the
    flight rows below it are penalized, those beyond end with the task's crash reward, in jax as
    in ModelEnv."""
    res, em = fit
    s, a, counts = lander_states(res.data.states, seed=1)
    menv = ModelEnv(res.model, res.job.spec, noise=False, events={"touchdown": em}, seed=0)
    u_all = menv.disagreement(menv.model_inputs(s, a))
    flight = np.asarray(events.in_flight(s))
    unc = dataclasses.replace(menv.task.uncertainty, free=0.0, limit=float(np.nanmedian(u_all[flight])))
    plain = ModelEnv(res.model, res.job.spec, noise=False, penalty=False, events={"touchdown": em}, seed=0)
    _, r_plain, t_plain, _ = plain.step(s, a)
    menv.task = dataclasses.replace(menv.task, uncertainty=unc)
    ref, _, u, _, _ = model_env_step(menv, s, a, counts)
    stepper, finite = jax_stepper(menv), ~np.isnan(s).any(axis=1)
    diffs = [compare(fn(s, a, counts, None, u), ref, finite, TOL_PENALTY) for fn in (stepper.step, jax.jit(stepper.step))]
    live = flight & ~ref[3] & ~t_plain
    over, under = live & (u_all > unc.limit), live & (u_all <= unc.limit)
    assert np.all(ref[2][over] & (ref[1][over] == -100.0)) and np.all(r_plain[under] - ref[1][under] > 0)
    assert over.sum() >= 1000 and under.sum() >= 1000, (over.sum(), under.sum())
    print(f"pessimism: max |jax - numpy| (eager, jit) {diffs}; {int(under.sum())} rows penalized, "
          f"{int(over.sum())} ended by the limit")


def test_landers_settle_to_rest_as_the_model_env_does(fit):
    """64 landers just above or on the pad, 5 steps of random engines, then engines off for 195:
    each steps its own states (jit), with ModelEnv's noise and event draws; every step's outputs
    and sleep counts are ModelEnv's, and the landers come to rest (+100) or crash as there."""
    res, em = fit
    spec = res.job.spec
    menv = ModelEnv(res.model, spec, events={"touchdown": em}, seed=0)
    stepper = jax_stepper(menv)
    step = jax.jit(stepper.step)
    rng = np.random.default_rng(5)
    n = 64
    s = np.column_stack([rng.uniform(-0.3, 0.3, n), rng.uniform(-0.01, 0.12, n), rng.uniform(-0.15, 0.15, n),
                         rng.uniform(-0.4, 0.05, n), rng.uniform(-0.3, 0.3, n), rng.uniform(-0.2, 0.2, n),
                         np.zeros(n), np.zeros(n)])
    s[:, 6:] = s[:, [1]] < 0.02
    s = spec.round_obs(s)
    mine, aux = s.copy(), stepper.init_aux(n)
    ended, draws, worst = {}, 0, [0.0, 0.0]
    for k in range(200):
        a = rng.integers(4, size=(n, 1)) if k < 5 else np.zeros((n, 1), dtype=int)
        eps = copy.deepcopy(menv.noise_rng).standard_normal((n, 6))
        erng = copy.deepcopy(menv._rngs["events"])
        menv.last_events = {}
        ref = menv.step(s, a)
        idx = menv.last_events.get("touchdown", (np.zeros(0, int),))[0]
        u = np.zeros((n, 1))
        u[idx, 0] = erng.random(len(idx))
        draws += len(idx)
        got = [np.asarray(x) for x in step(mine, a, aux, step_noise(menv, a, eps), u)]
        assert np.array_equal(got[2], ref[2]) and np.array_equal(got[3], ref[3]), k
        assert np.array_equal(got[4], menv._step_batch.memory["count"]), k
        worst = [max(worst[0], float(np.max(np.abs(got[0] - ref[0])))), max(worst[1], float(np.max(np.abs(got[1] - ref[1]))))]
        for i in np.flatnonzero(ref[2]):
            ended.setdefault(int(i), (k, float(ref[1][i])))
        s, mine, aux = ref[0], got[0], got[4]
    assert max(worst) <= TOL, worst
    outcome = [r for _, r in ended.values()]
    rests, crashes = outcome.count(100.0), outcome.count(-100.0)
    assert len(ended) == n and rests >= 10 and crashes >= 10 and draws >= 1, (rests, crashes, draws)
    print(f"settling: max |jax - numpy| over 200 steps {worst}; {rests} rests, {crashes} crashes, {draws} event draws")


def test_event_probabilities_and_draws_are_the_event_models(fit):
    """``outcome_probabilities`` is ``EventModel.probabilities`` to rounding (numpy and jax) for
    the fitted touchdown model and a multinomial one with an outcome never seen;
    ``draw_outcomes`` with ModelEnv's uniforms is ``EventModel.draw``."""
    jax_modules()  # float64 on (jax_stepper turns it on; this test calls the helpers alone)
    res, em = fit
    event = res.job.spec.task.events[0]
    s, _, _ = lander_states(res.data.states)
    x = np.asarray(event.features(s[np.isfinite(s).all(axis=1)]))
    rng = np.random.default_rng(0)
    y = np.digitize(x[:, 0] + 0.3 * rng.standard_normal(len(x)), [-0.5, 0.5])  # classes 0, 1, 2
    clf = make_pipeline(StandardScaler(), LogisticRegression(max_iter=1000)).fit(x, np.array([0, 1, 3])[y])
    four = EventModel("multi", ("a", "b", "c", "d"), event.feature_names, clf, len(y), {}, 1.0, 0.0)
    diffs = {}
    for model in (em, four):
        numbers = logistic_numbers(model)
        k = len(model.outcome_names)
        ref = model.probabilities(x)
        assert set(ref.argmax(axis=1)) == set(model.classifier.classes_)  # each seen outcome the likeliest somewhere
        got = np.asarray(jax.jit(lambda f, numbers=numbers, k=k: outcome_probabilities(numbers, f, k))(x))
        diffs[model.event] = (float(np.max(np.abs(outcome_probabilities(numbers, x, k) - ref))),
                              float(np.max(np.abs(got - ref))))
        assert max(diffs[model.event]) <= TOL
        u = copy.deepcopy(rng).random(len(x))
        drawn = model.draw(x, copy.deepcopy(rng))
        assert np.array_equal(np.asarray(jax.jit(draw_outcomes)(got, u)), drawn)
        assert len(np.unique(drawn)) == len(model.classifier.classes_)
    assert logistic_numbers(four)[2].shape == (3, len(event.feature_names)) and np.all(four.probabilities(x)[:, 2] == 0)
    print(f"event probabilities: max |numpy, jax - EventModel| {diffs}")


def test_the_array_rules_on_numpy_are_the_kernels(fit):
    """The array rules on numpy arrays against the compiled kernels (settle step, step with its
    memory) to rounding, identical flags; the event functions' numpy results as before."""
    res, _ = fit
    spec = res.job.spec
    s, a, counts = lander_states(res.data.states, seed=2)
    finite = np.isfinite(s).all(axis=1)
    s, a, counts = s[finite], a[finite], counts[finite]
    menv = ModelEnv(res.model, spec, noise=False, penalty=False, seed=0)
    pred = menv._predict_rows(menv.model_inputs(s, a))
    ref_rows = task.regime_dynamics(spec.rules, True, s, a, pred)
    rows = array_rules.regime_dynamics(spec.rules, True, s, a, pred.T)
    assert np.max(np.abs(rows - ref_rows.T)) <= TOL
    prime(menv, s, counts)
    ref = (*menv._step_batch(s, a, ref_rows), menv._step_batch.memory["count"])
    got = array_rules.make_step(spec.rules, True, menv.limit, menv.obs_low, menv.obs_high)(s, a, ref_rows.T, counts)
    compare(got, ref, np.ones(len(s), bool))
    prior = np.array([kernels.touchdown_crash(float(p[3]), float(p[4]), task.rules_vector(spec.rules)) for p in s], dtype=int)
    assert np.array_equal(events.touchdown_prior(s, spec), prior) and prior.any() and not prior.all()
    x = s[:, 0]
    feats = np.column_stack([x, np.abs(x), np.maximum(np.abs(x) - 0.2, 0.0), s[:, 1], s[:, 2], np.abs(s[:, 2]), s[:, 3],
                             s[:, 4], np.abs(s[:, 4]), s[:, 5], np.abs(s[:, 5])])
    assert np.array_equal(events.touchdown_features(s), feats)


def test_the_continuous_lander_and_terrain():
    """The continuous lander (throttles clipped in jax too) is ModelEnv's step, on flat ground
    and with terrain."""
    res = fit_dynamics(build_fit_job(compose_cfg("env=lunar_lander_continuous", "collector=random",
                                                 "n_transitions=1500")))
    spec = res.job.spec
    menv = ModelEnv(res.model, spec, seed=0)
    s, _, counts = lander_states(res.data.states, seed=3)
    a = np.random.default_rng(3).uniform(-1.5, 1.5, size=(N, 2))
    ref, _, _, _, _ = model_env_step(menv, s, a, counts)
    diffs = compare(jax.jit(jax_stepper(menv).step)(s, a, counts), ref, ~np.isnan(s).any(axis=1))
    print(f"lunar_lander_continuous: max |jax - numpy| {diffs}")
    hilly = ModelEnv(res.model, dataclasses.replace(spec, terrain=True), seed=0)
    ground = task.draw_terrain(np.random.default_rng(3), N)
    ref, _, _, _, _ = model_env_step(hilly, s, a, counts, ground)
    nxt, rewards, terminated, diverged, (after, _) = jax.jit(jax_stepper(hilly).step)(s, a, (counts, ground))
    diffs = compare((nxt, rewards, terminated, diverged, after), ref, ~np.isnan(s).any(axis=1))
    print(f"lunar_lander_continuous with terrain: max |jax - numpy| {diffs}")
