"""The JAX evaluator (models/jax_eval.py) against the numpy ones: every built-in env's sparse fit
(SINDy and per-equation, staged with bounds, ensemble members) on 10,000 inputs spanning the
data and beyond the bounds; eager evaluation is the one-state evaluator bit for bit; jit agrees
to rounding (bit for bit without FMA); NN models are refused; the package imports without jax."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import numpy as np
import pysindy as ps
import pytest

jax = pytest.importorskip("jax")
pytestmark = pytest.mark.jax

from helpers import compose_cfg  # noqa: E402
from sdrl_bench.cli.build import build_fit_job  # noqa: E402
from sdrl_bench.models.fast import batch_predictor, scalar_predictor  # noqa: E402
from sdrl_bench.models.jax_eval import jax_predictor, linear_predictor  # noqa: E402
from sdrl_bench.models.libraries import LibraryPart, RationalLibrary, TrigLibrary, build_library  # noqa: E402
from sdrl_bench.models.per_equation import PerEquationModel  # noqa: E402
from sdrl_bench.models.sindy import SindyModel  # noqa: E402
from sdrl_bench.models.terms import OPS  # noqa: E402
from sdrl_bench.pipeline import fit_dynamics  # noqa: E402
from sdrl_bench.surrogate.model_env import member_predictors  # noqa: E402

ENVS = {"mountain_car": 75, "pendulum": 200, "lunar_lander": 1000, "cartpole_swingup": 300}
"""Every built-in env with a sparse fit path: its default library and transitions for a quick fit."""
TOL = 1e-12
_FITS: dict[str, tuple] = {}


def fitted(env: str) -> tuple:
    """(model, spec, model inputs of the fit's data (N, n_inputs)), fitted once per env."""
    if env not in _FITS:
        res = fit_dynamics(build_fit_job(compose_cfg(f"env={env}", "collector=random", f"n_transitions={ENVS[env]}")))
        x, u = res.job.spec.model_inputs(res.data.states, res.data.actions)
        _FITS[env] = (res.model, res.job.spec, np.concatenate([x, u], axis=1))
    return _FITS[env]


def draw_inputs(spec, data: np.ndarray, n: int = 10_000, seed: int = 0) -> np.ndarray:
    """n inputs spanning the data's range and the env's bounds, and half that span beyond on each
    side (past the bounds); one-hot action columns stay one-hot."""
    rng = np.random.default_rng(seed)
    lo, hi = data.min(axis=0), data.max(axis=0)
    index = np.concatenate([spec.target_index, spec.exogenous_index]).astype(int)  # the state inputs
    n_s = len(index)
    for bound, side, pick in ((spec.state_low, lo, np.fmin), (spec.state_high, hi, np.fmax)):
        if bound is not None:  # fmin / fmax skip the NaN of an unbounded side
            b = np.asarray(bound, dtype=float)[index]
            side[:n_s] = pick(side[:n_s], np.where(np.isfinite(b), b, np.nan))
    span = np.where(hi > lo, hi - lo, 1.0)
    z = rng.uniform(lo - 0.5 * span, hi + 0.5 * span, size=(n, data.shape[1]))
    k = spec.n_discrete_actions if spec.action_encoding == "one_hot" else 0
    if k:
        z[:, -k:] = np.eye(k)[rng.integers(k, size=n)]
    return z


def with_bounds(model: PerEquationModel, data: np.ndarray, states: list[str]) -> PerEquationModel:
    """The model reloaded with bounds on its primed ``states`` at the 15th / 85th percentiles of its
    predictions on the data: a staged model whose bounds are active on many inputs."""
    pred = model.predict(data[:, :len(model.state_names_)], data[:, len(model.state_names_):])
    d = model.to_dict()
    d["bounds"] = {s: [float(q) for q in np.percentile(pred[:, model.state_names_.index(s)], [15, 85])] for s in states}
    staged = PerEquationModel.from_dict(d)
    assert staged.stages_ is not None and len(staged.stages_["stages"]) > 1
    return staged


def check_agrees(model, z: np.ndarray, member: int | None = None) -> float:
    """max |jax - numpy| against the batch evaluator and ``model.predict`` (for ensemble member
    ``member``: against its batch evaluator, ``member_predictors``, and ``predict_members``);
    asserts it is at most 1e-12 and returns it."""
    n = len(model.state_names_)
    if member is None:
        got = np.asarray(jax_predictor(model)(z))
        batch = batch_predictor(model)(np.ascontiguousarray(z.T)).T
        ref = model.predict(z[:, :n], z[:, n:])
    else:
        got = np.asarray(jax_predictor(model, model.members_[member])(z))
        batch = member_predictors(model)[member](np.ascontiguousarray(z.T)).T
        ref = model.predict_members(z[:, :n], z[:, n:])[member]
    assert got.shape == (len(z), n) and got.dtype == np.float64
    diff = max(float(np.max(np.abs(got - batch))), float(np.max(np.abs(got - ref))))
    assert diff <= TOL, diff
    # the coefficients as an argument of one compiled program (linear_predictor), for the model
    # and each member through the same program
    lin, _, columns = linear_predictor(model)
    c = columns(model.coef_ if member is None else model.members_[member])
    arg = np.asarray(jax.jit(lin)(z, c))
    assert np.max(np.abs(arg - batch)) <= TOL
    return diff


def check_clips_active(model, z: np.ndarray, share: float = 0.05) -> None:
    """Every bound a staged model applies between stages is active on at least ``share`` of z."""
    n = len(model.state_names_)
    pred = model.predict(z[:, :n], z[:, n:])
    for st in model.stages_["stages"]:
        for r, _, lo, hi in st["clips"]:
            assert np.mean((pred[:, r] < lo) | (pred[:, r] > hi)) >= share, (model.state_names_[r], lo, hi)


@pytest.mark.parametrize("env", list(ENVS))
def test_each_envs_fit_matches_the_numpy_evaluators(env):
    """10,000 inputs spanning the data and past the bounds: |jax - numpy| <= 1e-12 (Pendulum's
    staged law clips thdot' before th' reads it on a good share of them)."""
    model, spec, data = fitted(env)
    assert isinstance(model, SindyModel if env == "mountain_car" else PerEquationModel)
    z = draw_inputs(spec, data)
    if env == "pendulum":
        check_clips_active(model, z)
    check_agrees(model, z)


@pytest.mark.parametrize("env, states", [("lunar_lander", ["vx", "vy", "angvel"]), ("cartpole_swingup", ["xdot", "thdot"])])
def test_staged_laws_with_active_bounds_and_ensemble_members_match(env, states):
    """The flight law and the cart-pole law with bounds on their primed velocities (several
    stages, clips between them, products of a bounded next value with a function of an input)
    and, for LunarLander, every bootstrap member's coefficients."""
    model, spec, data = fitted(env)
    staged = with_bounds(model, data, states)
    z = draw_inputs(spec, data, seed=1)
    check_clips_active(staged, z)
    check_agrees(staged, z)
    members = staged.members_
    assert (len(members) == 5) == (env == "lunar_lander")
    for k in range(len(members)):
        check_agrees(staged, z, k)


def test_every_op_of_the_term_table():
    """A SINDy library that uses every op (powers, sin / cos at two frequencies, rat, xrat)."""
    rng = np.random.default_rng(0)
    x, u = rng.uniform(-1, 1, (300, 3)), rng.uniform(-1, 1, (300, 2))
    x_next = np.column_stack([0.9 * x[:, 0] + 0.1 * u[:, 0] * x[:, 1], x[:, 1] - 0.2 * np.sin(3.0 * x[:, 1]),
                              0.5 * x[:, 2] / (1 + x[:, 2] ** 2) + 0.3])
    parts = [LibraryPart(ps.PolynomialLibrary(degree=2)), LibraryPart(TrigLibrary([0.5, 3.0]), ("s1",)),
             LibraryPart(RationalLibrary(), "states")]
    names, controls = ["s0", "s1", "s2"], ["c0", "c1"]
    model = SindyModel(build_library(parts, names, controls), ps.STLSQ(threshold=0.0, alpha=1e-6), snap_alpha=None).fit(
        x, u, x_next, state_names=names, control_names=controls)
    used = {f[1] for k, t in enumerate(model.terms_) if np.any(model.coef_[:, k]) for f in t}
    assert used == set(OPS)
    check_agrees(model, rng.uniform(-3, 3, (10_000, 5)))


def test_eager_is_the_one_state_evaluator_bit_for_bit_and_jit_agrees_to_rounding():
    """Eager evaluation runs the one-state evaluator's generated source on columns: equal bit for
    bit. Under jit, XLA's CPU backend fuses a*b + c into FMAs: equal to rounding, and the same
    compiled function gives the same bits again (whole batch, a slice, vmapped rows)."""
    for env in ENVS:
        model, spec, data = fitted(env)
        z = draw_inputs(spec, data, seed=2)
        f = jax_predictor(model)
        eager = np.asarray(f(z))
        one = scalar_predictor(model)
        assert np.array_equal(eager[:500], np.array([one(list(r)) for r in z[:500]])), env
        assert np.array_equal(np.asarray(f(z[7])), eager[7])  # one input vector: (n_states,)
        jf = jax.jit(f)
        compiled = np.asarray(jf(z))
        assert np.max(np.abs(compiled - eager)) <= 1e-14 * max(1.0, float(np.max(np.abs(eager)))), env
        assert np.array_equal(np.asarray(jf(z)), compiled)
        assert np.array_equal(np.asarray(jax.jit(jax.vmap(f))(z)), compiled)


@pytest.mark.skipif(platform.machine().lower() not in ("x86_64", "amd64"), reason="XLA's x86 ISA flag")
def test_jit_equals_eager_bit_for_bit_without_fma(tmp_path):
    """With FMA instructions off (XLA_FLAGS=--xla_cpu_max_isa=AVX, set before jax starts), the
    compiled function gives exactly the eager (op by op) results on every env's fit."""
    paths = []
    for env in ENVS:
        model, spec, data = fitted(env)
        paths.append(str(model.save(tmp_path / f"{env}.json")))
        np.save(tmp_path / f"{env}.npy", draw_inputs(spec, data, seed=3))
    code = (
        "import sys, numpy as np, jax\n"
        "from sdrl_bench.models.base import load_model\n"
        "from sdrl_bench.models.jax_eval import jax_predictor\n"
        "for p in sys.argv[1:]:\n"
        "    f, z = jax_predictor(load_model(p)), np.load(p[:-5] + '.npy')\n"
        "    a, b = np.asarray(f(z)), np.asarray(jax.jit(f)(z))\n"
        "    print(p, np.array_equal(a, b), np.max(np.abs(a - b)))\n"
    )
    out = subprocess.run([sys.executable, "-c", code, *paths], capture_output=True, text=True, timeout=120,
                         env={**_env(), "XLA_FLAGS": "--xla_cpu_max_isa=AVX"})
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.splitlines()
    assert len(lines) == len(ENVS) and all(" True " in line for line in lines), out.stdout


def test_a_backend_started_before_the_harness_flags_is_warned_of():
    """XLA reads XLA_FLAGS once, when jax's backend starts. A process that ran a jax computation
    before sdrl_bench's jax modules set the harness's flags is told, once; one that starts jax
    through them is not, and XLA_FLAGS then holds every harness flag."""
    from sdrl_bench.models.jax_eval import DEFAULT_XLA_FLAGS

    def run(first: str) -> subprocess.CompletedProcess:
        code = (
            "import os, warnings\n"
            "warnings.simplefilter('always')\n"
            f"{first}\n"
            "from sdrl_bench.models.jax_eval import jax_modules\n"
            "jax_modules('probe'); jax_modules('probe')\n"
            "print(os.environ['XLA_FLAGS'])\n"
        )
        return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=_env())

    early = run("import jax; jax.numpy.ones(2).block_until_ready()")
    assert early.returncode == 0, early.stderr[-2000:]
    said = [line for line in early.stderr.splitlines() if "started before sdrl_bench set XLA_FLAGS" in line]
    assert len(said) == 1 and all(flag in said[0] for flag in DEFAULT_XLA_FLAGS.values()), early.stderr[-2000:]
    assert "probe: JAX's backend" in said[0]

    through = run("import jax")  # imported, not started
    assert through.returncode == 0, through.stderr[-2000:]
    assert "started before sdrl_bench" not in through.stderr
    assert all(flag in through.stdout for flag in DEFAULT_XLA_FLAGS.values()), through.stdout


def test_products_are_full_precision_unless_the_user_says_otherwise():
    """``jax_modules`` sets JAX's default matmul precision to ``highest`` (SB3's torch computes
    float32 products in full; JAX's default on a GPU is TF32), so the compiled programs' products
    are annotated so; a ``$JAX_DEFAULT_MATMUL_PRECISION`` the user set stands."""
    code = ("from sdrl_bench.models.jax_eval import jax_modules\n"
            "jax, jnp = jax_modules('probe')\n"
            "x = jnp.ones((4, 4), jnp.float32)\n"
            "text = jax.jit(lambda a: a @ a).lower(x).as_text()\n"
            "print(jax.config.jax_default_matmul_precision, 'precision = [HIGHEST, HIGHEST]' in text)\n")
    for var, want in ((None, "highest True"), ("bfloat16", "bfloat16 False")):
        env = {k: v for k, v in _env().items() if k != "JAX_DEFAULT_MATMUL_PRECISION"}
        if var:
            env["JAX_DEFAULT_MATMUL_PRECISION"] = var
        res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
        assert res.returncode == 0 and res.stdout.split("\n")[-2] == want, (res.stdout, res.stderr[-2000:])


def _env() -> dict:
    return {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}


@pytest.mark.parametrize("kind", ["nn", "pe"])
def test_nn_models_are_refused_naming_their_kind(kind):
    from sdrl_bench.models.nn import MLPDynamics
    from sdrl_bench.models.pe import GaussianEnsembleDynamics

    model = MLPDynamics() if kind == "nn" else GaussianEnsembleDynamics()
    with pytest.raises(TypeError, match=rf"a '{kind}' model .* only the sparse models"):
        jax_predictor(model)


def test_the_package_imports_without_jax(tmp_path):
    """jax is an optional extra: the module imports without it, and asking for a JAX evaluator
    says how to install it."""
    model, *_ = fitted("pendulum")
    path = model.save(tmp_path / "m.json")
    code = (
        "import sys\n"
        "sys.modules['jax'] = None\n"
        "import sdrl_bench.models.jax_eval as j\n"
        "from sdrl_bench.models.base import load_model\n"
        "try:\n"
        "    j.jax_predictor(load_model(sys.argv[1]))\n"
        "except ImportError as exc:\n"
        "    print('ImportError:', exc)\n"
    )
    out = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=120, env=_env())
    assert out.returncode == 0, out.stderr[-2000:]
    assert "ImportError: sdrl_bench.models.jax_eval needs jax" in out.stdout and "sdrl-bench[jax]" in out.stdout


@pytest.mark.parametrize("bounded", [False, True])
def test_fits_of_one_library_that_keep_other_terms_share_one_compiled_program(bounded):
    """A per-equation refit that drops terms has another term table but the same candidate
    structure: ``linear_predictor`` gives both one key, and the program compiled for the first
    evaluates the second's coefficients (its own ``columns``) as its numpy evaluators do, staged
    bounds included."""
    model, spec, data = fitted("lunar_lander")
    if bounded:
        model = with_bounds(model, data, ["vx", "vy", "angvel"])
    table = {repr(t) for t in model.terms_}

    def dropped(t: str, k: int) -> PerEquationModel:
        d = model.to_dict()
        d.pop("members", None)  # the members' terms are in the table too
        d["coefficients"][t] = [0.0 if j == k else c for j, c in enumerate(d["coefficients"][t])]
        return PerEquationModel.from_dict(d)

    # a refit that keeps one term fewer, where that leaves another flattened term table
    refits = (dropped(t, k) for t, c in model.eq_coef_.items() for k in np.flatnonzero(c))
    sparser = next(m for m in refits if {repr(x) for x in m.terms_} != table)
    lin_a, key_a, _ = linear_predictor(model)
    _, key_b, columns_b = linear_predictor(sparser)
    assert key_a == key_b
    z = draw_inputs(spec, data, n=2000, seed=2)
    got = np.asarray(jax.jit(lin_a)(z, columns_b(sparser.coef_)))
    want = batch_predictor(sparser)(np.ascontiguousarray(z.T)).T
    assert np.max(np.abs(got - want)) <= TOL
    assert np.max(np.abs(got - batch_predictor(model)(np.ascontiguousarray(z.T)).T)) > 1e-3  # the drop matters
