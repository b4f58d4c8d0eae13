"""The scripts (``benchmarks/``, ``studies/``, ``scripts/reproduce.py``) refuse a bad command line
in one line naming the flag, with argparse's exit status 2, before they fit, train, pretrain an
expert or write anything (``sdrl_bench.cli.args``): a count of 0, a core count above the
process's, a malformed or backwards seed list, an unknown arm, a file where a folder goes, a
tracking URI that is a folder, a git revision that does not exist. Each case runs the script in a
subprocess and takes a few seconds at most (the checks come before the heavy imports or work)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from helpers import ROOT

CORES = len(os.sched_getaffinity(0))
SEEDS = "seeds as 0-4, 0,2 or 0-4,20-24 are required"

CASES = [
    ("benchmarks/time_to_solve.py", ["--env", "mountain_car", "--seeds", "0-4,", "--arms", "b"],
     f"--seeds: {SEEDS}, got '0-4,'"),
    ("benchmarks/time_to_solve.py", ["--env", "mountain_car", "--arms", "bx"],
     "--arms: 'x' is not an arm (abcdeBDETKR)"),
    ("benchmarks/time_to_solve.py", ["--env", "lunar_lander", "--arms", "cK"],
     "--arms: lunar_lander has no compiled pack for arm K (paper_lunar_lander, fast_lunar_lander, "
     "fast_lunar_lander_terrain)"),
    ("benchmarks/time_to_solve.py", ["--env", "mountain_car", "--arms", "b", "--jobs", "0"],
     "--jobs: a whole number of parallel jobs other than 0 is required (1, 2, ...; -1 for every core), got 0"),
    ("benchmarks/time_to_solve.py", ["--env", "mountain_car", "--arms", "d", "--transitions", "0"],
     "--transitions: an integer >= 1 is required, got 0"),
    ("benchmarks/time_to_solve.py", ["--env", "mountain_car", "--arms", "b", "--workdir", "{file}"],
     "--workdir: {file} is a file, not a folder"),
    ("benchmarks/time_to_solve.py", ["--env", "mountain_car", "--arms", "b", "--uri", "sqlite:///{tmp}"],
     "--uri: {tmp} is a folder, not an SQLite file"),
    ("scripts/reproduce.py", ["--workdir", "{tmp}/w", "--seeds", "4-0"], f"--seeds: {SEEDS}, got '4-0'"),
    ("scripts/reproduce.py", ["--workdir", "{tmp}/w", "--jobs", "0"],
     "--jobs: a whole number of parallel jobs other than 0 is required (1, 2, ...; -1 for every core), got 0"),
    ("scripts/reproduce.py", ["--workdir", "{file}"], "--workdir: {file} is a file, not a folder"),
    ("scripts/reproduce.py", ["--workdir", "{tmp}/w", "--out", "{file}"],
     "--out: {file} is a file, not a folder; choose another folder or move it"),
    ("scripts/reproduce.py", ["--workdir", "{tmp}/w", "--out", "{tmp}", "--name", "a_file"],
     "--out/--name: {file} is a file, not a folder; choose another name or move it"),
    ("benchmarks/xla_opt_level.py", ["--cores", str(CORES + 1)],
     f"--cores: an integer from 1 to {CORES} (the cores this process may use) is required, got {CORES + 1}"),
    ("benchmarks/xla_opt_level.py", ["--levels", "3,,1"], "--levels: comma-separated levels 0 to 3 are required, got '3,,1'"),
    ("benchmarks/eval_interlude.py", ["--rounds", "0"], "--rounds: an integer >= 1 is required, got 0"),
    ("benchmarks/tracking_writes.py", ["--runs", "0"], "--runs: an integer >= 1 is required, got 0"),
    ("benchmarks/surrogate_vs_revision.py", ["--base", "no-such-revision"],
     "--base: 'no-such-revision' is not a commit of this checkout"),
    ("studies/compiled_recipe.py", ["--cores", "0"],
     f"--cores: an integer from 1 to {CORES} (the cores this process may use) is required, got 0"),
    ("studies/dyna_real_steps.py", ["--workdir", "{tmp}/w", "--arms", "real,pe"], "--arms: 'pe' is not an arm (real,sindy,nn)"),
    ("studies/compare_surrogates.py", ["--uri", "sqlite:///{tmp}"], "--uri: {tmp} is a folder, not an SQLite file"),
    ("studies/touchdown_set.py", ["--episodes", "0", "--out", "{tmp}/t.npz"], "--episodes: an integer >= 1 is required, got 0"),
    ("studies/replay_exactness.py", ["--episodes", "0"], "--episodes: an integer >= 1 is required, got 0"),
    ("studies/own_data_ablation.py", ["--seeds", "1,,2"], f"--seeds: {SEEDS}, got '1,,2'"),
    ("studies/own_data_ablation.py", ["--uri", "sqlite:///{tmp}"], "--uri: {tmp} is a folder, not an SQLite file"),
    ("studies/noise_floor.py", ["--out", "{tmp}/no/floor.json"], "--out: {tmp}/no/floor.json is a folder, or in a folder "
     "that does not exist"),
    ("studies/calibrate_lunar_lander.py", ["--model", "{tmp}/no.pkl"],
     "--model: {tmp}/no.pkl is not a file (a saved LunarLander model)"),
]


@pytest.mark.parametrize(("script", "args", "message"), CASES,
                         ids=[f"{s.split('/')[-1]} {' '.join(a)}" for s, a, _ in CASES])
def test_a_bad_flag_is_one_line_before_any_work(tmp_path, script, args, message):
    (tmp_path / "a_file").write_text("the user's")
    fill = {"tmp": str(tmp_path), "file": str(tmp_path / "a_file")}
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    proc = subprocess.run([sys.executable, str(ROOT / script), *(a.format(**fill) for a in args)], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert proc.stderr.strip().splitlines()[-1] == f"{script.split('/')[-1]}: error: {message.format(**fill)}"
    assert proc.stdout == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]  # nothing made, the user's file as it was
    assert (tmp_path / "a_file").read_text() == "the user's"
