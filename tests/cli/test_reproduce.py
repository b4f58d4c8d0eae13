"""scripts/reproduce.py: every command it runs composes and builds into a job (a typo in a key or
a value fails here, not an hour into a rebuild), every RL stage runs 5 seeds, and the NN
transfer sweeps come after the SINDy ones so their real arms are reused, not retrained."""

from __future__ import annotations

import itertools

import pytest

from helpers import compose_cfg, load_script
from sdrl_bench.cli.build import build_dyna_job, build_fit_job, build_transfer_job
from sdrl_bench.pipeline import check


def _script():
    return load_script("scripts/reproduce.py")


def _jobs(sweep: list[str]) -> list[list[str]]:
    """The sweep's jobs as override lists (the cartesian product of comma-separated values; the
    first seed only: seeds change no key)."""
    choices = []
    for o in sweep:
        k, _, v = o.partition("=")
        values = v.split(",") if k == "seed" or ("," in v and not v.startswith("[")) else [v]
        choices.append([f"{k}={x}" for x in (values[:1] if k == "seed" else values)])
    return [list(c) for c in itertools.product(*choices)]


def test_every_stage_command_builds_and_every_rl_sweep_has_five_seeds(tmp_path, monkeypatch) -> None:
    mod = _script()
    # the commands run in the workdir, where the experts stage has written the touchdown set by
    # then; a config that names it checks that the file exists (its contents are read only by a fit)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "mlruns" / "datasets").mkdir(parents=True)
    (tmp_path / "mlruns" / "datasets" / "lunar_lander-touchdowns-v1.npz").write_bytes(b"")
    stages = dict(mod.stages([0, 1, 2, 3, 4]))
    assert list(stages) == ["experts", "fits", "transfer", "fast", "dyna", "own", "pe", "cartpole", "search", "fidelity"]
    built = 0
    for name, commands in stages.items():
        for cmd in commands:
            if cmd[0] == "parallel:":  # the experts' warm-up fits
                for pack in cmd[1:]:
                    check(build_fit_job(compose_cfg(pack, "task=fit")))
                    built += 1
            if cmd[0] == "search:":  # the search app's config
                from sdrl_bench.cli.build import compose

                from omegaconf import OmegaConf

                cfg = compose(cmd[1:], config_name="search_app")
                OmegaConf.to_container(cfg, resolve=True)  # every interpolation resolves (the expert's progress_bar)
                assert cfg.search.name == "tpe"
                built += 1
            if cmd[0] != "-m":
                continue
            if name == "fidelity":  # a study pack sweeps its own cluster seeds (hydra.sweeper.params)
                from sdrl_bench.cli.fidelity_task import build_cluster

                cfg = compose_cfg(*cmd[1:])
                assert cfg.task == "fidelity" and not any(c.startswith("seed=") for c in cmd)
                build_cluster(cfg, given=cmd[1:])
                built += 1
                continue
            assert "seed=0,1,2,3,4" in cmd or "seed=5,6,7,8,9" in cmd or "seed=0,1,2,3,4,5,6,7,8,9" in cmd, (name, cmd)
            for job in _jobs(cmd[1:]):
                cfg = compose_cfg(*job)
                fit = build_fit_job(cfg)
                check(fit)  # the checks a run makes before collecting (a collector the env lacks, ...)
                if cfg.task == "train":
                    build_transfer_job(cfg, fit)
                elif cfg.task == "dyna":
                    build_dyna_job(cfg, fit)
                built += 1
    assert built >= 20
    transfer = [" ".join(c) for c in stages["transfer"]]
    for env in ("mountain_car", "lunar_lander"):
        sindy = next(i for i, c in enumerate(transfer) if f"paper_{env}" in c and "surrogate=sindy" in c)
        nn = next(i for i, c in enumerate(transfer) if f"paper_{env}" in c and "surrogate=nn" in c)
        assert sindy < nn  # the NN sweep finds the SINDy sweep's finished real arms and reuses them


def test_a_rerun_skips_finished_stages_and_keeps_the_cost_of_an_interrupted_one(tmp_path, monkeypatch) -> None:
    """Stage bookkeeping with the commands replaced by a recorder (the sweeps themselves resume
    through Hydra; tests/e2e covers that): a failed stage is recorded as interrupted with what it
    cost, the rerun runs it again from there and adds the cost, finished stages are skipped, and
    --only refuses a stage whose predecessors have not finished."""
    import json
    import sys
    import time
    import types

    mod = _script()
    ran: list[str] = []
    fail = {"transfer"}

    def fake(cmd, workdir, uri, jobs, log):
        stage = log.name.rsplit("/", 1)[-1][:-4]
        ran.append(stage)
        if stage in fail:
            raise SystemExit("reproduce: a command failed")
        return [" ".join(cmd)]

    monkeypatch.setattr(mod, "run_command", fake)
    clock = iter(range(0, 10**6, 100))  # every reading of the stage clock is 100 s after the last
    monkeypatch.setattr(mod, "time", types.SimpleNamespace(time=lambda: float(next(clock)), strftime=time.strftime,
                                                           gmtime=time.gmtime))
    monkeypatch.setattr(mod.subprocess, "run", lambda *a, **k: type("P", (), {"returncode": 0})())
    argv = ["reproduce.py", "--workdir", str(tmp_path), "--jobs", "2"]
    monkeypatch.setattr(sys, "argv", argv)
    with pytest.raises(SystemExit):
        mod.main()
    record = json.loads((tmp_path / "rebuild.json").read_text())
    assert [(k, v["status"], v["attempts"]) for k, v in record["stages"].items()] == [
        ("experts", "finished", 1), ("fits", "finished", 1), ("transfer", "interrupted", 1)]
    assert record["stages"]["fits"]["jobs"] == 2 and record["stages"]["fits"]["argv"][0].startswith("-m env=mountain_car")
    assert record["stages"]["transfer"]["wall_seconds"] == 100.0  # the failed attempt: start, then its record
    fail.clear()
    ran.clear()
    assert mod.main() == 0
    record = json.loads((tmp_path / "rebuild.json").read_text())
    assert set(ran) == {"transfer", "fast", "dyna", "own", "pe", "cartpole", "search", "fidelity"}  # experts and fits were skipped
    # the rerun's 100 s added to the failed attempt's 100 s, not in place of them
    assert record["stages"]["transfer"]["attempts"] == 2 and record["stages"]["transfer"]["wall_seconds"] == 200.0
    assert all(v["status"] == "finished" for v in record["stages"].values())
    monkeypatch.setattr(sys, "argv", ["reproduce.py", "--workdir", str(tmp_path / "fresh"), "--only", "fits"])
    with pytest.raises(SystemExit, match="needs experts finished first"):
        mod.main()
