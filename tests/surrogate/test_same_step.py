"""SINDy, NN and probabilistic-ensemble surrogates of one env step through the same model-env
code: the same reset pool, step noise (each model's own: measured dispersion, or the PE's learned
variance), the same pessimism from whatever spread the model has (non-zero for every ensemble),
the same learned events."""

from __future__ import annotations

import numpy as np
import pytest
from gymnasium.envs.box2d.lunar_lander import heuristic
from sklearn.dummy import DummyClassifier
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import StandardScaler

from helpers import compose_cfg
from sdrl_bench.cli.build import build_fit_job
from sdrl_bench.pipeline import fit_dynamics
from sdrl_bench.surrogate.events import EventModel
from sdrl_bench.surrogate.model_env import ModelEnv, surrogate_settings
from sdrl_bench.surrogate.vec import SurrogateVecEnv

BASE = ("env=lunar_lander", "collector=heuristic", "n_transitions=600")


@pytest.fixture(scope="module")
def fits():
    """The same 600 heuristic transitions fitted by SINDy's flight law (5 bootstrap members) and
    by an NN ensemble of 3 (a short fit: what it learns does not matter here, that it has a spread)."""
    sindy = fit_dynamics(build_fit_job(compose_cfg(*BASE)))
    nn = fit_dynamics(build_fit_job(compose_cfg(*BASE, "surrogate=nn", "surrogate.model.ensemble_size=3",
                                                "surrogate.model.max_steps=300")))
    pe = fit_dynamics(build_fit_job(compose_cfg(*BASE, "surrogate=pe", "surrogate.model.width=32",
                                                "surrogate.model.max_steps=300")))
    assert sindy.dataset_hash == nn.dataset_hash == pe.dataset_hash
    return {"sindy": sindy, "nn": nn, "pe": pe}


def _always_crash(spec) -> EventModel:
    event = next(e for e in spec.task.events if e.name == "touchdown")
    crash = event.outcome_names.index("crash")
    x = np.zeros((2, len(event.feature_names)))
    clf = make_pipeline(StandardScaler(), DummyClassifier(strategy="constant", constant=crash)).fit(x, [crash, crash])
    return EventModel("touchdown", event.outcome_names, event.feature_names, clf, 2, {"survive": 0, "crash": 2}, 1.0, 0.0)


@pytest.mark.parametrize("kind", ["sindy", "nn", "pe"])
def test_noise_and_pessimism_come_from_the_model_env_for_every_model(fits, kind):
    fit = fits[kind]
    model, spec = fit.model, fit.spec
    members = {"sindy": 5, "nn": 3, "pe": 5}[kind]
    noise = ("learned variance: a random elite's Gaussian each step" if kind == "pe"
             else "residual covariance per a_left, a_main, a_right")
    assert surrogate_settings(model, spec) == {"surrogate.noise": noise,
                                               "surrogate.pessimism": f"ensemble disagreement ({members} members)"}
    env = ModelEnv(model, spec, seed=0)
    assert env.pessimism == "ensemble disagreement"
    assert (env._sample is not None) if kind == "pe" else (env._chol is not None)
    states = env.initial_states(64)
    main = np.full(64, 2)  # the main engine: dispersed
    # noise: the same states and action, two noise draws differ; without noise, one deterministic step
    a, _, _, _ = ModelEnv(model, spec, seed=1).step(states, main)
    b, _, _, _ = ModelEnv(model, spec, seed=2).step(states, main)
    c, _, _, _ = ModelEnv(model, spec, seed=1, noise=False).step(states, main)
    d, _, _, _ = ModelEnv(model, spec, seed=2, noise=False).step(states, main)
    assert not np.allclose(a[:, :6], b[:, :6]) and np.array_equal(c, d)
    # pessimism: the same deterministic step with and without the penalty; it only lowers rewards
    _, r_pen, _, _ = ModelEnv(model, spec, seed=1, noise=False).step(states, main)
    _, r_raw, _, _ = ModelEnv(model, spec, seed=1, noise=False, penalty=False).step(states, main)
    gap = r_raw - r_pen
    assert np.all(gap >= 0) and np.any(gap > 0)


def test_resets_and_learned_events_are_the_same_code_for_both(fits):
    spec = fits["sindy"].spec
    starts = {k: ModelEnv(f.model, f.spec, seed=7).initial_states(32) for k, f in fits.items()}
    assert np.array_equal(starts["sindy"], starts["nn"])  # the run's reset pool, the same draws
    crashes = {}
    for kind, fit in fits.items():
        venv = SurrogateVecEnv(fit.model, fit.spec, 16, seed=3, events={"touchdown": _always_crash(spec)})
        env = spec.make_env()
        obs = venv.reset()
        for _ in range(400):
            obs, _, _, _ = venv.step(np.array([heuristic(env.unwrapped, o) for o in obs]))
        crashes[kind] = venv.event_counts["touchdown"]["crash"]
    assert crashes["sindy"] > 0 and crashes["nn"] > 0  # the learned event decides touchdowns under either model


def test_a_single_nn_gets_no_pessimism_and_says_so():
    fit = fit_dynamics(build_fit_job(compose_cfg(*BASE, "surrogate=nn", "surrogate.model.max_steps=100")))
    assert surrogate_settings(fit.model, fit.spec)["surrogate.pessimism"] == "none: the model has no members"
    assert ModelEnv(fit.model, fit.spec, seed=0).pessimism == "none: the model has no members"
