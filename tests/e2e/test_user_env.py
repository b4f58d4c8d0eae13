"""A user's own env, end to end from the command line: a gymnasium env registered in the user's
own module (a temp directory on PYTHONPATH), its YAML in a ``--config-dir``, fitted and
transferred with tiny budgets; nothing under sdrl_bench/ is touched. Then the saved model drives
``gym.make("sdrl/Surrogate-v0", spec="oscillator", config_dir=...)``."""

from __future__ import annotations

import json
import os

import gymnasium as gym
import numpy as np

from helpers import run_cli, search
from user_env import LAW, write_user_dir

TINY = ("rl.surrogate_steps=64", "rl.real_steps=64", "rl.eval_every=64", "rl.eval_episodes=1", "rl.final_episodes=2",
        "agent.algo.train_freq=16", "agent.algo.gradient_steps=2", "agent.algo.batch_size=32",
        "agent.algo.policy_kwargs.net_arch=[16]", "progress_bar=false")


def test_user_env_fits_and_transfers_from_a_config_dir(tmp_path, store, monkeypatch):
    src, conf = write_user_dir(tmp_path / "user")
    env = {"PYTHONPATH": os.pathsep.join(p for p in (str(src), os.environ.get("PYTHONPATH", "")) if p)}
    res = run_cli("--config-dir", str(conf), "env=oscillator", "collector=random", "task=train", "agent=sac", *TINY,
                  f"tracking.uri={store}", cwd=tmp_path, env=env)
    assert res.returncode == 0, res.stderr[-3000:]
    runs = search(store)
    assert runs["status"].tolist() == ["FINISHED"] and runs["tags.env"].tolist() == ["oscillator"]
    row = runs.iloc[0]
    assert row["metrics.surrogate/real_transitions_model"] == 60
    assert np.isfinite(row["metrics.surrogate/final_return_mean"]) and np.isfinite(row["metrics.real/final_return_mean"])

    # the known law, recovered from 60 random transitions (float32 observations; snapped)
    import mlflow

    client = mlflow.tracking.MlflowClient(store)
    path = client.download_artifacts(row["run_id"], "model/model.json", str(tmp_path))
    from sdrl_bench.models.sindy import SindyModel

    model = SindyModel.load(path)
    got = {eq: {t: c for t, c in terms.items() if c != 0} for eq, terms in model.coefficients_by_name().items()}
    assert got == LAW, json.dumps(got)

    # the same spec by name, for gym.make, from the user's config dir
    monkeypatch.syspath_prepend(str(src))
    import sdrl_bench  # noqa: F401  (registers sdrl/Surrogate-v0)

    sur = gym.make("sdrl/Surrogate-v0", model=path, spec="oscillator", config_dir=str(conf))
    obs, _ = sur.reset(seed=0, options={"state": [0.5, -0.2]})
    obs, reward, *_ = sur.step(np.array([2.0], dtype=np.float32))  # clipped to 1 by the encoding
    np.testing.assert_allclose(obs, [0.5 - 0.02, -0.2 - 0.05 + 0.1], rtol=1e-6)
    assert reward == -0.25
