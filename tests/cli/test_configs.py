"""Every config group option composes, and every combination instantiates into a FitJob."""

from __future__ import annotations

import importlib.util
import itertools
from importlib import resources

import pytest

from helpers import compose_cfg
from sdrl_bench import ConfigError
from sdrl_bench.cli.build import build_fit_job
from sdrl_bench.pipeline import check


def options(group: str) -> list[str]:
    """The options Hydra finds for a group in the package's configs (pkg://sdrl_bench.conf)."""
    return sorted(p.name[: -len(".yaml")] for p in resources.files("sdrl_bench.conf").joinpath(group).iterdir()
                  if p.name.endswith(".yaml"))


def test_groups_have_the_expected_options():
    assert {"mountain_car", "lunar_lander", "lunar_lander_continuous"} <= set(options("env"))
    assert {"polynomial", "trig", "poly_trig", "rational"} <= set(options("library"))
    assert {"stlsq", "sr3", "ensemble"} <= set(options("optimizer"))
    assert {"random", "heuristic"} <= set(options("collector"))
    assert "sindy" in options("surrogate")


@pytest.mark.parametrize(
    "env,library,optimizer",
    list(itertools.product(options("env"), options("library"), options("optimizer"))),
)
def test_every_combination_instantiates(env, library, optimizer):
    collector = "random" if env in ("pendulum", "cartpole_swingup", "cartpole_swingup_circle") else "heuristic"  # no heuristic policy
    cfg = compose_cfg(f"env={env}", f"library={library}", f"optimizer={optimizer}", f"collector={collector}")
    job = build_fit_job(cfg)
    # a per-equation library names its env's states (CartPole-v1's are the swing-up's: x, th, xdot, thdot, force)
    home = {"lunar_lander_flight": ("lunar_lander",), "pendulum_law": ("pendulum",),
            "cartpole_swingup_law": ("cartpole_swingup", "cartpole"),
            "cartpole_swingup_affine": ("cartpole_swingup_circle",)}.get(library)
    if library in ("trig", "poly_trig") and not cfg.env.trig_inputs:  # an env with no angle state (cos, sin observed)
        with pytest.raises(ConfigError, match=r"^library.parts\[\d\].inputs: selects no input for this env"):
            check(job)
        return
    if home is not None and env not in home:
        with pytest.raises(ConfigError, match=r"^library.equations(.\w+(\[\d+\])?)?: (not a regressed state|unknown name|no equation for)"):
            check(job)
        return
    library_obj, data = check(job)  # validates budgets against the library size, no env steps
    assert data is None
    assert job.spec.name == env
    assert job.names == {"env": env, "collector": collector, "library": library,
                         "optimizer": optimizer, "surrogate": "sindy"}
    assert type(job.optimizer).__name__ in {"STLSQ", "SR3", "EnsembleOptimizer"}
    assert len(library_obj.libraries) == len(cfg.library.parts)


def test_each_env_has_its_default_library_and_the_command_line_wins():
    """LunarLander defaults to its per-equation flight law (its env config overrides the library
    group), the continuous one to polynomials; MountainCar keeps poly_trig; an explicit library= always wins."""
    defaults = {env: build_fit_job(compose_cfg(f"env={env}")) for env in ("mountain_car", "lunar_lander", "lunar_lander_continuous")}
    assert {env: job.names["library"] for env, job in defaults.items()} == {
        "mountain_car": "poly_trig", "lunar_lander": "lunar_lander_flight", "lunar_lander_continuous": "polynomial"}
    assert len(check(defaults["lunar_lander_continuous"])[0].libraries) == 1  # no trigonometric part
    assert defaults["lunar_lander"].spec.fit_regime == "flight"
    assert build_fit_job(compose_cfg("env=lunar_lander", "library=poly_trig")).names["library"] == "poly_trig"
    assert build_fit_job(compose_cfg("experiment=paper_mountain_car")).names["library"] == "poly_trig"


def test_lunar_lander_spec_encodes_actions_one_hot():
    job = build_fit_job(compose_cfg("env=lunar_lander"))
    assert job.spec.control_names == ("leg_left", "leg_right", "a_noop", "a_left", "a_main", "a_right")
    assert job.spec.encode_actions([[2], [0]]).tolist() == [[0, 0, 1, 0], [1, 0, 0, 0]]
    cont = build_fit_job(compose_cfg("env=lunar_lander_continuous")).spec
    assert cont.control_names == ("leg_left", "leg_right", "main", "lateral")
    assert cont.make_env().action_space.shape == (2,)


def test_budgets_shrink_by_override():
    job = build_fit_job(compose_cfg("n_transitions=40", "collector.epsilon=0.5", "seed=7"))
    assert (job.n_transitions, job.epsilon, job.seed) == (40, 0.5, 7)


def test_pendulum_needs_no_code_but_has_no_heuristic():
    with pytest.raises(ConfigError, match="collector: env 'pendulum' has no heuristic"):
        check(build_fit_job(compose_cfg("env=pendulum")))


@pytest.mark.parametrize("pack", options("experiment"))
def test_every_experiment_pack_composes_and_validates(pack):
    from sdrl_bench.cli.train import build_transfer_job

    from sdrl_bench.cli.build import build_dyna_job, real_arm_key

    cfg = compose_cfg(f"experiment={pack}")
    assert cfg.task in ("train", "dyna", "fidelity")
    if cfg.task == "fidelity":  # a study pack: its first cluster builds; the compiled agent needs the [jax] extra
        from sdrl_bench.cli.fidelity_task import build_cluster

        cluster, axes, _ = build_cluster(cfg, given=[f"experiment={pack}"])
        assert axes["n_clusters"] * len(cluster.variants) >= 40 and cluster.agent.name == "ppo_jax"
        if importlib.util.find_spec("jax") is not None:
            cluster.check()
        else:
            with pytest.raises(ConfigError, match=r"\[jax\]"):
                cluster.check()
        return
    job = build_transfer_job(cfg, build_fit_job(cfg))
    assert job.agent.name in {"sac", "ppo", "ppo_fast", "ppo_jax"} and set(job.arms) == set(cfg.rl.arms) and job.arms
    if job.agent.name == "ppo_jax" and importlib.util.find_spec("jax") is None:  # a compiled pack, without the extra
        with pytest.raises(ConfigError, match=r"\[jax\]"):
            job.check()
        return
    job.check()  # agent fits the action space, budgets positive; no expert is trained here
    if cfg.task == "dyna":  # a Dyna pack validates, and finds the real arm of its fast pack (same key)
        build_dyna_job(cfg, build_fit_job(cfg)).check()
        base = pack.replace("dyna_", "fast_").removesuffix("_own")  # a variant: its base's
        # without a fast pack, its real arm is the pack's own recipe run in the real env
        fast = (compose_cfg(f"experiment={base}") if base in options("experiment")
                else compose_cfg(f"experiment={pack}", "task=train", "rl.arms=[real]"))
        assert real_arm_key(cfg) == real_arm_key(fast)


def test_paper_packs_use_the_papers_budgets():
    mc = compose_cfg("experiment=paper_mountain_car")
    ll = compose_cfg("experiment=paper_lunar_lander")
    assert (mc.n_transitions, mc.rl.surrogate_steps, mc.rl.real_steps, mc.agent.name) == (75, 65000, 100000, "sac")
    assert (ll.n_transitions, ll.rl.surrogate_steps, ll.rl.real_steps, ll.agent.name) == (1000, 800000, 1000000, "ppo")
    assert mc.collector.name == ll.collector.name == "expert" and mc.collector.epsilon == 0.2


def test_help_names_the_app_and_says_which_groups_other_commands_read(tmp_path):
    """``sdrl-bench --help`` (a real process): our header and example commands, every group Hydra
    finds, and a line saying that ``search`` and ``reference`` are read by the other commands."""
    from helpers import run_cli

    out = run_cli("--help", cwd=tmp_path, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("sdrl-bench: collect real transitions")
    assert "sdrl-bench experiment=quick_mountain_car" in out.stdout
    for group in ("agent", "env", "experiment", "library", "search", "reference"):
        assert f"\n{group}: " in out.stdout
    assert "search is read by sdrl-bench-search and reference by sdrl-bench-report" in out.stdout
    assert not any(tmp_path.iterdir())  # help makes no store, no run folder
    search = run_cli("--help", cwd=tmp_path, timeout=120, module="sdrl_bench.cli.search")
    assert search.returncode == 0, search.stderr
    assert search.stdout.startswith("sdrl-bench-search: an Optuna study")
    assert "experiment holds sdrl-bench's packs" in search.stdout
    assert not any(tmp_path.iterdir())
