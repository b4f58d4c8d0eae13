"""studies/kernel_choices.py reruns a case in fresh processes with one kernel choice changed each
(docs/seeds.md): MountainCar's fit is the exact law under any OpenBLAS core type, bit for bit."""

from __future__ import annotations

import subprocess
import sys

from helpers import ROOT


def test_mountain_cars_fit_does_not_move_with_openblas_kernels(tmp_path):
    cmd = [sys.executable, str(ROOT / "studies" / "kernel_choices.py"), "--rows", "fit_mountain_car"]
    proc = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = [line.split("|")[1:-1] for line in proc.stdout.splitlines() if line.startswith("| fit_mountain_car")]
    assert [r[1].strip() for r in rows] == ["nothing (the reference)", "OPENBLAS_CORETYPE=Sandybridge",
                                            "OPENBLAS_CORETYPE=Prescott"]
    assert len({r[2] for r in rows}) == 1 and all(r[3].strip() == "yes" and float(r[5]) == 0 for r in rows)
    assert all(r[4].strip().startswith("0 of ") for r in rows)
    assert proc.stdout.startswith("machine: ")
