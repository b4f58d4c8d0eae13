"""Every real step counted by purpose (rl/accounting.py; definitions: docs/accounting.md): the
columns add up from the per-purpose metrics of real runs, against a real env's own step counter;
adding a prior changes a run's accounting; a prior's missing file is one line; two runs of the same
seed count the same real steps."""

from __future__ import annotations

import pytest
from mlflow.tracking import MlflowClient

from helpers import compose_cfg, search
from sdrl_bench import ConfigError
from sdrl_bench.cli.build import build_dyna_job, build_fit_job
from sdrl_bench.cli.train import run_train
from sdrl_bench.rl.accounting import OWN
from sdrl_bench.rl.dyna import run_dyna

TINY_SAC = ("rl.surrogate_steps=64", "rl.real_steps=64", "rl.eval_every=32", "rl.eval_episodes=2", "rl.final_episodes=2",
            "agent.algo.train_freq=16", "agent.algo.gradient_steps=1", "agent.algo.batch_size=32",
            "agent.algo.policy_kwargs.net_arch=[16]", "rl.reuse_real_arm=false", "progress_bar=false")


def test_the_columns_add_up_and_match_the_real_envs_own_count(store):
    """A transfer run on a MountainCar that counts its own steps: per arm, this run's data = model
    data + training + selection, all = this run's + priors + expert + tuning; and every step the
    env took is one of the purposes (monitoring and judging included)."""
    import counting_env

    cfg = compose_cfg("experiment=quick_mountain_car", f"tracking.uri={store}", "collector=heuristic",
                      f"+env.spec.gym_id=counting_env:{counting_env.ENV_ID}", *TINY_SAC)
    before = counting_env.CountingMountainCar.steps
    summary = run_train(cfg, build_fit_job(cfg), None)
    counted = counting_env.CountingMountainCar.steps - before
    total = 0.0
    for arm in ("surrogate", "real"):
        m = {k[len(arm) + 1:]: v for k, v in summary.items() if k.startswith(f"{arm}/")}
        assert m["real_steps/this_run"] == sum(m[f"real_steps/{p}"] for p in OWN)
        assert m["real_steps/all"] == (m["real_steps/this_run"] + m["real_steps/priors"] + m["real_steps/expert"]
                                       + m["real_steps/tuning"])
        assert m["real_steps/model_data"] == m["real_transitions_model"] and m["real_steps/train"] == m["real_transitions_train"]
        assert m["real_steps/selection"] == 0 and m["real_steps/monitor"] == m["eval_steps"] > 0  # no stop rule
        total += m["real_steps/this_run"] + m["real_steps/monitor"] + m["real_steps/judge"]
    assert summary["surrogate/real_steps/model_data"] == 75 and summary["real/real_steps/train"] >= 64
    assert summary["surrogate/real_steps/judge"] > summary["surrogate/final_eval_steps"]  # + the held-out set
    assert total == counted  # every step the env took has a purpose, none twice
    row = search(store).iloc[0]
    assert row["metrics.surrogate/real_steps/all"] == summary["surrogate/real_steps/all"]
    # the fit's own accounting is under fit/: the run's only headlines are its arms'
    stored = MlflowClient(store).get_run(row["run_id"]).data.metrics
    assert stored["fit/real_steps/model_data"] == stored["fit/real_steps/this_run"] == 75
    assert not [k for k in stored if k.startswith(("real_steps/", "real_resets/"))]


def test_a_stop_rule_makes_the_curve_a_selection(store):
    cfg = compose_cfg("experiment=quick_mountain_car", f"tracking.uri={store}", "collector=heuristic",
                      "rl.arms=[real]", "rl.stop_when_solved=true", *TINY_SAC)
    summary = run_train(cfg, build_fit_job(cfg), None)
    assert summary["real/real_steps/selection"] == summary["real/eval_steps"] > 0
    assert summary["real/real_steps/this_run"] == summary["real/real_steps/train"] + summary["real/real_steps/selection"]


def test_adding_a_prior_changes_the_accounting_and_a_missing_prior_file_is_one_line(store, tmp_path):
    """The same fit with and without a declared fitted prior: all real steps grow by its steps,
    this run's data does not; a prior of a simulator counts its real steps and its replays apart."""
    from sdrl_bench.cli.main import run_fit

    prior = "{name: my-calibration, kind: fitted, sets: [sindy.threshold], source: my study, real_steps: 5000}"
    replay = "{name: my-floor, kind: simulator, sets: [noise], source: replays, real_steps: 300, simulator_steps: 9000}"
    plain = run_fit(compose_cfg(f"tracking.uri={store}", "collector=heuristic"))
    with_prior = run_fit(compose_cfg(f"tracking.uri={store}", "collector=heuristic", f"+env.spec.priors=[{prior},{replay}]"))
    m0, m1 = plain.fidelity.metrics, with_prior.fidelity.metrics
    runs = search(store).sort_values("start_time")
    a, b = runs.iloc[0], runs.iloc[1]
    assert a["metrics.real_steps/model_data"] == b["metrics.real_steps/model_data"] == 75
    assert a["metrics.real_steps/priors"] == 0 and b["metrics.real_steps/priors"] == 5300
    assert b["metrics.real_steps/all"] - a["metrics.real_steps/all"] == 5300
    assert b["metrics.real_steps/simulator"] == 9000 and b["metrics.real_steps/prior/my-calibration"] == 5000
    assert m0.keys() == m1.keys()
    from mlflow.tracking import MlflowClient

    inputs = {i.dataset.name: i.tags[0].value for i in MlflowClient(store).get_run(b["run_id"]).inputs.dataset_inputs}
    assert inputs["my-calibration"] == "prior:fitted" and inputs["my-floor"] == "prior:simulator"
    with pytest.raises(ConfigError, match=r"^env.spec.priors\[0\].file: no such file: /no/such.npz$"):
        build_fit_job(compose_cfg("+env.spec.priors=[{name: p, kind: fitted, sets: [x], source: s, real_steps: 1, "
                                  "file: /no/such.npz}]"))
    with pytest.raises(ConfigError, match=r"^env.spec.priors\[0\].real_steps: a fitted prior names"):
        build_fit_job(compose_cfg("+env.spec.priors=[{name: p, kind: fitted, sets: [x], source: s}]"))


def test_lunar_landers_priors_count_once_with_their_expert():
    """LunarLander's declared priors: the contact calibration, the touchdown set (and the expert
    behind 51 of its episodes, counted once even when the collector is that expert), the noise
    floor (its real test set, its replays apart), the pessimism's band; knowledge counts nothing."""
    from sdrl_bench.rl.accounting import headline

    spec = build_fit_job(compose_cfg("env=lunar_lander")).spec
    kinds = {p.name: p.kind for p in spec.declared_priors}
    assert kinds["box2d-sleep-and-friction"] == "simulator_knowledge" and kinds["lunar_lander-interface"] == "knowledge"
    m = headline({"model_data": 1000}, spec.declared_priors, ["lunar_lander-ppo-n1000000"])
    assert m["real_steps/priors"] == 28000 + 102914 + 3841 + 1000
    assert m["real_steps/expert"] == 1_000_000 and m["real_steps/simulator"] == 1_274_197
    assert m["real_steps/all"] == 1000 + 28000 + 102914 + 3841 + 1000 + 1_000_000


def test_two_dyna_runs_of_one_seed_count_the_same_real_steps(store):
    tiny = ("experiment=dyna_mountain_car", "agent.n_envs=4", "agent.algo.n_steps=16", "agent.algo.batch_size=32",
            "agent.algo.n_epochs=1", "n_transitions=30", "rl.dyna.collect_per_round=20", "rl.dyna.first_round_steps=64",
            "rl.dyna.surrogate_steps_per_round=64", "rl.dyna.max_rounds=2", "rl.dyna.eval_episodes=2",
            "rl.dyna.final_episodes=2", "rl.dyna.audit_episodes=2", "progress_bar=false", "seed=3")
    outs = []
    for _ in range(2):
        cfg = compose_cfg(*tiny, f"tracking.uri={store}")
        job = build_dyna_job(cfg, build_fit_job(cfg))
        outs.append(run_dyna(job, job.check()).summary)
    steps = [{k: v for k, v in o.items() if k.startswith(("real_steps", "real_transitions", "real_resets"))} for o in outs]
    assert steps[0] == steps[1] and steps[0]["real_steps/this_run"] == steps[0]["real_transitions_total"]
    assert steps[0]["real_steps/tuning"] == 711_000  # the fast recipe's declared tuning
    assert outs[0]["judged_solved"] in (0.0, 1.0)


def test_an_nn_surrogates_tuned_defaults_count_as_tuning_in_the_surrogate_arm_only(store):
    """The MLP's defaults were chosen on other real data (conf/surrogate/nn.yaml): a fit with them
    counts those steps as tuning, as does the surrogate arm of a transfer run; the real arm does
    not use the model and does not; the probabilistic ensemble (nothing tuned) counts none."""
    from sdrl_bench.cli.main import run_fit

    nn = run_fit(compose_cfg("surrogate=nn", "surrogate.model.max_steps=50", f"tracking.uri={store}"))
    from sdrl_bench.tracking.fit import fit_metrics

    m = fit_metrics(nn)
    assert m["real_steps/tuning"] == 6114 and m["real_steps/all"] == m["real_steps/this_run"] + 6114
    assert fit_metrics(run_fit(compose_cfg("surrogate=pe", "surrogate.model.max_steps=50",
                                           f"tracking.uri={store}")))["real_steps/tuning"] == 0
    cfg = compose_cfg("experiment=quick_mountain_car", f"tracking.uri={store}", "collector=heuristic", "surrogate=nn",
                      "surrogate.model.max_steps=50", *TINY_SAC)
    summary = run_train(cfg, build_fit_job(cfg), None)
    assert summary["surrogate/real_steps/tuning"] == 6114 and summary["real/real_steps/tuning"] == 0
    with pytest.raises(ConfigError, match=r"surrogate.tuning_real_steps must be >= 0, got -1"):
        build_fit_job(compose_cfg("surrogate=nn", "surrogate.tuning_real_steps=-1"))
