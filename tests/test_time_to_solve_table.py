"""benchmarks/time_to_solve.py's table arithmetic: the medians over seeds with unsolved and
unjudged seeds counted as infinitely slow, the compile taken out, and the compile replaced by the
warm-up's cold one (``wall_judged_cold``)."""

from __future__ import annotations

import math

import pytest

from helpers import load_script


@pytest.fixture(scope="module")
def tts():
    return load_script("benchmarks/time_to_solve.py")


def run(wall: float | None, compile_s: float, judged: bool = True, hits: int = 3) -> dict[str, float]:
    m = {"compile_wall_seconds": compile_s, "compile_programs": 3.0, "compile_cache_hits": float(hits),
         "judged_solved": float(judged), "final_return_mean": 200.0}
    if wall is not None:
        m["solved_wall_seconds"] = wall
    return m


def test_the_judged_medians_with_and_without_the_compile_and_with_a_cold_one(tts):
    runs = {0: run(3.0, 0.7), 1: run(2.0, 0.6, judged=False), 2: run(4.0, 0.8), 3: run(None, 0.7), 4: run(5.0, 0.7)}
    row = tts.arm_row(runs, [0, 1, 2, 3, 4], cold_compile=4.5)
    assert (row["solved"], row["judged"]) == (4, 3)
    assert row["wall"] == 4.0  # 2, 3, 4, 5 and one unsolved (inf): the third of five
    assert row["wall_judged"] == 5.0  # seed 1 unjudged: 3, 4, 5, inf, inf
    assert row["wall_judged_ex_compile"] == pytest.approx(4.3)  # 2.3, 3.2, 4.3, inf, inf
    assert row["wall_judged_cold"] == pytest.approx(5.0 - 0.7 + 4.5)  # each run's compile the cold one
    assert (row["programs"], row["cache_hits"]) == (3.0, 3.0)
    assert math.isnan(tts.arm_row(runs, [0, 1, 2, 3, 4])["wall_judged_cold"])  # no warm-up: no cold figure


def test_a_warm_up_is_one_short_unstopped_run_on_a_seed_outside_the_tables(tts, monkeypatch, tmp_path):
    calls = []
    monkeypatch.setattr(tts, "cli", lambda workdir, overrides, multirun=True: calls.append(overrides))
    tts.warm_up("lunar_lander", "T", tmp_path, "sqlite:///x.db", 3000)
    (over,) = calls
    assert f"seed={tts.WARM_SEED}" in over
    assert [o for o in over if o.startswith("rl.stop_when_solved")] == ["rl.stop_when_solved=false"]  # collect skips it
    assert {"experiment=fast_lunar_lander_terrain", "agent=ppo_jax", "resume=false", "rl.surrogate_steps=1",
            "rl.real_steps=1", "rl.final_episodes=1", "n_transitions=3000", "collector=expert"} <= set(over)


def stored(seed: int, arm: str, stopped: bool, **metrics: float) -> dict:
    """A finished transfer run as ``find_runs`` gives it: (t') for the surrogate arm, (b') for the real one."""
    surrogate = arm == "surrogate"
    params = {"rl.stop_when_solved": str(stopped), "rl.eval_episodes": "10", "rl.confirm_episodes": "20",
              **({"collector.name": "expert", "n_transitions": "3000"} if surrogate else {})}
    tags = {"env": "lunar_lander", "agent": "ppo_jax", "arms": arm, "seed": str(seed),
            "sdrl.experiment": "fast_lunar_lander_terrain" if surrogate else "fast_lunar_lander"}
    return {"run_id": f"{arm}-{seed}-{len(metrics)}", "status": "FINISHED", "tags": tags, "params": params,
            "metrics": {f"{arm}/{k}": v for k, v in metrics.items()}}


def test_the_tables_leave_the_warm_ups_out_and_take_a_cold_one_as_the_cold_compile(tts, monkeypatch):
    w = tts.WARM_SEED
    runs = [stored(w, "surrogate", False, compile_wall_seconds=4.8, compile_cache_hits=0.0),  # cold: the figure
            stored(w, "real", False, compile_wall_seconds=0.2, compile_cache_hits=1.0),  # found its update cached
            stored(0, "surrogate", True, solved_wall_seconds=3.7, compile_wall_seconds=0.7, compile_cache_hits=3.0),
            stored(0, "real", True, solved_wall_seconds=15.0, compile_wall_seconds=0.2, compile_cache_hits=1.0),
            stored(w, "surrogate", False, compile_wall_seconds=0.6, compile_cache_hits=3.0)]  # a rerun's, warm: not it
    monkeypatch.setattr(tts, "find_runs", lambda *a, **k: runs)
    timed = tts.collect("sqlite:///x.db", "lunar_lander", 3000, confirm=20)
    assert sorted(timed["T"]) == [0] and sorted(timed["B"]) == [0]  # no warm-up in the tables
    cold = tts.collect("sqlite:///x.db", "lunar_lander", 3000, warm_ups=True)
    assert cold["T"][w]["compile_wall_seconds"] == 4.8 and cold["B"] == {}  # only a warm-up with no cache hit


def mountain_car_run(seed: int, arm: str, pack: str, wall: float, compile_s: float = 0.1) -> dict:
    """A finished MountainCar run of ``pack``, stopped when solved and judged solved (the surrogate arm's model fitted on 75 expert transitions)."""
    r = stored(seed, arm, True, solved_wall_seconds=wall, compile_wall_seconds=compile_s, judged_solved=1.0)
    r["tags"].update(env="mountain_car", **{"sdrl.experiment": pack})
    if arm == "surrogate":
        r["params"].update({"collector.name": "expert", "n_transitions": "75"})
    return r


def test_the_compiled_packs_arms_run_and_read_back_as_their_own(tts, monkeypatch):
    """(k') and (r'): the env's compiled pack under the compiled PPO, in the surrogate (on the
    expert's data, as (d')) and in real envs; the store's runs of that pack are theirs, not (d')'s
    or (b')'s, and the report sets (k') against its own control and the fastest real one."""
    over = tts.arm_overrides("mountain_car", "K", [0, 1], "sqlite:///x.db", 1, confirm=20)
    assert {"experiment=compiled_mountain_car", "agent=ppo_jax", "rl.arms=[surrogate]", "collector=expert",
            "rl.confirm_episodes=20", "seed=0,1"} <= set(over)
    real = tts.arm_overrides("mountain_car", "R", [0], "sqlite:///x.db", 1)
    assert {"experiment=compiled_mountain_car", "agent=ppo_jax", "rl.arms=[real]"} <= set(real)
    assert not any(o.startswith("collector=") for o in real)
    with pytest.raises(SystemExit, match="no compiled pack"):
        tts.arm_overrides("lunar_lander", "K", [0], "sqlite:///x.db", 1)

    runs = [mountain_car_run(0, "surrogate", "compiled_mountain_car", 0.4), mountain_car_run(0, "real", "compiled_mountain_car", 1.5),
            mountain_car_run(0, "surrogate", "fast_mountain_car", 0.7), mountain_car_run(0, "real", "fast_mountain_car", 2.5)]
    monkeypatch.setattr(tts, "find_runs", lambda *a, **k: runs)
    got = tts.collect("sqlite:///x.db", "mountain_car", 75, confirm=20)
    walls = {k: v[0]["solved_wall_seconds"] for k, v in got.items() if v}
    assert walls == {"K": 0.4, "R": 1.5, "D": 0.7, "B": 2.5}


def test_the_report_sets_each_compiled_arm_beside_the_fastest_real_control(tts, monkeypatch, capsys):
    runs = [mountain_car_run(0, "surrogate", "compiled_mountain_car", 0.4), mountain_car_run(0, "real", "compiled_mountain_car", 1.5),
            mountain_car_run(0, "real", "fast_mountain_car", 2.5, compile_s=0.2)]
    monkeypatch.setattr(tts, "find_runs", lambda *a, **k: runs)
    tts.report("sqlite:///x.db", "mountain_car", [0], None, 75, confirm=20)
    out = capsys.readouterr().out
    assert "(k')/the fastest real control = 0.267 (of (r')); 0.214 (of (r'), compile excluded)" in out
    assert "(k')/(r') = 0.267 (compile excluded: 0.214)" in out
