"""The NN baseline: accuracy on a toy linear system, reproducibility, saving as data, bad input,
the ``sindy,nn`` multirun on identical data, and the surrogate env checks."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from mlflow.tracking import MlflowClient

from helpers import compose_cfg, search
from sdrl_bench import ConfigError
from sdrl_bench.cli.main import run_fit
from sdrl_bench.report.compare import surrogate_ratios
from sdrl_bench.models.base import DynamicsModel, load_model
from sdrl_bench.models.nn import MLPDynamics

A = np.array([[0.95, 0.10], [-0.20, 0.90]])
B = np.array([[0.0], [0.5]])
SMALL = dict(width=32, depth=2, learning_rate=3e-3, max_epochs=400, max_steps=1500, batch_size=64, patience=100)


def toy(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x' = A x + B u on x in [-1, 1]^2, u in [-1, 1]."""
    rng = np.random.default_rng(seed)
    x, u = rng.uniform(-1, 1, (n, 2)), rng.uniform(-1, 1, (n, 1))
    return x, u, x @ A.T + u @ B.T


def fit_toy(**kw) -> MLPDynamics:
    x, u, xn = toy(256, 0)
    return MLPDynamics(**{**SMALL, **kw}).fit(x, u, xn, state_names=["p", "q"], control_names=["c"])


@pytest.fixture(scope="module")
def ensemble() -> MLPDynamics:
    return fit_toy(ensemble_size=3, seed=4)


def test_fits_a_toy_linear_system_to_1e4_mse(ensemble):
    model = fit_toy(seed=0)
    x, u, xn = toy(1000, 1)
    mse = np.mean((model.predict(x, u) - xn) ** 2, axis=0)
    assert np.all(mse < 1e-4), mse  # the states have variance ~0.3: R^2 > 0.9997
    assert np.all(np.mean((ensemble.predict(x, u) - xn) ** 2, axis=0) < 1e-4)
    assert isinstance(model, DynamicsModel)
    m = model.summary_metrics()
    assert m["n_parameters"] == (3 * 32 + 32) + (32 * 32 + 32) + (32 * 2 + 2)
    assert 0 < m["nn_epochs_run"] <= 400 and m["nn_steps_run"] <= 1500 and m["nn_best_val_loss"] < 1e-3
    assert "MLP 3 -> 32 -> 32 -> 2 (tanh, float32)" in model.describe()


def test_same_seed_gives_bitwise_equal_predictions_and_another_seed_does_not():
    x, u, _ = toy(50, 2)
    a, b, c = (fit_toy(seed=s, max_steps=200) for s in (7, 7, 8))
    assert np.array_equal(a.predict(x, u), b.predict(x, u))
    assert not np.array_equal(a.predict(x, u), c.predict(x, u))


def test_ensemble_mean_and_member_disagreement(ensemble):
    x, u, _ = toy(20, 3)
    members = ensemble.predict_members(x, u)
    assert members.shape == (3, 20, 2)
    assert np.allclose(ensemble.predict(x, u), members.mean(axis=0), rtol=0, atol=1e-12)
    std = ensemble.predict_std(x, u)
    assert std.shape == (20, 2) and np.all(std > 0) and np.all(std < 0.05)
    single = fit_toy(seed=0, max_steps=50)
    assert np.array_equal(single.predict_std(x, u), np.zeros((20, 2)))
    assert ensemble.summary_metrics()["nn_val_member_std"] > 0


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_save_load_round_trip_is_bitwise_and_data_only(tmp_path, ensemble, dtype):
    model = ensemble if dtype == "float32" else fit_toy(dtype="float64", max_steps=100)
    path = model.save(tmp_path / "m" / "model.json")
    assert sorted(p.name for p in path.parent.iterdir()) == ["model.json", "model.pt"]
    meta = json.loads(path.read_text())
    assert meta["kind"] == "nn" and meta["format"] == "sdrl-bench/nn-model-v1"
    assert meta["hyperparameters"]["dtype"] == dtype and len(meta["input_mean"]) == 3
    state = torch.load(path.parent / "model.pt", weights_only=True)
    assert all(isinstance(t, torch.Tensor) for t in state.values())
    loaded = load_model(path)
    assert isinstance(loaded, MLPDynamics)
    x, u, _ = toy(64, 5)
    assert np.array_equal(loaded.predict(x, u), model.predict(x, u))
    assert np.array_equal(loaded.predict_std(x, u), model.predict_std(x, u))
    assert loaded.summary_metrics() == model.summary_metrics()
    assert loaded.describe() == model.describe()


@pytest.mark.parametrize("kw,needle", [
    ({"width": 0}, "surrogate.model.width must be a positive integer, got 0"),
    ({"depth": -1}, "surrogate.model.depth must be a positive integer"),
    ({"learning_rate": -1e-3}, "surrogate.model.learning_rate must be positive, got -0.001"),
    ({"learning_rate": 0}, "surrogate.model.learning_rate must be positive"),
    ({"weight_decay": -1}, "surrogate.model.weight_decay must be >= 0"),
    ({"activation": "sigmoidal"}, "surrogate.model.activation must be one of"),
    ({"val_fraction": 1.0}, r"surrogate.model.val_fraction must be in \(0, 1\)"),
    ({"batch_size": 0}, "surrogate.model.batch_size"),
    ({"max_steps": 0}, "surrogate.model.max_steps"),
    ({"ensemble_size": 0}, "surrogate.model.ensemble_size"),
    ({"dtype": "float16"}, "surrogate.model.dtype"),
    ({"width": 2.5}, "surrogate.model.width"),
])
def test_out_of_range_hyperparameters_name_the_key(kw, needle):
    with pytest.raises(ConfigError, match=needle):
        MLPDynamics(**kw)


def test_bad_hyperparameter_from_the_command_line_fails_before_any_run(new_store):
    store = new_store
    with pytest.raises(ConfigError, match="surrogate.model.width must be a positive integer, got 0"):
        run_fit(compose_cfg("surrogate=nn", "surrogate.model.width=0", f"tracking.uri={store}"))
    with pytest.raises(ConfigError, match="surrogate.model.learning_rate must be positive"):
        run_fit(compose_cfg("surrogate=nn", "surrogate.model.learning_rate=-0.01", f"tracking.uri={store}"))
    assert not Path(store[len("sqlite:///"):]).exists()  # failed before the store was touched


def test_state_dict_that_does_not_match_its_metadata_names_the_file(tmp_path):
    model = fit_toy(max_steps=20)
    path = model.save(tmp_path / "a" / "model.json")
    other = fit_toy(width=16, max_steps=20).save(tmp_path / "b" / "model.json")
    weights = path.parent / "model.pt"
    weights.write_bytes((other.parent / "model.pt").read_bytes())  # a narrower network's weights
    with pytest.raises(ConfigError, match=r"^\S*model\.pt: state dict does not match its metadata model\.json "
                                          r"\(size mismatch for layers\.0\.weight: copying a param with shape "
                                          r"\(1, 3, 16\) from checkpoint, the shape in current model is \(1, 3, 32\)\.;") as info:
        load_model(path)
    assert "\n" not in str(info.value)  # one line, though torch's own message has several
    full = model.net_.state_dict()
    torch.save({k: full[k].clone() for k in ("layers.0.weight", "layers.0.bias")}, weights)
    with pytest.raises(ConfigError, match=r"model\.pt: .*Missing key\(s\) in state_dict: \"layers\.1\.weight\", "
                                          r"\"layers\.1\.bias\""):
        load_model(path)
    torch.save({k: v.to(torch.float64) for k, v in full.items()}, weights)  # load_state_dict would cast it
    with pytest.raises(ConfigError, match=r"model\.pt: .*layers\.0\.weight is torch\.float64, expected torch\.float32"):
        load_model(path)
    torch.save({k: v + 1 for k, v in full.items()}, weights)
    with pytest.raises(ConfigError, match=r"model\.pt: .*sha256"):
        load_model(path)
    torch.save(np.arange(3), weights)  # not a tensor dict: weights_only loading refuses it
    with pytest.raises(ConfigError, match=r"model\.pt"):
        load_model(path)
    weights.unlink()
    with pytest.raises(ConfigError, match=r"model\.pt: weights file named by .*model\.json not found"):
        load_model(path)
    meta = json.loads(path.read_text())
    meta["hyperparameters"]["width"] = 0
    path.write_text(json.dumps(meta))
    with pytest.raises(ConfigError, match=r"model\.json: surrogate.model.width must be a positive integer"):
        load_model(path)


def test_ratios_by_hand():
    s = {"fit_wall_seconds": 0.01, "fit_cpu_seconds": 0.02, "n_parameters": 7, "mse/v": 1e-18, "mse/x": 2e-16}
    n = {"fit_wall_seconds": 2.0, "fit_cpu_seconds": 0.0, "n_parameters": 4546, "mse/v": 1e-7, "mse/x": 4e-5}
    r = surrogate_ratios(s, n)
    assert r["sindy_over_nn/fit_wall_seconds"] == pytest.approx(0.005)
    assert np.isnan(r["sindy_over_nn/fit_cpu_seconds"])
    assert r["sindy_over_nn/n_parameters"] == pytest.approx(7 / 4546)
    assert r["sindy_over_nn/mse/v"] == pytest.approx(1e-11) and r["sindy_over_nn/mse/x"] == pytest.approx(5e-12)
    assert r["nn_over_sindy/fit_wall_seconds"] == pytest.approx(200)
    with pytest.raises(KeyError, match="nn run metrics lack"):
        surrogate_ratios(s, {"mse/v": 1.0})


def test_uncertainty_metrics_by_hand():
    from sdrl_bench.fidelity import uncertainty_metrics

    err = np.array([[0.1, 1.0], [0.2, 3.0], [0.3, 2.0], [0.4, 4.0]])
    std = np.array([[1.0, 0.1], [2.0, 0.4], [3.0, 0.3], [4.0, 0.2]])
    m = uncertainty_metrics(("a", "b"), err, std)
    assert m["uncertainty/spearman/a"] == pytest.approx(1.0)  # same ranking
    assert m["uncertainty/spearman/b"] == pytest.approx(0.4)  # ranks (1, 3, 2, 4) vs (1, 4, 3, 2)
    assert m["uncertainty/within_2std/a"] == 1.0 and m["uncertainty/within_2std/b"] == 0.0
    assert m["uncertainty/mean_std/a"] == pytest.approx(2.5)


def test_ensemble_fit_logs_its_disagreement_per_held_out_transition(store, tmp_path):
    """surrogate=nn with 3 members: uncertainty metrics and a per-transition CSV in the run."""
    import pandas as pd

    res = run_fit(compose_cfg("surrogate=nn", "surrogate.model.ensemble_size=3", "surrogate.model.max_steps=400",
                              f"tracking.uri={store}"))
    run = search(store).iloc[0]
    for n in ("x", "v"):
        assert 0 < run[f"metrics.uncertainty/mean_std/{n}"] < 0.1
        assert -1 <= run[f"metrics.uncertainty/spearman/{n}"] <= 1
        assert 0 <= run[f"metrics.uncertainty/within_2std/{n}"] <= 1
    path = MlflowClient(store).download_artifacts(run["run_id"], "fidelity/uncertainty.csv", str(tmp_path))
    table = pd.read_csv(path)
    assert len(table) == len(res.test) and (table["v_std"] > 0).all()
    assert np.allclose(table["x_abs_err"], np.abs(table["x_pred"] - table["x_true"]))
    assert np.allclose(table["v_std"], res.fidelity.pred_std[:, 1])


def test_nn_surrogate_passes_the_env_checks():
    from gymnasium.utils.env_checker import check_env as gym_check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    from sdrl_bench.data import collect, heuristic_policy
    from sdrl_bench import surrogate
    from sdrl_bench.envs.mountain_car import MountainCarSpec
    from sdrl_bench.surrogate.vec import SurrogateVecEnv

    spec = MountainCarSpec()
    data = collect(spec, heuristic_policy, 75, 0.2, 0)
    x, u = spec.model_inputs(data.states, data.actions)
    keep = ~spec.at_bound(data.next_states)
    model = MLPDynamics(**{**SMALL, "max_steps": 300}).fit(
        x[keep], u[keep], data.next_states[keep][:, spec.target_index], state_names=spec.target_names, control_names=spec.control_names)
    env = surrogate.SurrogateEnv(model, spec)
    gym_check_env(env, skip_render_check=True)
    sb3_check_env(surrogate.SurrogateEnv(model, spec), warn=True)
    obs, _ = env.reset(seed=0)
    nxt, *_ = env.step(np.array([1.0], dtype=np.float32))
    assert nxt.shape == (2,) and np.all(np.isfinite(nxt))
    vec = SurrogateVecEnv(model, spec, n_envs=4)
    vec.seed(0)
    first = vec.reset()
    obs, rewards, dones, infos = vec.step(np.ones((4, 1), dtype=np.float32))
    assert first.shape == obs.shape == (4, 2) and np.all(np.isfinite(obs))
    single = np.array([model.predict(s[None, :], np.ones((1, 1)))[0] for s in first.astype(float)])
    assert np.allclose(obs, single, atol=1e-6)  # batched step = per-state predictions (float32 obs)
