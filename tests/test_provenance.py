"""Every constant the package takes from a study names its study, command and data: a
``Provenance:`` line (a docstring or a config comment) whose study exists under ``studies/``,
with the command in backticks and the data it ran on. Fitted constants without one fail."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PROVENANCE = re.compile(r"Provenance:\s*(studies/[\w./]+\.py)\s*\(`([^`]+)`\);\s*data:\s*\S")


def _texts() -> list[tuple[str, str]]:
    """(where, text) of every docstring-like string and every comment block in the package."""
    out = []
    for path in (ROOT / "sdrl_bench").rglob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and "Provenance" in node.value:
                out.append((f"{path.relative_to(ROOT)}:{node.lineno}", " ".join(node.value.split())))
    for path in (ROOT / "sdrl_bench" / "conf").rglob("*.yaml"):
        lines = path.read_text().splitlines()
        for i, line in enumerate(lines):
            if "# Provenance:" in line:
                block = [line.split("#", 1)[1]]
                j = i + 1
                while j < len(lines) and lines[j].strip().startswith("#") and "Provenance" not in lines[j]:
                    block.append(lines[j].strip()[1:])
                    j += 1
                out.append((f"{path.relative_to(ROOT)}:{i + 1}", " ".join(" ".join(block).split())))
    return out


def test_every_provenance_names_an_existing_study_its_command_and_data():
    texts = _texts()
    assert len(texts) >= 8
    for where, text in texts:
        for chunk in text.split("Provenance:")[1:]:
            m = PROVENANCE.match("Provenance:" + chunk)
            assert m, f"{where}: a Provenance needs 'studies/<x>.py (`command`); data: ...': {chunk[:120]!r}"
            assert (ROOT / m.group(1)).is_file(), f"{where}: no study {m.group(1)}"
            assert m.group(1) in m.group(2), f"{where}: the command does not run {m.group(1)}"


def test_fitted_constants_carry_their_provenance():
    """The fields and constants documented as fitted on real data name where from."""
    from sdrl_bench.envs.lunar_lander import task

    tree = ast.parse(Path(task.__file__).read_text())
    rules = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "LanderRules")
    docs = {}
    for a, b in zip(rules.body, rules.body[1:], strict=False):
        if isinstance(a, ast.AnnAssign) and isinstance(b, ast.Expr) and isinstance(b.value, ast.Constant):
            docs[a.target.id] = b.value.value
    fitted = [k for k, d in docs.items() if "fitted" in d or "Fitted" in d]
    assert {"leg_tilt", "touch_height", "release_height", "touchdown_speed", "stick", "settle"} <= set(fitted)
    for k in fitted:
        assert "Provenance: studies/" in docs[k], k
    spec_src = (ROOT / "sdrl_bench" / "envs" / "lunar_lander" / "spec.py").read_text()
    assert "Provenance: studies/noise_floor.py" in spec_src
