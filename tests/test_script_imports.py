"""Every name a script, study, benchmark or module imports from ``sdrl_bench`` exists: such
imports sit inside functions (so that ``--help`` stays fast, or an extra stays optional), where
nothing runs them until a user does. Read with ``ast``, checked by importing the module named
(modules that need an extra this install lacks are passed over)."""

from __future__ import annotations

import ast
import importlib
import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("sdrl_bench", "studies", "benchmarks", "scripts", "tests")


def _imports() -> dict[tuple[str, str], list[str]]:
    """(module, name) -> the files (path:line) that import it."""
    out: dict[tuple[str, str], list[str]] = {}
    for folder in FOLDERS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            if ".venv" in path.parts:
                continue
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").split(".")[0] == "sdrl_bench":
                    for alias in node.names:
                        out.setdefault((node.module, alias.name), []).append(f"{path.relative_to(ROOT)}:{node.lineno}")
    return out


def test_every_name_imported_from_sdrl_bench_exists():
    found = _imports()
    assert len(found) > 300  # the walk read the tree
    missing, modules = [], {}
    for (module, name), where in sorted(found.items()):
        if module not in modules:
            try:
                modules[module] = importlib.import_module(module)
            except ImportError as exc:
                if exc.name and exc.name.split(".")[0] == "sdrl_bench":
                    missing.append(f"{where[0]}: no module {module}")
                modules[module] = None  # an optional extra (jax, dm_control) this install lacks
                continue
        mod = modules[module]
        if mod is None or name == "*" or hasattr(mod, name):
            continue
        if not hasattr(mod, "__path__") or importlib.util.find_spec(f"{module}.{name}") is None:
            missing.append(f"{where[0]}: {module} has no {name}")
    assert missing == []
