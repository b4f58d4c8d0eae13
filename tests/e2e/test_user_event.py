"""An event no built-in env has, declared by a user: a body falling onto a floor breaks it (the
episode ends, -10) above a speed and rests there below it. The env, its task functions and its
YAML (with the ``events:`` declaration) live in a temp directory; nothing under sdrl_bench/ names
it. From the command line, the run learns the impact's outcome model from its own transitions,
scores it on held-out real impacts and logs it; its surrogate ends impacts with the learned
probability."""

from __future__ import annotations

import os

import numpy as np
import pytest

from helpers import run_cli, search
from user_env import write_faller_dir

TINY = ("rl.surrogate_steps=200", "rl.real_steps=64", "rl.eval_every=200", "rl.eval_episodes=1", "rl.final_episodes=2",
        "rl.arms=[surrogate]", "agent.algo.train_freq=16", "agent.algo.gradient_steps=1", "agent.algo.batch_size=32",
        "agent.algo.policy_kwargs.net_arch=[16]", "progress_bar=false")


@pytest.fixture
def faller(tmp_path, monkeypatch):
    src, conf = write_faller_dir(tmp_path / "user")
    monkeypatch.syspath_prepend(str(src))
    env = {"PYTHONPATH": os.pathsep.join(p for p in (str(src), os.environ.get("PYTHONPATH", "")) if p)}
    yield src, conf, env
    import sys

    for mod in [m for m in sys.modules if m == "faller_envs" or m.startswith("faller_envs.")]:
        del sys.modules[mod]


def test_a_user_event_is_learned_scored_logged_and_used_in_the_surrogate(tmp_path, store, faller):
    src, conf, env = faller
    res = run_cli("--config-dir", str(conf), "env=faller", "collector=random", "task=train", "agent=sac", *TINY,
                  f"tracking.uri={store}", cwd=tmp_path, env=env)
    assert res.returncode == 0, res.stderr[-3000:]
    row = search(store).iloc[0]
    assert row["status"] == "FINISHED" and row["tags.env"] == "faller"
    m = {k[len("metrics."):]: v for k, v in row.items() if k.startswith("metrics.") and np.isfinite(v)}
    # learned from the run's own impacts (both outcomes seen), scored on the held-out test set's impacts
    assert m["events/impact/learned"] == 1.0
    assert m["events/impact/n_events"] >= 8 and m["events/impact/n_break"] >= 1 and m["events/impact/n_rest"] >= 1
    assert m["events/impact/test_n"] >= 5 and m["events/impact/test_accuracy"] >= 0.8
    # used in the surrogate the agent trained in: impacts drawn, some ending the episode
    assert m["surrogate/surrogate_events/impact/break"] + m["surrogate/surrogate_events/impact/rest"] >= 1

    import mlflow

    client = mlflow.tracking.MlflowClient(store)
    logged = client.download_artifacts(row["run_id"], "events/impact.json", str(tmp_path))
    import json

    model = json.loads(open(logged).read())
    assert model["event"] == "impact" and model["outcomes"] == ["rest", "break"] and model["features"] == ["v"]
    # the learned boundary: faster impacts (more negative v) break; one feature, so one slope
    assert model["coef"][0][0] < 0


def test_the_learned_impact_decides_surrogate_impacts_by_speed(faller):
    """In-process: the fit's event model ends fast surrogate impacts and lets slow ones rest."""
    from helpers import compose_cfg
    from sdrl_bench.cli.build import build_fit_job
    from sdrl_bench.pipeline import fit_dynamics
    from sdrl_bench.surrogate.model_env import ModelEnv

    src, conf, _ = faller
    job = build_fit_job(compose_cfg(f"hydra.searchpath=[file://{conf}]", "env=faller", "collector=random"))
    fit = fit_dynamics(job)
    assert fit.events["impact"] is not None
    core = ModelEnv(fit.model, job.spec, events=fit.events, seed=0)
    n = 400
    for v0, expect_break in ((-1.5, True), (-0.1, False)):
        states = np.column_stack([np.full(n, 0.001), np.full(n, v0)])
        _, rewards, terminated, _ = core.step(states, np.zeros((n, 1)))  # u = 0: falls through the floor
        broke = terminated.mean()
        assert (broke > 0.9) if expect_break else (broke < 0.1), (v0, broke)
        assert np.all(rewards[terminated] == -10.0)
    assert core.event_counts["impact"]["break"] > 0.9 * n and core.event_counts["impact"]["rest"] > 0.9 * n
