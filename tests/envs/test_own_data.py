"""LunarLander from the run's own data (``env.spec.own_data``): the contact rules and the
pessimism's scale learned from real transitions, the priors they replace no longer counted, the
surrogate built on (and swapped to) the learned spec, a tiny Dyna run in a real store."""

from __future__ import annotations

import math

import numpy as np
import pytest
from mlflow.tracking import MlflowClient

from helpers import compose_cfg, search
from sdrl_bench.cli.build import build_dyna_job, build_fit_job
from sdrl_bench.data import collect, heuristic_policy, held_out_test_set
from sdrl_bench.envs.lunar_lander import LunarLanderSpec, task
from sdrl_bench.envs.lunar_lander.own_data import STICK_GRID, choose_stick, learn_rules
from sdrl_bench.envs.lunar_lander.spec import FLIGHT_NOISE_FLOOR
from sdrl_bench.envs.lunar_lander.task import LanderRules
from sdrl_bench.pipeline import fit_dynamics
from sdrl_bench.rl.accounting import prior_steps
from sdrl_bench.rl.dyna import run_dyna
from sdrl_bench.surrogate.vec import SurrogateVecEnv
from sdrl_bench.tracking.client import start_run
from sdrl_bench.tracking.dyna_runs import DynaRunRecorder

OWN = ("experiment=dyna_lunar_lander_own",)


@pytest.fixture(scope="module")
def heuristic_data():
    """1000 real transitions of gymnasium's heuristic at eps 0.2 (Dyna's first collection)."""
    return collect(LunarLanderSpec(), heuristic_policy, 1000, 0.2, seed=1001)


def _settle_mse(rules: LanderRules, test) -> np.ndarray:
    s, ns = test.states, test.next_states
    both = (s[:, 6] > 0.5) & (s[:, 7] > 0.5) & (ns[:, 6] > 0.5) & (ns[:, 7] > 0.5) & ~test.terminated.astype(bool)
    pred = task.regime_dynamics(rules, True, s[both], test.actions[both], np.zeros((6, int(both.sum()))))
    return ((pred.T - ns[both][:, :6]) ** 2).mean(axis=0)


def test_contact_rules_from_1000_heuristic_transitions_predict_held_out_contact(heuristic_data):
    """The leg rule, floor and settle model learned from 1000 transitions: the flags right on
    over 95% of the pad rows, the floor just below the pad, and the settle step on the held-out
    set's standing rows better than no motion (the state copied) on vx and vy, and than the
    settle model calibrated on the touchdown set on every velocity."""
    rules, learned = learn_rules(LanderRules(), heuristic_data)
    assert learned["rules.touchdown_speed"] == math.inf and rules.touchdown_speed == math.inf
    assert learned["rules.leg_accuracy"] > 0.95 and learned["rules.contact_rows"] >= 20
    assert -0.06 < rules.floor < 0.0
    assert "rules.settle" in learned and rules.settle != LanderRules().settle
    _, test = held_out_test_set(LunarLanderSpec())
    frozen = LanderRules(settle=(0.0,) * 14, coulomb=0.0, stick=0.0, floor=-np.inf)
    own, still, calibrated = _settle_mse(rules, test), _settle_mse(frozen, test), _settle_mse(LanderRules(), test)
    assert np.all(own[2:4] < still[2:4])  # vx, vy (angvel on the legs: neither model beats the copy)
    velocities = [2, 3, 5]  # vx, vy, angvel
    assert np.all(own[velocities] < calibrated[velocities])  # than the prior fitted on 102,914 other real steps


def test_the_stiction_is_chosen_off_the_edge_where_replayed_landings_stop_resting():
    """Two landings that rest only from grid rows 3 and 4 on, each timed worse as the stiction
    grows (the surrogate rests them early): the least mean error is on the edge (row 4), a band
    of two rows moves the choice two rows up, and a run whose landings no candidate rests keeps 0."""
    never = 301.0
    rows = np.arange(len(STICK_GRID))
    errors = np.stack([np.where(rows >= 3, rows - 3.0, never), np.where(rows >= 4, 2.0 * (rows - 4), never)], axis=1)
    assert choose_stick(errors) == 4
    assert choose_stick(errors, band=2) == 6 and STICK_GRID[6] == pytest.approx(0.06)
    assert choose_stick(np.full((len(STICK_GRID), 3), never)) == 0


def test_own_data_fit_learns_the_scale_drops_the_fitted_priors_and_counts_none():
    cfg = compose_cfg(*OWN)
    plain = fit_dynamics(build_fit_job(compose_cfg("experiment=dyna_lunar_lander")))
    own = fit_dynamics(build_fit_job(cfg))
    assert plain.spec is plain.job.spec and plain.learned == {}
    assert prior_steps(plain.spec.declared_priors)["priors"] == 135_755
    kinds = {p.kind for p in own.spec.declared_priors}
    assert kinds == {"knowledge", "simulator_knowledge"}
    steps = prior_steps(own.spec.declared_priors)
    assert steps["priors"] == steps["simulator"] == steps["expert"] == 0
    # the pessimism's scale: the flight law's own residuals, close to the replay noise floor
    ratio = np.asarray(own.spec.task.uncertainty.scale) / np.sqrt(FLIGHT_NOISE_FLOOR)
    assert np.all((ratio > 0.8) & (ratio < 1.5)), ratio
    assert 0.0 < own.spec.task.uncertainty.free < 1.0
    assert own.spec.rules.touchdown_speed == math.inf and own.job.spec.rules.touchdown_speed == 3.05
    assert own.fidelity.metrics["learned/rules.leg_accuracy"] == own.learned["rules.leg_accuracy"]
    # the surrogate is built on the learned rules, and a swap moves it to another fit's
    venv = SurrogateVecEnv(own.model, own.spec, 2, seed=0, events=own.events)
    assert venv.surrogate.spec.rules == own.spec.rules
    venv.swap_model(plain.model, plain.events, seed=1, spec=plain.spec)
    assert venv.surrogate.spec.rules == LanderRules() and venv.surrogate.task is plain.spec.task


def test_a_tiny_own_data_dyna_run_counts_no_prior_and_logs_what_it_learned(store):
    cfg = compose_cfg(*OWN, f"tracking.uri={store}", "agent.n_envs=4", "agent.algo.n_steps=16", "agent.algo.batch_size=32",
                      "agent.algo.n_epochs=1", "rl.dyna.collect_per_round=300", "rl.dyna.first_round_steps=64",
                      "rl.dyna.surrogate_steps_per_round=64", "rl.dyna.max_rounds=2", "rl.dyna.eval_episodes=1",
                      "rl.dyna.final_episodes=1", "rl.dyna.audit_episodes=1", "rl.dyna.screen_max_steps=50",
                      "progress_bar=false")
    job = build_dyna_job(cfg, build_fit_job(cfg))
    with start_run(store, "sdrl-bench", "own-dyna", {"sdrl.kind": "dyna"}) as parent:
        recorder = DynaRunRecorder(parent, "sdrl-bench", "own-dyna", {"env": "lunar_lander"})
        outcome = run_dyna(job, job.check(), recorder)
        recorder.finish(outcome, job.fit.spec, None, "test")
    s = outcome.summary
    assert s["real_steps/priors"] == 0 and s["real_steps/expert"] == 0
    assert s["real_steps/all"] == s["real_steps/this_run"] + s["real_steps/tuning"]
    assert s["real_steps/tuning"] == 1_713_000
    r0, r1 = outcome.rounds[0].fit, outcome.rounds[1].fit
    assert r0.learned and r1.learned and len(r1.data) > len(r0.data)
    runs = search(store)
    children = runs[runs["tags.mlflow.parentRunId"] == parent.run_id].sort_values("tags.dyna.round")
    client = MlflowClient(store)
    first = children.iloc[0]
    assert first["metrics.real_steps/priors"] == 0
    learned = client.download_artifacts(first["run_id"], "own_data/learned.json")
    import json

    got = json.loads(open(learned).read())
    assert got["rules.touchdown_speed"] == "inf" and got["rules.floor"] == pytest.approx(r0.learned["rules.floor"])
    assert {i.dataset.name for i in client.get_run(first["run_id"]).inputs.dataset_inputs} >= {"lunar_lander-interface"}
