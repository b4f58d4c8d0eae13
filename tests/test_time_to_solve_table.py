"""benchmarks/time_to_solve.py's table arithmetic: the medians over seeds with unsolved and
unjudged seeds counted as infinitely slow, the compile taken out, and the compile replaced by the
warm-up's cold one (``wall_judged_cold``)."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import pytest

PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "time_to_solve.py"


@pytest.fixture(scope="module")
def tts():
    spec = importlib.util.spec_from_file_location("time_to_solve", PATH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


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
    assert tts.WARM_SEED not in tts.parse_seeds("0-4,20-29") and f"seed={tts.WARM_SEED}" in over
    assert [o for o in over if o.startswith("rl.stop_when_solved")] == ["rl.stop_when_solved=false"]  # collect skips it
    assert {"experiment=fast_lunar_lander_terrain", "agent=ppo_jax", "resume=false", "rl.surrogate_steps=1",
            "n_transitions=3000", "collector=expert"} <= set(over)
