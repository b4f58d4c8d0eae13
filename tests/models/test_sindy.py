"""The compiled numpy evaluator equals pysindy's predict; models save and load as JSON data."""

from __future__ import annotations

import json

import numpy as np
import pysindy as ps
import pytest

from sdrl_bench import ConfigError
from sdrl_bench.models.libraries import LibraryPart, RationalLibrary, TrigLibrary, build_library
from sdrl_bench.models.sindy import SindyModel

LIBRARIES = {
    "poly3": [LibraryPart(ps.PolynomialLibrary(degree=3), "all")],
    "poly_no_bias_interaction_only": [LibraryPart(ps.PolynomialLibrary(degree=2, include_bias=False, interaction_only=True))],
    "fourier": [LibraryPart(ps.PolynomialLibrary(degree=1)), LibraryPart(ps.FourierLibrary(n_frequencies=2), "states")],
    "trig_rational": [
        LibraryPart(ps.PolynomialLibrary(degree=2)),
        LibraryPart(TrigLibrary([0.5, 3.0]), ("s1",)),
        LibraryPart(RationalLibrary(), "states"),
        LibraryPart(ps.FourierLibrary(include_sin=False), "controls"),
    ],
}


def random_system(seed: int = 0, n: int = 400):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1, 1, size=(n, 3))
    u = rng.uniform(-1, 1, size=(n, 2))
    x_next = np.column_stack([
        0.9 * x[:, 0] + 0.1 * u[:, 0] * x[:, 1],
        x[:, 1] - 0.2 * np.sin(3.0 * x[:, 1]) + 0.05 * u[:, 1],
        0.5 * x[:, 2] / (1 + x[:, 2] ** 2) + 0.3,
    ])
    return x, u, x_next


@pytest.mark.parametrize("name", sorted(LIBRARIES))
def test_compiled_evaluator_equals_pysindy_predict(name):
    x, u, x_next = random_system()
    lib = build_library(LIBRARIES[name], ["s0", "s1", "s2"], ["c0", "c1"])
    opt = ps.STLSQ(threshold=1e-3, alpha=1e-6)
    model = SindyModel(lib, opt).fit(x, u, x_next, state_names=["s0", "s1", "s2"], control_names=["c0", "c1"])
    # refit with pysindy alone, then compare on fresh inputs
    ref = ps.DiscreteSINDy(optimizer=ps.STLSQ(threshold=1e-3, alpha=1e-6), feature_library=lib)
    ref.fit(x, t=1, x_next=x_next, u=u, feature_names=["s0", "s1", "s2", "c0", "c1"])
    xt, ut, _ = random_system(seed=1, n=50)
    np.testing.assert_allclose(model.predict(xt, ut), ref.predict(xt, u=ut), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(model.features(xt, ut), ref.feature_library.transform(np.hstack([xt, ut])), rtol=1e-13, atol=0)
    assert model.feature_names_ == ref.get_feature_names()
    assert model.compile_max_abs_diff_ < 1e-12


def test_rational_and_trig_terms_are_recovered():
    x, u, x_next = random_system()
    lib = build_library(LIBRARIES["trig_rational"], ["s0", "s1", "s2"], ["c0", "c1"])
    model = SindyModel(lib, ps.STLSQ(threshold=1e-3, alpha=0.0)).fit(
        x, u, x_next, state_names=["s0", "s1", "s2"], control_names=["c0", "c1"])
    coefs = model.coefficients_by_name()
    assert coefs["s0"] == pytest.approx({"s0": 0.9, "s1 c0": 0.1}, abs=1e-9)
    assert coefs["s1"] == pytest.approx({"s1": 1.0, "sin(3 s1)": -0.2, "c1": 0.05}, abs=1e-9)
    assert coefs["s2"] == pytest.approx({"1": 0.3, "s2/(1+s2^2)": 0.5}, abs=1e-9)
    assert model.n_active_terms == 7
    assert "sin(3 s1)" in model.equations()[1]


def test_save_load_round_trip_is_bitwise(tmp_path):
    x, u, x_next = random_system()
    lib = build_library(LIBRARIES["trig_rational"], ["s0", "s1", "s2"], ["c0", "c1"])
    model = SindyModel(lib, ps.STLSQ(threshold=1e-3)).fit(x, u, x_next, state_names=["s0", "s1", "s2"], control_names=["c0", "c1"])
    loaded = SindyModel.load(model.save(tmp_path / "m.json"))
    assert np.array_equal(loaded.predict(x, u), model.predict(x, u))
    assert loaded.equations() == model.equations()


def test_malformed_model_files_are_rejected_with_the_file_named(tmp_path):
    x, u, x_next = random_system()
    lib = build_library(LIBRARIES["poly3"], ["s0", "s1", "s2"], ["c0", "c1"])
    good = SindyModel(lib, ps.STLSQ(threshold=1e-3)).fit(x, u, x_next, state_names=["s0", "s1", "s2"], control_names=["c0", "c1"]).to_dict()
    with pytest.raises(ConfigError, match="model file not found"):
        SindyModel.load(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ConfigError, match="bad.json: not a valid model file"):
        SindyModel.load(tmp_path / "bad.json")
    evil = dict(good, terms=[[[0, "__import__('os').system('true')", 1.0]]] * len(good["terms"]))
    (tmp_path / "evil.json").write_text(json.dumps(evil))
    with pytest.raises(ConfigError, match="evil.json: not a valid SINDy model file"):
        SindyModel.load(tmp_path / "evil.json")
    wrong = dict(good, coefficients=[[0.0]])
    (tmp_path / "shape.json").write_text(json.dumps(wrong))
    with pytest.raises(ConfigError, match="shape.json"):
        SindyModel.load(tmp_path / "shape.json")


def test_ensemble_fit_is_deterministic_under_a_seed():
    x, u, x_next = random_system()
    lib = build_library(LIBRARIES["poly3"], ["s0", "s1", "s2"], ["c0", "c1"])

    def fit(seed):
        opt = ps.EnsembleOptimizer(ps.STLSQ(threshold=1e-3), bagging=True, n_models=5)
        return SindyModel(lib, opt, seed=seed).fit(x, u, x_next, state_names=["s0", "s1", "s2"], control_names=["c0", "c1"]).coef_

    np.testing.assert_array_equal(fit(3), fit(3))


# ---------------------------------------------------------------------- snapping exact laws
def float32_law(seed: int = 0, n: int = 120, noise: float = 0.0):
    """y = s0 + 0.25 s1 - 0.0035 c0 + 0.6 s0 s1 on float32 inputs, rounded to float32 (an exact
    law seen through float32 observations), plus optional Gaussian noise."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1, 1, size=(n, 3)).astype(np.float32).astype(float)
    u = rng.uniform(-1, 1, size=(n, 2)).astype(np.float32).astype(float)
    y = x[:, 0] + 0.25 * x[:, 1] - 0.0035 * u[:, 0] + 0.6 * x[:, 0] * x[:, 1]
    y = y.astype(np.float32).astype(float) + noise * rng.standard_normal(n)
    return x, u, np.column_stack([y, x[:, 1], x[:, 2]])


def fit_law(x, u, x_next, **kw):
    lib = build_library(LIBRARIES["poly3"], ["s0", "s1", "s2"], ["c0", "c1"])
    return SindyModel(lib, ps.STLSQ(threshold=1e-3, alpha=0.0), **kw).fit(
        x, u, x_next, state_names=["s0", "s1", "s2"], control_names=["c0", "c1"])


def test_an_exact_law_in_float32_data_snaps_to_its_decimals():
    x, u, x_next = float32_law()
    raw, snapped = fit_law(x, u, x_next, snap_alpha=None), fit_law(x, u, x_next)
    law = {"s0": 1.0, "s1": 0.25, "c0": -0.0035, "s0 s1": 0.6}
    assert snapped.coefficients_by_name()["s0"] == law  # exactly, not approximately
    assert raw.coefficients_by_name()["s0"] != law
    assert raw.coefficients_by_name()["s0"] == pytest.approx(law, rel=1e-6)
    assert snapped.snap_digits_[0] == 2 and raw.snap_digits_ == [0, 0, 0]
    assert snapped.summary_metrics()["n_snapped_equations"] >= 1
    assert snapped.summary_metrics()["snap_digits/s0"] == 2.0


def test_noisy_equations_are_never_snapped():
    x, u, x_next = float32_law(noise=1e-3)
    snapped, raw = fit_law(x, u, x_next), fit_law(x, u, x_next, snap_alpha=None)
    assert snapped.snap_digits_[0] == 0
    np.testing.assert_array_equal(snapped.coef_[0], raw.coef_[0])


def test_snapping_keeps_the_digits_the_data_demand():
    """0.00153 is not rounded to 0.0015: the test rejects the shorter value on exact data."""
    from sdrl_bench.models.snap import snap_equation

    rng = np.random.default_rng(1)
    theta = rng.uniform(-1, 1, size=(200, 2))
    y = theta @ np.array([1.0, 0.00153]) + 1e-9 * rng.standard_normal(200)
    coef = np.linalg.lstsq(theta, y, rcond=None)[0]
    snapped, digits = snap_equation(theta, y, coef)
    assert snapped.tolist() == [1.0, 0.00153] and digits == 3
    assert snap_equation(theta, y, coef, rtol=1e-12)[1] == 0  # outside the exact regime: kept


def test_snap_digits_round_trip_and_older_files_load(tmp_path):
    x, u, x_next = float32_law()
    model = fit_law(x, u, x_next)
    loaded = SindyModel.load(model.save(tmp_path / "m.json"))
    assert loaded.snap_digits_ == model.snap_digits_
    old = {k: v for k, v in model.to_dict().items() if k != "snap_digits"}
    (tmp_path / "old.json").write_text(json.dumps(old))
    assert SindyModel.load(tmp_path / "old.json").snap_digits_ == [0, 0, 0]


@pytest.mark.parametrize("kw,needle", [({"snap_alpha": 1.5}, "surrogate.model.snap_alpha"),
                                       ({"snap_rtol": 0.0}, "surrogate.model.snap_rtol")])
def test_bad_snap_settings_name_the_key(kw, needle):
    with pytest.raises(ConfigError, match=needle):
        SindyModel(None, **kw)
