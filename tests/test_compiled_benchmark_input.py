"""benchmarks/compiled_ppo.py refuses an unknown ``--recipes`` name in one line (argparse's exit
status 2) before it fits a surrogate or starts jax: the names are the env's own, with spaces. Its
paired ratio gives a CI only from enough pairs."""

from __future__ import annotations

import re
import subprocess
import sys

from helpers import ROOT, load_script


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


def test_the_pairs_ci_is_printed_from_five_pairs_and_brackets_their_median():
    """Under five pairs the printout says why it gives no CI; from five, the percentile bootstrap
    CI of the pairs' median lies within their range and contains the median."""
    bench = load_script("benchmarks/compiled_ppo.py")
    three = bench.paired_ratio([7.0, 8.0, 6.5])
    assert three == "7.0 8.0 6.5; median 7.0x (no CI under 5 pairs: --repeats 5 or more)"
    pairs = [7.0, 8.2, 6.5, 7.4, 7.1, 6.9, 7.7]
    text = bench.paired_ratio(pairs)
    assert text.startswith("7.0 8.2 6.5 7.4 7.1 6.9 7.7; median 7.1x, 95% CI [")
    low, high = (float(x) for x in re.search(r"CI \[([\d.]+), ([\d.]+)\]", text).groups())
    assert min(pairs) <= low <= 7.1 <= high <= max(pairs) and low < high
