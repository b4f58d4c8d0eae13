"""task=dyna: rounds of collect -> refit -> train on, on tiny budgets with real envs, agents and
a real SQLite store; the learned touchdown-crash model on real LunarLander touchdowns; bad
``rl.dyna.*`` values."""

from __future__ import annotations

import numpy as np
import pytest
from mlflow.tracking import MlflowClient

from gymnasium.envs.box2d.lunar_lander import heuristic

from helpers import compose_cfg, run_cli, search
from sdrl_bench import ConfigError
from sdrl_bench.cli.build import build_dyna_job, build_fit_job
from sdrl_bench.fidelity import step
from sdrl_bench.rl.dyna import LOOP_PHASES, run_dyna
from sdrl_bench.surrogate.events import fit_event_model, label_events, score_events
from sdrl_bench.surrogate.vec import SurrogateVecEnv
from sdrl_bench.tracking.client import start_run
from sdrl_bench.tracking.dyna_runs import DynaRunRecorder

TINY = [
    "experiment=dyna_mountain_car", "agent.n_envs=4", "agent.algo.n_steps=16", "agent.algo.batch_size=32",
    "agent.algo.n_epochs=1", "n_transitions=30", "rl.dyna.collect_per_round=20", "rl.dyna.first_round_steps=64",
    "rl.dyna.surrogate_steps_per_round=64", "rl.dyna.max_rounds=2", "rl.dyna.eval_episodes=2",
    "rl.dyna.final_episodes=2", "rl.dyna.audit_episodes=1", "progress_bar=false",
]


class _Agents:
    """Records the agent object of every round, then hands the round on."""

    def __init__(self, inner):
        self.inner, self.agents, self.rounds = inner, [], []

    def sb3_logger(self):
        return self.inner.sb3_logger()

    def round_done(self, result, agent):
        self.agents.append(agent)
        self.rounds.append(result)
        self.inner.round_done(result, agent)


@pytest.mark.parametrize("from_evaluations", [True, False])
def test_two_round_loop_counts_every_real_step_and_keeps_the_agent(store, from_evaluations):
    import counting_env

    cfg = compose_cfg(*TINY, f"tracking.uri={store}", f"+env.spec.gym_id=counting_env:{counting_env.ENV_ID}",
                      f"rl.dyna.data_from_evaluations={str(from_evaluations).lower()}",
                      "rl.dyna.max_real_transitions=100000")
    job = build_dyna_job(cfg, build_fit_job(cfg))
    checked = job.check()
    with start_run(store, "sdrl-bench", "dyna-test", {"sdrl.kind": "dyna"}) as parent:
        recorder = _Agents(DynaRunRecorder(parent, "sdrl-bench", "dyna-test", {"env": "mountain_car"}))
        before = counting_env.CountingMountainCar.steps
        outcome = run_dyna(job, checked, recorder)
        counted = counting_env.CountingMountainCar.steps - before
        recorder.inner.finish(outcome, job.fit.spec, None, "test")
    s = outcome.summary
    held_out = len(outcome.rounds[-1].fit.test)  # the held-out test set is played once, by the same env
    # the phases add up to the env's own counter (the audit and the test set apart)
    assert counted == s["real_transitions_total"] + s["audit_steps"] + held_out
    assert s["real_transitions_total"] == sum(s[f"real_steps_{p}"] for p in LOOP_PHASES)
    assert s["real_steps_collect"] == 30 + 20  # the initial collection + one round's (round 2 is the last)
    assert s["audit_steps"] > 0 and s["audit_episodes"] == 1
    # the last model's fidelity on the audit's own (on-policy, held-out) transitions, as fidelity.evaluate scores it
    from sdrl_bench.rl.dyna import audit_fidelity

    audit = outcome.audit_data
    assert len(audit) == s["audit_steps"] and audit.content_hash() != outcome.rounds[-1].fit.test.content_hash()
    again = audit_fidelity(outcome.rounds[-1].fit, audit)
    assert {k: s[k] for k in again} == again and "audit_fidelity/rollout100_mse/x" in again
    assert again["audit_fidelity/mse/v"] == pytest.approx(
        float(np.mean((step(outcome.rounds[-1].fit.model, job.fit.spec, audit.states, audit.actions)[:, 1]
                       - audit.next_states[:, 1]) ** 2)), rel=1e-12)
    # round 1's refit saw exactly the rows recorded so far: collections (+ the screens' episodes)
    r1 = outcome.rounds[1]
    expected_rows = 30 + 20 + (r1.screen.steps + (r1.final.steps if r1.final else 0) if from_evaluations else 0)
    assert len(r1.fit.data) == expected_rows
    # the evaluations' rows that reached a fit are counted as reused, not the last round's screens
    reused = [v for k, v in s.items() if k.endswith("reused_as_model_data")]
    assert reused and set(reused) == {float(len(outcome.rounds[-1].fit.data) - 50 if from_evaluations else 0)}
    assert r1.fit.data.content_hash() != outcome.rounds[0].fit.data.content_hash()
    # one agent object across the rounds, trained on: its step count grows
    assert len(recorder.agents) == 3 and all(a is recorder.agents[0] for a in recorder.agents)
    assert [r.surrogate_steps for r in recorder.rounds] == [0, 64, 128]
    # the store: rounds are child runs of the parent, with their fits and accounting
    runs = search(store)
    children = runs[runs["tags.mlflow.parentRunId"] == parent.run_id].sort_values("tags.dyna.round")
    assert children["tags.dyna.round"].tolist() == ["0", "1", "2"]
    assert (children["status"] == "FINISHED").all()
    assert children["metrics.real_transitions_total"].tolist() == [r.real_transitions for r in outcome.rounds]
    # rounds 0 and 1 refitted and hold their fit's metrics; the last round (2) did not refit
    assert children["metrics.mse/x"].notna().tolist() == [True, True, False]
    assert [r.refit for r in outcome.rounds] == [True, True, False]
    client = MlflowClient(store)
    p = client.get_run(parent.run_id).data.metrics
    assert p["real_transitions_total"] == s["real_transitions_total"] and p["surrogate_steps"] == 128
    history = client.get_metric_history(parent.run_id, "dyna/curve_return_mean")
    assert sorted(m.step for m in history) == [int(x) for x, _, _ in outcome.curve]
    artifacts = {a.path for a in client.list_artifacts(parent.run_id, "agents")}
    assert artifacts == {"agents/dyna.zip"}
    # SB3's own training metrics reach the parent run, at the agent's cumulative step count
    assert {m.step for m in client.get_metric_history(parent.run_id, "dyna/sb3/time/total_timesteps")} == {64, 128}


def test_dyna_cli_writes_parent_and_round_runs(store, tmp_path):
    res = run_cli(*TINY, "rl.dyna.max_rounds=1", f"tracking.uri={store}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "Dyna: " in res.stdout and "audit:" in res.stdout
    runs = search(store)
    parent = runs[runs["tags.sdrl.kind"] == "dyna"]
    assert len(parent) == 1 and parent["status"].iloc[0] == "FINISHED"
    assert parent["params.rl.dyna.collect_per_round"].iloc[0] == "20"
    rounds = runs[runs["tags.sdrl.kind"] == "dyna_round"]
    assert sorted(rounds["tags.dyna.round"]) == ["0", "1"]
    assert (rounds["tags.mlflow.parentRunId"] == parent["run_id"].iloc[0]).all()


@pytest.mark.parametrize("override,needle", [
    ("rl.dyna.collect_per_round=-1", "rl.dyna.collect_per_round: an integer >= 0"),
    ("rl.dyna.first_round_steps=0", "rl.dyna.first_round_steps: a positive integer"),
    ("rl.dyna.max_real_transitions=1.5", "rl.dyna.max_real_transitions: a positive integer"),
    ("rl.dyna.epsilon=2", "rl.dyna.epsilon must be within [0, 1]"),
    ("rl.dyna.learn_events=maybe", "rl.dyna.learn_events: true or false"),
    ("rl.dyna.audit_episodes=-1", "rl.dyna.audit_episodes: an integer >= 0"),
    ("+rl.dyna.rounds=3", "rl.dyna.rounds: unknown key"),
])
def test_bad_dyna_values_are_one_line_errors_naming_the_key(override, needle):
    cfg = compose_cfg(*TINY, override)
    with pytest.raises(ConfigError, match=needle.replace("[", r"\[").replace("]", r"\]")):
        build_dyna_job(cfg, build_fit_job(cfg))


def test_bad_dyna_value_exits_2_before_any_run(store, tmp_path):
    res = run_cli(*TINY, "rl.dyna.surrogate_steps_per_round=-5", f"tracking.uri={store}", cwd=tmp_path)
    assert res.returncode == 2
    lines = [ln for ln in res.stderr.strip().splitlines() if ln.startswith("sdrl-bench")]
    assert lines == ["sdrl-bench: error: rl.dyna.surrogate_steps_per_round: a positive integer is required, got -5"]
    db = tmp_path / "mlruns" / "mlflow.db"  # the store of ``store``: never made, or without runs
    assert not db.exists() or search(store).empty


def _episodes(touchdowns):
    """Recorded LunarLander episodes in the dataset layout: each (x, vy, outcome, rows after
    the touchdown): 3 flight rows descending to the touchdown row (s' has a leg flag), then
    rows on the legs; outcome "crash" ends with -100, "rest" with +100, "cut" just stops."""
    from sdrl_bench.data import _stack

    rows = []
    for e, (x, vy, outcome, after) in enumerate(touchdowns):
        t = 0
        for k in range(3):
            s = np.array([x, 0.3 - 0.1 * k, 0.0, vy, 0.0, 0.0, 0.0, 0.0])
            rows.append((s, np.array([0.0]), -0.1, s + [0, -0.1, 0, 0, 0, 0, 0, 0], False, False, e, t))
            t += 1
        s = np.array([x, 0.0, 0.0, vy, 0.0, 0.0, 0.0, 0.0])
        legs = s + [0, -0.01, 0, 0, 0, 0, 1, 1]
        rows.append((s, np.array([0.0]), 10.0, legs, False, False, e, t))
        for k in range(after):
            last = k == after - 1 and outcome != "cut"
            r = {"crash": -100.0, "rest": 100.0}.get(outcome, 0.0) if last else 0.0
            rows.append((legs, np.array([0.0]), r, legs, last, False, e, t + 1 + k))
    return _stack(rows)


def _touchdown(spec):
    return next(e for e in spec.task.events if e.name == "touchdown")


def test_touchdown_outcomes_are_labelled_and_learned_off_the_pad():
    """The generic event code finds each episode's first touchdown (the declared trigger) and
    labels it from how the episode ended; touchdowns the prior already crashes (too fast) are
    left to the prior and cut episodes are left out; the fitted model gives off-pad touchdowns a
    higher crash probability than on-pad ones."""
    spec = build_fit_job(compose_cfg("env=lunar_lander")).spec
    event = _touchdown(spec)
    rng = np.random.default_rng(0)
    xs = rng.uniform(-0.8, 0.8, 40)
    episodes = [(x, -0.05, "crash" if abs(x) > 0.35 else "rest", 5 if abs(x) > 0.35 else 40) for x in xs]
    episodes += [(0.0, -0.05, "cut", 10),     # stops 10 rows after its touchdown: outcome unknown
                 (0.0, -0.9, "crash", 2),     # 6.75 m/s down: the prior's crash, not the model's
                 (0.5, -0.05, "crash", 45)]   # -100 long after the touchdown: not the touchdown's crash
    data = _episodes(episodes)
    events = label_events(event, data)
    assert len(events) == 42 and events.prior.tolist() == [0] * 40 + [1, 0]
    crash = event.outcome_names.index("crash")
    assert (events.outcome[:40] == crash).tolist() == [abs(x) > 0.35 for x in xs] and events.outcome[41] != crash
    feats = event.features(events.pre)
    np.testing.assert_allclose(feats[:40, 0], xs)
    np.testing.assert_allclose(feats[:40, 2], np.maximum(np.abs(xs) - 0.2, 0.0))
    model = fit_event_model(event, data, min_events=8)
    assert model is not None and model.n_events == 41 and model.counts["crash"] == int(sum(abs(xs) > 0.35))
    states = np.zeros((3, 8))
    states[:, 0], states[:, 3] = [0.0, 0.3, 0.7], -0.05
    p = model.probabilities(event.features(states))[:, crash]
    assert p[0] < 0.2 < 0.8 < p[2] and p[0] < p[1] < p[2]
    assert model.train_accuracy >= 0.85  # one event (x = 0.5, crashed 45 steps later) is off the boundary
    assert 0.8 <= model.cv_accuracy <= 1.0
    # too few events, or one outcome only: no model (the rules alone decide)
    assert fit_event_model(event, _episodes(episodes[:5]), min_events=8) is None
    assert fit_event_model(event, _episodes([e for e in episodes[:40] if e[2] == "rest"]), min_events=8) is None
    # the score on held-out events: the prior decides the fast one, the model the rest
    held = _episodes([(0.0, -0.05, "rest", 40), (0.7, -0.05, "crash", 3), (0.0, -0.9, "crash", 2)])
    score = score_events(event, model, held)
    assert score["n"] == 3 and score["accuracy"] == 1.0 and score["prior_accuracy"] == pytest.approx(2 / 3)
    assert score["log_loss"] < 0.5


def test_learned_crashes_end_surrogate_touchdowns_with_the_crash_reward():
    """An event model that always says crash ends every surrogate touchdown the rules let
    survive with -100; with no event model the same seed lands (no learned crash)."""
    from sklearn.dummy import DummyClassifier
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    from sdrl_bench.pipeline import fit_dynamics
    from sdrl_bench.surrogate.events import EventModel

    cfg = compose_cfg("env=lunar_lander", "collector=heuristic", "n_transitions=600")
    job = build_fit_job(cfg)
    fit = fit_dynamics(job)
    spec = job.spec
    event = _touchdown(spec)
    crash = event.outcome_names.index("crash")
    x = np.zeros((2, len(event.feature_names)))
    always = EventModel("touchdown", event.outcome_names, event.feature_names,
                        make_pipeline(StandardScaler(), DummyClassifier(strategy="constant", constant=crash)).fit(x, [crash, crash]),
                        2, {"survive": 0, "crash": 2}, 1.0, 0.0)
    outcomes = {}
    for name, events in (("none", None), ("always", {"touchdown": always})):
        venv = SurrogateVecEnv(fit.model, spec, 16, seed=3, events=events)
        env = spec.make_env()
        rewards = []
        obs = venv.reset()
        for _ in range(400):
            actions = np.array([heuristic(env.unwrapped, o) for o in obs])
            obs, r, done, infos = venv.step(actions)
            rewards.append(r)
        outcomes[name] = (venv.event_counts["touchdown"]["crash"], np.concatenate(rewards))
    assert outcomes["none"][0] == 0
    assert outcomes["always"][0] > 0
    assert np.sum(outcomes["always"][1] == -100) >= outcomes["always"][0]
    assert np.sum(outcomes["always"][1] == 100) < np.sum(outcomes["none"][1] == 100)


def test_the_event_score_is_the_learned_models_and_differs_with_the_data():
    """``events/<name>/test_*`` score the run's own event model: two datasets with different
    touchdowns give different models and different held-out scores; the prior alone scores the
    same for both (what the old fixed score measured)."""
    spec = build_fit_job(compose_cfg("env=lunar_lander")).spec
    event = _touchdown(spec)
    rng = np.random.default_rng(1)
    held = _episodes([(x, -0.05, "crash" if abs(x) > 0.35 else "rest", 5 if abs(x) > 0.35 else 40)
                      for x in rng.uniform(-0.8, 0.8, 30)])
    scores = []
    for boundary in (0.35, 0.6):  # a run whose landers crashed off the pad, and one whose survived further out
        xs = rng.uniform(-0.8, 0.8, 40)
        data = _episodes([(x, -0.05, "crash" if abs(x) > boundary else "rest", 5 if abs(x) > boundary else 40) for x in xs])
        model = fit_event_model(event, data)
        scores.append(score_events(event, model, held))
    assert scores[0]["prior_accuracy"] == scores[1]["prior_accuracy"]
    assert scores[0]["log_loss"] != scores[1]["log_loss"] and scores[0]["accuracy"] > scores[1]["accuracy"]


def test_a_real_step_budget_below_the_first_collection_is_refused():
    """Before, the header promised 'at most 10 real steps', then collected 75 and trained round 1."""
    cfg = compose_cfg(*TINY, "rl.dyna.max_real_transitions=10")
    with pytest.raises(ConfigError) as err:
        build_dyna_job(cfg, build_fit_job(cfg)).check()
    assert str(err.value) == "rl.dyna.max_real_transitions: 10 is below the first collection's n_transitions=30"
