"""The report's folder (``--out``/``--name``): a folder the report made is rebuilt in place, its
stale figures removed; a folder holding anything else, or a path that is a file, is refused in
one line (exit 2) before the runs are loaded, and nothing the user had is touched. Real SQLite
stores, real builds, and a real process for the case the audit reproduced."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from sdrl_bench import tracking
from sdrl_bench.cli.report import main
from sdrl_bench.report import build
from sdrl_bench.report import folder as report_folder
from helpers import ROOT, run_cli

EXP = "sdrl-bench"
CURVES = "figures/curves_mountain_car_sac_sindy.png"  # drawn from the transfer runs' curves


@pytest.fixture
def report_store(store: str) -> str:
    """A fit and two seeds of transfer runs (their learning curves make a figure)."""
    with tracking.start_run(store, EXP, "fit", {"sdrl.kind": "fit", "env": "mountain_car", "library": "poly_trig",
                                                 "surrogate": "sindy", "seed": 0}) as run:
        run.log_metrics({"mse/x": 1e-16, "mse/v": 3e-19, "mse/mean": 1e-16, "corr/x": 1.0, "corr/v": 1.0})
    for seed in (0, 1):
        tags = {"sdrl.kind": "transfer", "env": "mountain_car", "agent": "sac", "surrogate": "sindy",
                "library": "poly_trig", "seed": seed}
        with tracking.start_run(store, EXP, f"train-s{seed}", tags) as run:
            run.log_metrics({"surrogate/final_return_mean": 93.0, "real/final_return_mean": 90.0})
            for arm in ("surrogate", "real"):
                run.log_text("train_steps,return_mean,return_std\n0,-10,1\n1000,90,1\n", f"curves/{arm}.csv")
    return store


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _one_error_line(capsys) -> str:
    err = capsys.readouterr()
    assert err.out == "" and "Traceback" not in err.err
    lines = err.err.strip().splitlines()
    assert len(lines) == 1, err.err
    return lines[0]


def _no_runs_loaded(monkeypatch) -> list:
    """The report's run selection, replaced by one that records that it was reached."""
    calls: list = []
    monkeypatch.setattr(build, "select_runs", lambda inp: calls.append(inp) or ([], ["select_runs was reached"]))
    return calls


def test_the_users_folder_is_refused_and_kept_as_it_was(report_store: str, tmp_path) -> None:
    """The audit's case, as a real process: ``--out . --name mythesis`` on a folder of the user's."""
    (tmp_path / "mythesis" / "figures").mkdir(parents=True)
    (tmp_path / "mythesis" / "figures" / "fig1.png").write_text("x\n")
    (tmp_path / "mythesis" / "report.md").write_text("notes\n")
    before = _snapshot(tmp_path / "mythesis")
    proc = run_cli("--uri", report_store, "--out", ".", "--name", "mythesis", "--no-log", cwd=tmp_path,
                   module="sdrl_bench.cli.report")
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.strip().splitlines() == [
        "sdrl-bench-report: error: --out/--name: mythesis holds files this report did not write under the names it "
        "writes (report.md); choose another folder or move them"]
    assert _snapshot(tmp_path / "mythesis") == before  # nothing overwritten, removed or added (no manifest)
    assert sorted(p.name for p in (tmp_path / "mythesis").iterdir()) == ["figures", "report.md"]
    assert not tracking.find_runs(report_store, EXP, "tags.`sdrl.kind` = 'report'")


def test_a_file_of_the_users_under_a_name_the_report_writes_is_refused(report_store: str, tmp_path, capsys,
                                                                       monkeypatch) -> None:
    assert main(["--uri", report_store, "--out", str(tmp_path), "--name", "r", "--no-log"]) == 0
    folder = tmp_path / "r"
    (folder / "figures" / "pred_mine_sindy.png").write_text("mine\n")  # not in the build's record: the user's
    before = _snapshot(folder)
    calls = _no_runs_loaded(monkeypatch)
    capsys.readouterr()
    assert main(["--uri", report_store, "--out", str(tmp_path), "--name", "r", "--no-log"]) == 2
    assert _one_error_line(capsys) == (f"sdrl-bench-report: error: --out/--name: {folder} holds files this report did "
                                       "not write under the names it writes (figures/pred_mine_sindy.png); choose "
                                       "another folder or move them")
    assert calls == [] and _snapshot(folder) == before


def test_a_rebuild_keeps_the_users_other_files_and_takes_its_own_changed_by_git(report_store: str, tmp_path) -> None:
    """A note beside the report is left where it is; report.md and report.html changed since the
    build (a git checkout of someone's rebuild) are still the report's, rebuilt in place."""
    args = ["--uri", report_store, "--out", str(tmp_path), "--name", "r", "--no-log"]
    assert main(args) == 0
    folder = tmp_path / "r"
    (folder / "notes.txt").write_text("mine\n")
    (folder / ".DS_Store").write_bytes(b"\0")
    for rel in ("report.md", "report.html"):
        (folder / rel).write_text((folder / rel).read_text() + "\nchanged by a checkout\n")
    assert main(args) == 0
    assert (folder / "notes.txt").read_text() == "mine\n" and (folder / ".DS_Store").read_bytes() == b"\0"
    assert "changed by a checkout" not in (folder / "report.md").read_text() + (folder / "report.html").read_text()
    assert "notes.txt" not in json.loads((folder / report_folder.MANIFEST).read_text())["files"]


def test_a_rebuild_in_place_removes_the_figures_the_new_build_no_longer_makes(report_store: str, tmp_path) -> None:
    args = ["--uri", report_store, "--out", str(tmp_path), "--name", "r", "--no-log"]
    assert main(args) == 0
    folder = tmp_path / "r"
    manifest = json.loads((folder / report_folder.MANIFEST).read_text())
    assert manifest["complete"] and CURVES in manifest["files"] and (folder / CURVES).is_file()
    assert set(manifest["files"]) == set(_snapshot(folder)) - {report_folder.MANIFEST}
    assert main([*args, "--tag", "sdrl.kind=fit"]) == 0  # no transfer runs now: no learning curves
    assert not (folder / CURVES).exists()
    manifest = json.loads((folder / report_folder.MANIFEST).read_text())
    assert CURVES not in manifest["files"] and set(manifest["files"]) == set(_snapshot(folder)) - {report_folder.MANIFEST}
    assert "Runs read: fit (FINISHED): 1." in (folder / "report.md").read_text()


def test_the_committed_report_made_before_the_manifest_is_rebuilt_in_place(report_store: str, tmp_path, capsys) -> None:
    """reports/reproduction (made by the report before it wrote a manifest) is the report's: a rebuild
    there replaces it and removes the figures and table the new build does not make, and leaves a
    file of the user's under another name where it is."""
    reference = ROOT / "reports" / "reproduction"
    folder = tmp_path / "reproduction"
    shutil.copytree(reference, folder)
    (folder / report_folder.MANIFEST).unlink(missing_ok=True)  # as the report wrote it before there was one
    old_figures = {p.name for p in (folder / "figures").iterdir()}
    assert len(old_figures) > 20 and (folder / "fidelity_correlations.csv").is_file()

    (folder / "figures" / "fig1.png").write_text("x\n")  # the user's, under a name the report never gives
    assert main(["--uri", report_store, "--out", str(tmp_path), "--name", "reproduction", "--no-log"]) == 0
    assert {p.name for p in (folder / "figures").iterdir()} == {Path(CURVES).name, "fig1.png"}
    assert (folder / "figures" / "fig1.png").read_text() == "x\n"
    assert not (folder / "fidelity_correlations.csv").exists()  # no fidelity runs in this store
    assert "Runs read: fit (FINISHED): 1, transfer (FINISHED): 2." in (folder / "report.md").read_text()
    assert json.loads((folder / report_folder.MANIFEST).read_text())["complete"]


def test_a_build_cut_short_leaves_a_folder_the_next_build_takes(report_store: str, tmp_path, monkeypatch) -> None:
    """A build stopped after its figures (Ctrl-C) leaves files its manifest does not list yet: the
    manifest says the build did not complete, and the next build takes the files the report names."""
    args = ["--uri", report_store, "--out", str(tmp_path), "--name", "r", "--no-log"]
    assert main([*args, "--tag", "sdrl.kind=fit"]) == 0  # no learning curves
    assert CURVES not in json.loads((tmp_path / "r" / report_folder.MANIFEST).read_text())["files"]

    def stop(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(build, "fidelity_blocks", stop)  # after the figures are written, before report.md
    with pytest.raises(KeyboardInterrupt):
        main(args)
    assert (tmp_path / "r" / CURVES).is_file()
    manifest = json.loads((tmp_path / "r" / report_folder.MANIFEST).read_text())
    assert not manifest["complete"] and CURVES not in manifest["files"]
    monkeypatch.undo()
    assert main([*args, "--tag", "sdrl.kind=fit"]) == 0
    assert not (tmp_path / "r" / CURVES).exists()
    assert json.loads((tmp_path / "r" / report_folder.MANIFEST).read_text())["complete"]


@pytest.mark.parametrize("case", ["--out", "--out/--name", "below --out"])
def test_a_file_where_the_folder_goes_is_one_line_before_the_runs_load(case: str, report_store: str, tmp_path,
                                                                        capsys, monkeypatch) -> None:
    afile = tmp_path / "afile"
    afile.write_text("the user's\n")
    out, name, key, named = {"--out": (afile, "z", "--out", afile),
                             "--out/--name": (tmp_path, "afile", "--out/--name", afile),
                             "below --out": (afile / "sub", "z", "--out", afile)}[case]
    calls = _no_runs_loaded(monkeypatch)
    assert main(["--uri", report_store, "--out", str(out), "--name", name, "--no-log"]) == 2
    what = "folder" if key == "--out" else "name"
    assert _one_error_line(capsys) == (f"sdrl-bench-report: error: {key}: {named} is a file, not a folder; choose "
                                       f"another {what} or move it")
    assert calls == [] and afile.read_text() == "the user's\n"


@pytest.mark.parametrize("args, line", [
    (["--name", "../escape"], "--name: a folder under --out is required (no absolute path, no '..'), got '../escape'"),
    (["--name", "a/../../escape"], "--name: a folder under --out is required (no absolute path, no '..'), got "
                                   "'a/../../escape'"),
    (["--name", "/tmp/escape"], "--name: a folder under --out is required (no absolute path, no '..'), got "
                                "'/tmp/escape'"),
    (["--ui-url", "http:x"], "--ui-url: an http(s) URL of an MLflow UI is required (e.g. http://127.0.0.1:5000), "
                             "got 'http:x'"),
    (["--ui-url", "notaurl"], "--ui-url: an http(s) URL of an MLflow UI is required (e.g. http://127.0.0.1:5000), "
                              "got 'notaurl'"),
])
def test_a_name_that_leaves_out_or_a_ui_url_that_is_no_url_is_one_line(args, line, report_store: str, tmp_path,
                                                                       capsys, monkeypatch) -> None:
    """``--name ../escape`` wrote the report outside ``--out``; ``--ui-url notaurl`` made relative
    links. Both refused in one line before the runs load, nothing written."""
    calls = _no_runs_loaded(monkeypatch)
    out = tmp_path / "out"
    assert main(["--uri", report_store, "--out", str(out), "--no-log", *args]) == 2
    assert _one_error_line(capsys) == f"sdrl-bench-report: error: {line}"
    assert calls == [] and not out.exists() and not (tmp_path / "escape").exists()


def test_an_empty_or_absent_folder_is_fine(report_store: str, tmp_path) -> None:
    (tmp_path / "empty").mkdir()
    for name in ("empty", "new/deeper"):
        assert main(["--uri", report_store, "--out", str(tmp_path), "--name", name, "--no-log"]) == 0
        assert (tmp_path / name / "report.md").read_text().startswith(report_folder.REPORT_HEADING)
