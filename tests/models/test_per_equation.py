"""Per-equation libraries: exact recovery of a known law, data round trip, compiled evaluators,
one-line config errors naming the key."""

from __future__ import annotations

import numpy as np
import pysindy as ps
import pytest

from helpers import compose_cfg
from sdrl_bench import ConfigError
from sdrl_bench.cli.build import build_fit_job
from sdrl_bench.models.base import load_model
from sdrl_bench.models.fast import batch_predictor, compile_scalar
from sdrl_bench.models.per_equation import PerEquationLibrary, PerEquationModel, sparse_model
from sdrl_bench.models.sindy import SindyModel
from sdrl_bench.pipeline import check

TOY = {"p": ["v'", "v", "u"], "v": ["bias", "u", "sin(p)", "cos(p)", "v*u", "p^2"]}


def toy_data(n: int = 200):
    """p' = p + 0.02 v', v' = v + 0.1 u - 0.05 sin(p): semi-implicit Euler of a pendulum-like law."""
    rng = np.random.default_rng(0)
    x, u = rng.uniform(-1, 1, (n, 2)), rng.uniform(-1, 1, (n, 1))
    v1 = x[:, 1] + 0.1 * u[:, 0] - 0.05 * np.sin(x[:, 0])
    return x, u, np.column_stack([x[:, 0] + 0.02 * v1, v1])


def fit_toy(**lib_kwargs) -> PerEquationModel:
    x, u, xn = toy_data()
    lib = PerEquationLibrary(equations=TOY, threshold=1e-6, **lib_kwargs)
    return PerEquationModel(lib, ps.STLSQ(threshold=0.5, alpha=0.0)).fit(
        x, u, xn, state_names=["p", "v"], control_names=["u"])


def test_toy_law_recovered_exactly_and_saved_as_data(tmp_path):
    m = fit_toy()
    assert np.array_equal(np.flatnonzero(m.eq_coef_["p"]), [0]) and m.eq_coef_["p"][0] == pytest.approx(0.02, abs=1e-12)
    assert np.array_equal(np.flatnonzero(m.eq_coef_["v"]), [1, 2])
    assert m.eq_coef_["v"][1:3] == pytest.approx([0.1, -0.05], abs=1e-12)
    assert m.equations() == ["p' = p +0.02 v'", "v' = v +0.1 u -0.05 sin(p)"]
    x, u, xn = toy_data()
    assert np.abs(m.predict(x, u) - xn).max() < 1e-12
    loaded = load_model(m.save(tmp_path / "model.json"))  # registered kind, JSON data only
    assert isinstance(loaded, PerEquationModel) and loaded.equations() == m.equations()
    assert np.array_equal(loaded.predict(x, u), m.predict(x, u))


def test_flattened_terms_drive_the_compiled_evaluators():
    m = fit_toy()
    x, u, _ = toy_data(50)
    z = np.column_stack([x, u])
    ref = m.predict(x, u)
    one = compile_scalar(m.terms_, m.coef_, 3)
    assert np.allclose([one(r) for r in z.tolist()], ref, rtol=0, atol=1e-15)
    assert np.allclose(batch_predictor(m)(z.T).T, ref, rtol=0, atol=1e-15)


def test_ensemble_members_and_step_noise_are_fitted_and_saved(tmp_path):
    m = fit_toy(ensemble=3, noise_by=())
    assert len(m.members_) == 3 and m.predict_members(*toy_data(5)[:2]).shape == (3, 5, 2)
    again = load_model(m.save(tmp_path / "m.json"))
    assert all(np.array_equal(a, b) for a, b in zip(again.members_, m.members_, strict=True))


def test_sparse_model_dispatches_on_the_library():
    assert isinstance(sparse_model(PerEquationLibrary(equations=TOY)), PerEquationModel)
    assert isinstance(sparse_model(ps.PolynomialLibrary(degree=1)), SindyModel)


@pytest.mark.parametrize("equations, message", [
    ({"p": ["w"], "v": ["u"]}, "library.equations.p[0]: unknown name 'w' in term 'w'; known: p, v, u"),
    ({"p": [], "v": ["u"]}, "library.equations.p: an equation needs at least one term"),
    ({"p": ["v"], "v": ["u"], "q": ["u"]}, "library.equations.q: not a regressed state; regressed: p, v"),
    ({"p": ["v'"], "v": ["p'"]}, "library.equations: next-value references form a cycle among p, v"),
    ({"p": ["tan(v)"], "v": ["u"]}, "library.equations.p[0]: cannot parse factor 'tan(v)'"),
    ({"p": ["v", "v"], "v": ["u"]}, "library.equations.p: duplicate term 'v'"),
    ({"p": ["v"]}, "library.equations: no equation for regressed state(s) v"),
])
def test_bad_configs_give_one_line_errors_naming_the_key(equations, message):
    with pytest.raises(ConfigError) as err:
        PerEquationLibrary(equations=equations).check_inputs(["p", "v"], ["u"])
    assert str(err.value).startswith(message) and "\n" not in str(err.value)


def test_bad_names_are_caught_before_any_data_is_collected():
    """A per-equation YAML library naming an unknown state fails in ``check`` (no env step)."""
    job = build_fit_job(compose_cfg("env=lunar_lander", "library=lunar_lander_flight"))
    lib = job.library_parts[0].library
    assert isinstance(lib, PerEquationLibrary) and set(lib.parsed) == {"x", "y", "vx", "vy", "angle", "angvel"}
    bad = PerEquationLibrary(equations={**lib.equations, "angle": ["omega"]})
    with pytest.raises(ConfigError, match=r"^library.equations.angle\[0\]: unknown name 'omega' in term 'omega'"):
        check(type(job)(**{**job.__dict__, "library_parts": (type(job.library_parts[0])(bad),)}))


def test_a_fit_with_pysindys_ensemble_optimizer_is_deterministic_under_its_seed():
    """pysindy's EnsembleOptimizer resamples from numpy's global random state: the same seed gives
    the same coefficients (members too) whatever that state was before, another seed other
    ones, and the caller's global state is left as it was."""
    x, u, xn = toy_data()
    noisy = xn + 1e-3 * np.random.default_rng(1).standard_normal(xn.shape)

    def fit(seed: int) -> PerEquationModel:
        lib = PerEquationLibrary(equations=TOY, threshold=1e-3, ensemble=2)
        opt = ps.EnsembleOptimizer(ps.STLSQ(threshold=1e-3, alpha=0.0), bagging=True, n_models=5)
        return PerEquationModel(lib, opt, seed=seed).fit(x, u, noisy, state_names=["p", "v"], control_names=["u"])

    np.random.seed(11)
    untouched = np.random.random()
    np.random.seed(11)
    a = fit(3)
    assert np.random.random() == untouched  # the caller's global stream goes on as if no fit ran
    np.random.seed(99)
    b = fit(3)
    assert all(np.array_equal(a.eq_coef_[k], b.eq_coef_[k]) for k in TOY)
    assert all(np.array_equal(m, n) for m, n in zip(a.members_, b.members_, strict=True))
    c = fit(4)
    assert any(not np.array_equal(a.eq_coef_[k], c.eq_coef_[k]) for k in TOY)


def test_pendulums_shipped_fit_names_its_law_term_by_term():
    """Pendulum-v1 fits per equation (library=pendulum_law): its nonzero coefficients by term, in
    the per-equation form, are the env's law exactly (snapped), as studies/byo_env_laws.py checks."""
    from sdrl_bench.pipeline import fit_dynamics

    model = fit_dynamics(build_fit_job(compose_cfg("env=pendulum", "collector=random", "seed=0"))).model
    assert isinstance(model, PerEquationModel)
    assert model.coefficients_by_name() == {"th": {"thdot'": 0.05}, "thdot": {"sin(th)": 0.75, "torque": 0.15}}
