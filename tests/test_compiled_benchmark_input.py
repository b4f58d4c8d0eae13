"""benchmarks/compiled_ppo.py refuses an unknown ``--recipes`` name in one line (argparse's exit
status 2) before it fits a surrogate or starts jax: the names are the env's own, with spaces."""

from __future__ import annotations

import subprocess
import sys

from helpers import ROOT


def test_an_unknown_recipe_is_refused_before_the_fit(tmp_path):
    cmd = [sys.executable, str(ROOT / "benchmarks" / "compiled_ppo.py"), "--env", "mountain_car",
           "--recipes", "fast pack", "fast"]
    proc = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2
    last = proc.stderr.strip().splitlines()[-1]
    assert last == ("compiled_ppo.py: error: --recipes: 'fast' is not one of mountain_car's recipes "
                    "('fast pack', 'compiled pack')")
    assert "fit:" not in proc.stdout
    assert not list(tmp_path.iterdir())  # nothing written: no mlruns, no jax cache
