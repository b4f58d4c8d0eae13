"""A repository script that runs commands (``scripts/reproduce.py``, ``benchmarks/time_to_solve.py``,
``studies/dyna_real_steps.py``, ``studies/own_data_ablation.py``) stops them when it is stopped
(``sdrl_bench.cli.args``: ``script_main``, ``run_child``, ``wait_children``). Before, a SIGTERM
to the script killed it alone and its ``sdrl-bench`` children ran on. Real processes and real
signals: a parent script like those, its child a Python process that records the signal it got."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from helpers import ROOT

CHILD = """
import signal, sys, time
out = sys.argv[1]
def on(signum, frame):
    open(out, "w").write(signal.Signals(signum).name)
    sys.exit(0)
signal.signal(signal.SIGTERM, on)
signal.signal(signal.SIGINT, on)
open(out + ".started", "w").write("")
time.sleep(300)
"""

PARENT = """
import sys
from sdrl_bench.cli.args import run_child, script_main
def main():
    run_child([sys.executable, "-c", sys.argv[1], sys.argv[2]])
script_main(main, "parent.py")
"""


def _start(tmp_path):
    out = tmp_path / "child.txt"
    proc = subprocess.Popen([sys.executable, "-c", PARENT, CHILD, str(out)], cwd=tmp_path, stderr=subprocess.PIPE,
                            text=True, start_new_session=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    deadline = time.monotonic() + 60
    while not (tmp_path / "child.txt.started").exists():
        assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
        time.sleep(0.05)
    return proc, out


def test_a_sigterm_to_the_script_stops_its_child_and_exits_143(tmp_path):
    proc, out = _start(tmp_path)
    proc.send_signal(signal.SIGTERM)  # to the script alone, as `kill PID` sends it
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM
    assert err.strip().splitlines() == ["parent.py: stopped by SIGTERM; its commands were stopped"]
    assert out.read_text() == "SIGTERM"  # the child got the stop, and ended by itself


@pytest.mark.parametrize("group", [True, False], ids=["ctrl-c at a terminal (the group)", "SIGINT to the script"])
def test_a_sigint_stops_the_child_once(tmp_path, group):
    """At a terminal Ctrl-C reaches the child too: it is left to end by itself, not signalled a
    second time; a SIGINT to the script alone is passed on (after the 10 s the child is given)."""
    proc, out = _start(tmp_path)
    (os.killpg if group else os.kill)(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGINT
    assert err.strip().splitlines() == ["parent.py: stopped by SIGINT; its commands were stopped"]
    assert out.read_text() == ("SIGINT" if group else "SIGTERM")  # the group's child: its own SIGINT, no second signal
