"""What ``sdrl-bench`` loads before it answers: a bad command line is refused (cli.precheck) before
pysindy, torch or SB3 is imported, and a fit's command never imports torch or SB3 (they serve the
RL tasks alone). Checked on the modules a real process holds when it ends, not on its time."""

from __future__ import annotations

import json
import subprocess
import sys

HEAVY = ("pysindy", "torch", "stable_baselines3", "mlflow")

SCRIPT = """
import json, sys
heavy = json.loads(sys.argv[2])
sys.argv = ["sdrl-bench", *json.loads(sys.argv[1])]
from sdrl_bench.cli.main import main
try:
    main()
except SystemExit as exc:
    code = exc.code
else:
    code = 0
print("LOADED " + json.dumps({"code": code, "modules": [m for m in heavy if m in sys.modules]}))
"""


def run(args: list[str], cwd) -> dict:
    proc = subprocess.run([sys.executable, "-c", SCRIPT, json.dumps(args), json.dumps(HEAVY)], cwd=cwd,
                          capture_output=True, text=True, timeout=300)
    line = [x for x in proc.stdout.splitlines() if x.startswith("LOADED ")]
    assert line, proc.stdout[-2000:] + proc.stderr[-2000:]
    return {**json.loads(line[-1][len("LOADED "):]), "stderr": proc.stderr}


def test_a_bad_command_line_is_refused_before_the_heavy_libraries_load(tmp_path):
    got = run(["n_transition=5"], tmp_path)
    assert got["code"] == 2 and got["modules"] == []
    assert got["stderr"].strip().splitlines() == [
        "sdrl-bench: error: n_transition: unknown config key; did you mean n_transitions? "
        "(to add a new key: +n_transition=...)"]
    assert not (tmp_path / "mlruns").exists() and not (tmp_path / "outputs").exists()


def test_a_fit_command_does_not_import_torch_or_sb3(tmp_path):
    got = run(["env=mountain_car", "n_transitions=60", f"tracking.uri=sqlite:///{tmp_path / 'mlruns' / 'mlflow.db'}"],
              tmp_path)
    assert got["code"] == 0, got["stderr"][-2000:]
    assert got["modules"] == ["pysindy", "mlflow"]  # the fit and its run; nothing of the RL stack
    assert (tmp_path / "mlruns" / "mlflow.db").exists()
