"""Env knowledge lives in ``envs/`` and the env's config: generic code never names an env.

An AST lint over the generic packages fails on an env's name, gym id, state, action, event or
regime name in a string literal or an identifier, on a literal index into a state array
(``states[:, 6]``), on an env's numeric constant (a solved threshold, a crash reward, a bound),
and on an import of an env's own module. The vocabulary is read from the env configs the
package ships (``conf/env/*.yaml``, the specs they build) and the env modules' constants, so a
new env is covered without editing this file. import-linter's contract in ``pyproject.toml``
forbids the same imports (CI runs both).
"""

from __future__ import annotations

import ast
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

from sdrl_bench.envs.base import EnvSpec, find_spec

PKG = Path(__file__).resolve().parents[1] / "sdrl_bench"
GENERIC = ("surrogate", "rl", "report", "cli", "tracking", "search", "models", "pipeline.py", "fidelity.py", "data.py",
           "plots.py", "metrics.py", "seeds.py")
ENV_AGNOSTIC = {"sdrl_bench.envs", "sdrl_bench.envs.base", "sdrl_bench.envs.task", "sdrl_bench.envs.functional"}
"""The modules of ``envs`` that generic code may import."""
TRIVIAL = {0.5, 0.1, 0.01, 0.2, 0.25, 0.05, 0.001, 0.005}
"""Numbers too common to be an env's constant (absolute values; integers count only below -10: a
crash reward). 0.005: SB3's SAC default ``tau`` (``rl.jax_sac``), and in envs/ only a grid's step."""
LAYOUT = {"figsize", "dpi", "fontsize", "shrink", "alpha", "linewidth", "lw", "pad", "wspace", "hspace", "markersize",
          "rotation", "size", "s", "width", "height"}
"""Keyword arguments whose numbers are a figure's layout, never an env's constant."""
FIELDS: set[str] = set()
"""Field names of env spec classes beyond the base's (filled by ``_vocabulary``): identifiers only."""
COMMON_WORDS = {"main", "force", "angle", "crash", "survive", "contact", "rest"}
"""Env names that are also ordinary identifiers (``hydra.main``, ``angle``): checked in strings only."""
STATE_ARRAYS = re.compile(r"^(s|ns|nxt|obs|pre|states?|next_states?|observations?|.*_states?)$")


def _env_specs() -> dict[str, EnvSpec]:
    return {p.stem: find_spec(p.stem) for p in sorted((PKG / "conf" / "env").glob("*.yaml"))}


def _vocabulary() -> tuple[set[str], set[float]]:
    """(names, numbers) that only an env knows."""
    base_fields = set(EnvSpec.__dataclass_fields__)
    names: set[str] = set()
    numbers: set[float] = set()
    for spec in _env_specs().values():
        base_id = spec.gym_id.rpartition(":")[2].split("-v")[0]  # LunarLander-v3 -> LunarLander, as prose names it
        names |= {spec.name, spec.gym_id, type(spec).__name__, base_id, base_id.replace("Continuous", "")}
        names |= set(spec.state_names) | set(spec.action_names) | set(spec.observation_names)
        FIELDS.update(set(type(spec).__dataclass_fields__) - base_fields)  # an env class's own fields (rules, ...)
        n = len(spec.state_names)
        names |= set(spec.regimes(np.zeros(2, int), np.zeros((2, n)), np.zeros(2), np.zeros((2, n))))
        if spec.task is not None:
            for e in spec.task.events:
                names |= {e.name, *e.outcome_names}
            if spec.task.crash_reward is not None:
                numbers.add(float(spec.task.crash_reward))
        for v in (spec.solved_threshold, *(spec.state_low or ()), *(spec.state_high or ())):
            if v is not None and np.isfinite(v):
                numbers.add(float(v))
    for path in (PKG / "envs").rglob("*.py"):  # module-level constants of the envs' own modules
        if path.name in ("base.py", "task.py", "functional.py", "__init__.py"):
            continue
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, ast.Assign) and all(isinstance(t, ast.Name) and t.id.isupper() for t in node.targets):
                for c in ast.walk(node.value):
                    if isinstance(c, ast.Constant) and isinstance(c.value, (int, float)) and not isinstance(c.value, bool):
                        numbers.add(float(c.value))
    names = {n for n in names if len(n) >= 3}  # one- and two-letter state names (x, v, th) are everyone's
    return names - {"EnvSpec"}, {x for x in numbers if _distinctive(x)}


def _distinctive(x: float) -> bool:
    return (x <= -10 if float(x).is_integer() else abs(x) not in TRIVIAL)


def _generic_files() -> list[Path]:
    out = []
    for g in GENERIC:
        p = PKG / g
        out += sorted(p.rglob("*.py")) if p.is_dir() else [p]
    return out


def _docstrings(tree: ast.AST) -> set[int]:
    ids = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
                ids.add(id(first.value))
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            ids.add(id(node.value))  # attribute docstrings (a string under a field)
    return ids


def _number(node: ast.AST) -> float | None:
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
        inner = _number(node.operand)
        return None if inner is None else -inner
    if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) and not isinstance(node.value, bool):
        return float(node.value)
    return None


def findings(path: Path, names: set[str], numbers: set[float]) -> list[str]:
    """What ``path`` knows of an env: one line per finding."""
    tree = ast.parse(path.read_text())
    docs, out = _docstrings(tree), []
    idents = (names | FIELDS) - COMMON_WORDS
    rel = path.relative_to(PKG.parent)
    negated = {id(n.operand) for n in ast.walk(tree) if isinstance(n, ast.UnaryOp) and isinstance(n.op, ast.USub)}
    layout = {id(c) for k in ast.walk(tree) if isinstance(k, ast.keyword) and k.arg in LAYOUT for c in ast.walk(k.value)}
    for node in ast.walk(tree):
        where = f"{rel}:{getattr(node, 'lineno', '?')}"
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docs:
            hit = sorted(set(re.findall(r"[A-Za-z_][A-Za-z0-9_\-]*", node.value)) & names)
            if hit:
                out.append(f"{where}: string names {hit}")
        elif isinstance(node, ast.Name) and node.id in idents:
            out.append(f"{where}: identifier {node.id!r}")
        elif isinstance(node, ast.Attribute) and node.attr in idents:
            out.append(f"{where}: attribute {node.attr!r}")
        elif isinstance(node, (ast.Constant, ast.UnaryOp)) and id(node) not in negated and id(node) not in layout:
            v = _number(node)
            if v is not None and v in numbers:
                out.append(f"{where}: env constant {v:g}")
        if isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name) and STATE_ARRAYS.match(node.value.id):
            idx = node.slice.elts if isinstance(node.slice, ast.Tuple) else [node.slice]
            if len(idx) >= 2 and any(_number(i) is not None for i in idx[1:]):
                out.append(f"{where}: literal state index {ast.unparse(node)}")
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("sdrl_bench.envs"):
            mods = [node.module] + [f"{node.module}.{a.name}" for a in node.names if node.module == "sdrl_bench.envs"]
            bad = [m for m in mods if m not in ENV_AGNOSTIC and not any(m == f"sdrl_bench.envs.{a.name}" and a.name in
                                                                          ("EnvSpec", "Policy", "TestSetRecipe") for a in node.names)]
            if node.module not in ENV_AGNOSTIC or bad:
                out.append(f"{where}: imports {node.module}")
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("sdrl_bench.envs") and a.name not in ENV_AGNOSTIC:
                    out.append(f"{where}: imports {a.name}")
    return out


def test_the_vocabulary_is_read_from_the_env_configs():
    names, numbers = _vocabulary()
    # what the lint looks for, read from the shipped configs (checked so that it cannot be empty)
    assert {"lunar_lander", "mountain_car", "LunarLander-v3", "LunarLander", "leg_left", "angvel", "touchdown", "flight"} <= names
    assert {"rules", "terrain", "touchdown_set"} <= FIELDS
    assert {-100.0, 0.07, -1.2, 0.45} <= numbers


def test_generic_code_knows_no_env():
    names, numbers = _vocabulary()
    found = [f for path in _generic_files() for f in findings(path, names, numbers)]
    assert not found, "env knowledge outside envs/:\n" + "\n".join(found)


def test_the_lint_catches_what_it_should(tmp_path):
    """The same lint on a file written as the old surrogate core was (names, indices, constants)."""
    names, numbers = _vocabulary()
    bad = PKG / "surrogate" / "_lint_probe.py"
    bad.write_text('def f(spec, states, rewards):\n'
                   '    if spec.rules.tip_angle:\n'
                   '        flight = states[:, 6] <= 0.5\n'
                   '    rewards[flight] = -100.0\n'
                   '    return f"{spec.name}: real touchdown"\n'
                   'from sdrl_bench.envs.lunar_lander import LunarLanderSpec\n')
    try:
        got = findings(bad, names, numbers)
    finally:
        bad.unlink()
    kinds = " | ".join(got)
    for needle in ("attribute 'rules'", "identifier 'flight'", "literal state index states[:, 6]", "env constant -100",
                   "string names ['touchdown']", "imports sdrl_bench.envs.lunar_lander"):
        assert needle in kinds, (needle, got)


def test_import_linter_forbids_env_modules_in_generic_code():
    """The contract CI runs (``lint-imports``) names every env package under ``envs/``."""
    conf = tomllib.loads((PKG.parent / "pyproject.toml").read_text())
    contracts = {c["name"]: c for c in conf["tool"]["importlinter"]["contracts"]}
    c = next(c for n, c in contracts.items() if n.startswith("Generic code imports no env"))
    env_modules = {f"sdrl_bench.envs.{p.stem if p.is_file() else p.name}" for p in (PKG / "envs").iterdir()
                   if (p.is_dir() and (p / "__init__.py").exists()) or (p.suffix == ".py" and p.stem not in
                                                                       ("__init__", "base", "task", "functional"))}
    assert env_modules and env_modules <= set(c["forbidden_modules"])
    assert {f"sdrl_bench.{g.removesuffix('.py')}" for g in GENERIC} <= set(c["source_modules"])


@pytest.mark.parametrize("name", ["lunar_lander", "mountain_car", "pendulum", "cartpole"])
def test_every_shipped_env_is_found_by_its_config(name):
    assert find_spec(name).name == name
