"""studies/compiled_ppo_parity.py resumes: each seed's returns go to its results file as the seed
ends, and a rerun of the same command trains only the seeds not there (the compiled SAC against
SB3's, tiny budgets, real training in MountainCar's surrogate)."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest

from helpers import ROOT, load_script

pytest.importorskip("jax")
pytest.importorskip("optax")
pytestmark = pytest.mark.jax

SCRIPT = str(ROOT / "studies" / "compiled_ppo_parity.py")


def study(tmp_path, seeds: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, SCRIPT, "--env", "mountain_car_sac", "--steps", "64", "--episodes", "1",
           "--seeds", seeds, "--results", str(tmp_path / "parity.jsonl")]
    return subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600)


def test_a_rerun_adopts_the_stored_seeds_and_trains_the_rest(tmp_path):
    first = study(tmp_path, "0-1")
    assert first.returncode == 0, first.stderr[-2000:]
    lines = [json.loads(x) for x in (tmp_path / "parity.jsonl").read_text().splitlines()]
    assert sorted(rec["seed"] for rec in lines) == [0, 1]
    for rec in lines:
        assert rec["env"] == "mountain_car_sac" and rec["steps"] == 64 and rec["episodes"] == 1 and rec["host"]
        assert set(rec["returns"]) == {"SB3 sac", "sac_jax"} and all(math.isfinite(v) for v in rec["returns"].values())
    assert "seed 0 (trained)" in first.stdout and "seed 1 (trained)" in first.stdout
    with (tmp_path / "parity.jsonl").open("a") as f:
        f.write('{"env": "mountain_car_sac", "steps": 64, "epis')  # a line cut short by a kill
    again = study(tmp_path, "0-2")
    assert again.returncode == 0, again.stderr[-2000:]
    assert "2 seed(s) from" in again.stdout and "training 1" in again.stdout
    assert "seed 2 (trained)" in again.stdout and "seed 0 (trained)" not in again.stdout
    stored = {rec["seed"]: rec["returns"] for rec in lines}
    assert f"seed 0: SB3 sac {stored[0]['SB3 sac']:.1f}, sac_jax {stored[0]['sac_jax']:.1f}" in again.stdout
    assert "Mann-Whitney U: p =" in again.stdout and "IQM difference, sac_jax - SB3 sac: " in again.stdout
    key = {"env": "mountain_car_sac", "steps": 64, "episodes": 1}
    assert sorted(load_script("studies/compiled_ppo_parity.py").stored(tmp_path / "parity.jsonl", key)) == [0, 1, 2]


def test_only_lines_of_the_same_command_are_adopted(tmp_path):
    mod = load_script("studies/compiled_ppo_parity.py")
    path = tmp_path / "r.jsonl"
    key = {"env": "mountain_car_sac", "steps": 64, "episodes": 1}
    mod.append(path, {**key, "seed": 0, "returns": {"a": 1.0}, "host": "h"})
    mod.append(path, {**key, "steps": 128, "seed": 1, "returns": {"a": 2.0}, "host": "h"})
    mod.append(path, {**key, "episodes": 20, "seed": 2, "returns": {"a": 3.0}, "host": "h"})
    with path.open("a") as f:
        f.write("not json\n")
    assert mod.stored(path, key) == {0: {"a": 1.0}}
    assert mod.stored(path, {**key, "steps": 128}) == {1: {"a": 2.0}}
    assert mod.stored(tmp_path / "none.jsonl", key) == {}


def test_a_line_after_a_cut_line_is_its_own(tmp_path):
    mod = load_script("studies/compiled_ppo_parity.py")
    path = tmp_path / "r.jsonl"
    key = {"env": "mountain_car_sac", "steps": 64, "episodes": 1}
    mod.append(path, {**key, "seed": 0, "returns": {"a": 1.0}, "host": "h"})
    with path.open("a") as f:
        f.write('{"env": "mountain_car_sac", "ste')  # a kill mid-line
    mod.append(path, {**key, "seed": 1, "returns": {"a": 2.0}, "host": "h"})
    assert mod.stored(path, key) == {0: {"a": 1.0}, 1: {"a": 2.0}}
    assert len(path.read_text().splitlines()) == 3 and path.read_text().endswith("\n")


def test_the_iqm_difference_and_its_bootstrap_interval():
    mod = load_script("studies/compiled_ppo_parity.py")
    assert mod.iqm_gap([0.0] * 4, [1.0] * 4) == 1.0 and mod.iqm_gap_ci([0.0] * 4, [1.0] * 4) == "[1.0, 1.0]"
    a, b = [-100.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 900.0], [15.0, 25.0, 35.0, 45.0]
    assert mod.iqm_gap(a, b) == 30.0 - 35.0  # the tails trimmed: IQM(a) of 20..50, IQM(b) of 25, 35
    lo, hi = (float(x) for x in mod.iqm_gap_ci(a, b).strip("[]").split(", "))
    assert lo < -5.0 < hi  # around the estimate
    assert mod.iqm_gap_ci(a, b) == mod.iqm_gap_ci(a, b)  # seeded: the same interval each time
