"""The report's folder: which files in it an earlier build of the report wrote (to replace and
remove) and which are the user's (never touched: the folder is refused). No pandas or MLflow
import, so that ``sdrl-bench-report`` answers a bad ``--out``/``--name`` before loading them.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path
from typing import Any
from collections.abc import Mapping, Sequence

from sdrl_bench import ConfigError

# ---------------------------------------------------------------------- the report's folder
# A report is written into out_dir/name, which may hold an earlier build's files: those are the
# report's to replace (and a figure the new build no longer makes must not linger), but anything
# else there is the user's, and is never overwritten or removed. A build records what it wrote
# in MANIFEST (each file with its SHA-256, for provenance; a recorded file stays the report's
# when a git checkout changes it). A folder without a manifest (made before there was one, e.g.
# reports/reproduction) is the report's when its report.md opens with the report's heading; its
# files under the report's names are then the report's. While a build runs its manifest says
# "complete": false, so that a build cut short leaves a folder the next build still recognises by
# those names. A file of the user's under a name the report writes stops the build; the user's
# other files are left where they are.

MANIFEST = ".sdrl-bench-report.json"
REPORT_HEADING = "# sdrl-bench report"  # report.md's first line starts so (overview_blocks' heading)
_REWRITTEN = ("report.md", "report.html", "runs.csv")  # every build writes these over the old ones
_NAMED = re.compile(r"(report\.md|report\.html|runs\.csv|fidelity_correlations\.csv"  # fidelity_study
                    r"|figures/(curves|policy_maps|real_steps|pred|study|fidelity)_[^/]+\.png)")  # figures, fidelity_study
_SCRATCH = re.compile(r"(\.dl|figures/\.dl-[^/]+)/.+|" + re.escape(MANIFEST) + r"\.tmp")  # downloads, a manifest being written


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _files(folder: Path) -> list[str]:
    """Every entry under ``folder`` that is not a directory (links included, never followed), as
    paths relative to it."""
    out = []
    for root, dirs, files in os.walk(folder, onerror=_raise):
        base = Path(root)
        for d in list(dirs):
            if (base / d).is_symlink():  # a link to a folder is an entry of its own, not a folder to enter
                dirs.remove(d)
                files.append(d)
        out += [(base / f).relative_to(folder).as_posix() for f in files]
    return sorted(out)


def _raise(exc: OSError) -> None:
    raise exc


def _manifest(folder: Path) -> dict[str, Any] | None:
    """The folder's manifest, or None when it has none (or one that is not the report's)."""
    try:
        data = json.loads((folder / MANIFEST).read_text())
    except (OSError, ValueError):
        return None
    if (not isinstance(data, dict) or data.get("written_by") != "sdrl-bench-report"
            or not isinstance(data.get("files"), dict)):
        return None
    return data


def _has_heading(path: Path) -> bool:
    try:
        with path.open(encoding="utf-8", errors="replace") as f:
            return f.readline().startswith(REPORT_HEADING)
    except OSError:
        return False


def report_files(out_dir: Path, name: str) -> tuple[Path, list[str], dict[str, Any] | None]:
    """The report's folder ``out_dir/name``, the files in it that earlier builds of the report
    wrote (relative paths: those its manifest records, or in a folder without a complete one,
    those under the report's names beside a report.md with its heading), and its manifest. A
    ConfigError (one line, nothing touched) when ``out_dir`` or the folder is not a folder, or when
    a file the report did not write has a name the report writes (report.md, a figure's, ...):
    the user's files are never overwritten or removed. Other files of the user's are left as
    they are."""
    folder = out_dir / name
    for p in (folder, *folder.parents):  # the nearest existing one must be a folder (mkdir makes the rest)
        if p.is_dir():
            break
        if p.exists() or p.is_symlink():
            key = "--out" if p == out_dir or p in out_dir.parents else "--out/--name"
            raise ConfigError(f"{key}: {p} is a file, not a folder; choose another {'folder' if key == '--out' else 'name'}"
                              " or move it")
    if not folder.is_dir():
        return folder, [], None
    try:
        files = _files(folder)
        manifest = _manifest(folder)
        recorded = manifest["files"] if manifest else {}
        complete = bool(manifest and manifest.get("complete"))
        named = manifest is not None or not files or ("report.md" in files and _has_heading(folder / "report.md"))

        def ours(rel: str) -> bool:
            if (folder / rel).is_symlink():  # the report writes no links
                return False
            if _SCRATCH.fullmatch(rel) or (rel == MANIFEST and manifest is not None) or rel in recorded:
                return True  # a recorded file may have changed since (a git checkout of a rebuilt report)
            if complete or not named or not _NAMED.fullmatch(rel):
                return False
            return rel != "report.md" or _has_heading(folder / rel)

        mine = [rel for rel in files if ours(rel)]
        in_the_way = [rel for rel in files if not ours(rel) and _NAMED.fullmatch(rel)]  # a name a build writes
    except OSError as exc:
        raise ConfigError(f"--out/--name: cannot read {folder} ({exc.strerror or exc}); choose another folder") from None
    if in_the_way:
        shown = ", ".join(in_the_way[:3]) + (f" and {len(in_the_way) - 3} more" if len(in_the_way) > 3 else "")
        raise ConfigError(f"--out/--name: {folder} holds files this report did not write under the names it writes "
                          f"({shown}); choose another folder or move them")
    return folder, mine, manifest


def _write_manifest(folder: Path, files: Mapping[str, str], complete: bool) -> None:
    tmp = folder / (MANIFEST + ".tmp")
    tmp.write_text(json.dumps({"written_by": "sdrl-bench-report", "complete": complete, "files": dict(files)},
                              indent=1, sort_keys=True) + "\n")
    tmp.replace(folder / MANIFEST)  # whole or not at all


def clear_earlier_build(folder: Path, files: Sequence[str], manifest: Mapping[str, Any] | None) -> set[str]:
    """Remove what an earlier build wrote (``files``, from ``report_files``), but the documents this
    build writes over, so that no figure or table of an earlier build outlives it; first mark
    the folder's manifest incomplete (keeping its record), so that a build cut short leaves a
    folder the next build still recognises. Returns the user's files left there."""
    folder.mkdir(parents=True, exist_ok=True)
    _write_manifest(folder, manifest["files"] if manifest else {}, complete=False)
    for rel in files:
        if rel in _REWRITTEN or rel == MANIFEST:
            continue
        path = folder / rel
        path.unlink(missing_ok=True)
        for parent in path.parents:  # the folders this leaves empty (figures/, a download's), not the report's
            if parent == folder or any(parent.iterdir()):
                break
            parent.rmdir()
    return {rel for rel in _files(folder) if rel not in files and rel != MANIFEST and not _SCRATCH.fullmatch(rel)}


def record_build(folder: Path, users: set[str]) -> None:
    """The manifest of a finished build: every file now in ``folder`` but the user's (``users``,
    from ``clear_earlier_build``), with its SHA-256."""
    written = [rel for rel in _files(folder) if rel != MANIFEST and rel not in users and not _SCRATCH.fullmatch(rel)]
    _write_manifest(folder, {rel: _sha256(folder / rel) for rel in written}, complete=True)
