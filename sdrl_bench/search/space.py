"""The search space over SINDy hyperparameters: parsing, validation, sampling, export.

A space is a mapping from a *known parameter* to its distribution, as written in
``conf/search/*.yaml``::

    threshold:   {type: float, low: 1.0e-6, high: 0.1, log: true}
    library:     {type: categorical, choices: [polynomial, poly_trig, rational]}
    poly_degree: {type: int, low: 1, high: 3}

Each known parameter maps onto one key of the ``sdrl-bench`` config (``PARAM_KEYS``), so the
best trial exports as plain command-line overrides or as an experiment pack that a fit run
uses directly. Everything here is pure: no storage, no tracking, no fitting.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any
from collections.abc import Mapping, Sequence

import yaml

from sdrl_bench import ConfigError

PARAM_KEYS: dict[str, str] = {
    "threshold": "env.sindy.threshold",
    "alpha": "env.sindy.alpha",
    "normalize_columns": "env.sindy.normalize_columns",
    "poly_degree": "env.poly_degree",
    "library": "library",
    "optimizer": "optimizer",
    "width": "surrogate.model.width",
    "depth": "surrogate.model.depth",
    "activation": "surrogate.model.activation",
    "learning_rate": "surrogate.model.learning_rate",
    "weight_decay": "surrogate.model.weight_decay",
    "batch_size": "surrogate.model.batch_size",
}
"""Known parameter -> the ``sdrl-bench`` config key it sets (``library`` and ``optimizer`` are
config-group choices, the rest are values). The ``surrogate.model.*`` ones are an NN's
(``surrogate=nn`` or ``pe``), the others SINDy's."""
GROUP_PARAMS = ("library", "optimizer")
NN_PARAMS = tuple(k for k, v in PARAM_KEYS.items() if v.startswith("surrogate.model."))
KINDS = ("float", "int", "categorical")


@dataclass(frozen=True)
class ParamSpec:
    """One searched parameter."""

    name: str
    """A key of ``PARAM_KEYS``."""
    kind: str
    """``float``, ``int`` or ``categorical``."""
    low: float | None = None
    """Lower bound (float, int)."""
    high: float | None = None
    """Upper bound, inclusive (float, int); must exceed ``low``."""
    log: bool = False
    """Sample on a log scale (bounds must be positive)."""
    choices: tuple[Any, ...] | None = None
    """The values of a categorical parameter."""
    grid: tuple[Any, ...] | None = None
    """The values the grid sampler visits (within the bounds); categorical: ``choices``."""

    def describe(self) -> dict[str, Any]:
        """The distribution as plain data (what a study stores and compares; no grid)."""
        if self.kind == "categorical":
            return {"type": "categorical", "choices": list(self.choices or ())}
        return {"type": self.kind, "low": self.low, "high": self.high, "log": self.log}


SearchSpace = tuple[ParamSpec, ...]


def parse_space(raw: Mapping[str, Any] | None, key: str = "search.space") -> SearchSpace:
    """Validate a space written as plain data; every problem is a one-line ``ConfigError``."""
    if not raw:
        raise ConfigError(f"{key}: the search space is empty")
    return tuple(_parse_param(str(name), spec, f"{key}.{name}") for name, spec in raw.items())


def check_model_kind(space: SearchSpace, kind: str, key: str = "search.space") -> None:
    """A space searches the hyperparameters of the model it fits: an NN's with ``surrogate=nn``
    or ``pe``, SINDy's with ``surrogate=sindy`` (a parameter of the other kind would be ignored)."""
    for p in space:
        if (p.name in NN_PARAMS) != (kind != "sindy"):
            what = "an NN hyperparameter" if p.name in NN_PARAMS else "a SINDy hyperparameter"
            raise ConfigError(f"{key}.{p.name}: {what}, but the search fits surrogate={kind}; "
                              f"use {'surrogate=nn or surrogate=pe' if p.name in NN_PARAMS else 'surrogate=sindy'}")


def _parse_param(name: str, spec: Any, key: str) -> ParamSpec:
    if name not in PARAM_KEYS:
        raise ConfigError(f"{key}: unknown parameter '{name}'; known parameters: {', '.join(PARAM_KEYS)}")
    if not isinstance(spec, Mapping):
        raise ConfigError(f"{key}: expected a mapping with 'type' and bounds or choices, got {spec!r}")
    unknown = set(spec) - {"type", "low", "high", "log", "choices", "grid"}
    if unknown:
        raise ConfigError(f"{key}: unknown fields {sorted(unknown)}")
    kind = spec.get("type")
    if kind not in KINDS:
        raise ConfigError(f"{key}.type: must be one of {list(KINDS)}, got {kind!r}")
    if kind == "categorical":
        return _parse_categorical(name, spec, key)
    return _parse_numeric(name, kind, spec, key)


def _parse_categorical(name: str, spec: Mapping, key: str) -> ParamSpec:
    choices = spec.get("choices")
    if not isinstance(choices, Sequence) or isinstance(choices, str) or len(choices) == 0:
        raise ConfigError(f"{key}.choices: a categorical parameter needs a non-empty list of choices")
    if len(set(map(repr, choices))) != len(choices):
        raise ConfigError(f"{key}.choices: duplicate choices in {list(choices)}")
    if name in GROUP_PARAMS and not all(isinstance(c, str) for c in choices):
        raise ConfigError(f"{key}.choices: {name} choices are config names (strings)")
    return ParamSpec(name, "categorical", choices=tuple(choices), grid=tuple(choices))


def _parse_numeric(name: str, kind: str, spec: Mapping, key: str) -> ParamSpec:
    low, high, log = spec.get("low"), spec.get("high"), spec.get("log", False)
    if not isinstance(log, bool):  # bool("maybe") was a log scale
        raise ConfigError(f"search.space.{name}.log: true or false is required, got {log!r}")
    for bound, value in (("low", low), ("high", high)):
        if not _is_number(value) or not math.isfinite(float(value)):
            raise ConfigError(f"{key}.{bound}: a finite number is required, got {value!r}")
        if kind == "int" and float(value) != int(value):
            raise ConfigError(f"{key}.{bound}: an integer is required for type int, got {value!r}")
    low, high = (float(low), float(high)) if kind == "float" else (int(low), int(high))
    if low >= high:
        raise ConfigError(f"{key}: low ({low:g}) must be below high ({high:g})")
    if log and low <= 0:
        raise ConfigError(f"{key}: a log scale needs positive bounds, got low={low:g}")
    grid = spec.get("grid")
    if grid is not None:
        if not isinstance(grid, Sequence) or isinstance(grid, str) or not grid:
            raise ConfigError(f"{key}.grid: a non-empty list of values is required")
        bad = [g for g in grid if not _is_number(g) or not low <= float(g) <= high]
        if bad:
            raise ConfigError(f"{key}.grid: values {bad} are not numbers within [{low:g}, {high:g}]")
        grid = tuple(float(g) if kind == "float" else int(g) for g in grid)
    return ParamSpec(name, kind, low=low, high=high, log=log, grid=grid)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


Condition = tuple[str, frozenset[str]]
"""(a config group, the options of it that read a parameter): a parameter with conditions is
sampled only in the trials whose choice of one of those groups is one of its options."""
Conditions = dict[str, tuple[Condition, ...]]
_INTERPOLATION = re.compile(r"\$\{([^${}]*)\}")
_DOTTED = re.compile(r"[A-Za-z_][\w]*(?:\.[A-Za-z_][\w]*)*")


def reads(node: Any, key: str) -> bool:
    """Whether an unresolved config node (plain containers) interpolates ``key`` or a node
    above it (``${env.sindy}`` reads ``env.sindy.alpha``), also inside a resolver's arguments."""
    if isinstance(node, Mapping):
        return any(reads(v, key) for v in node.values())
    if isinstance(node, (list, tuple)):
        return any(reads(v, key) for v in node)
    if not isinstance(node, str):
        return False
    for inner in _INTERPOLATION.findall(node):
        for ref in _DOTTED.findall(inner):
            if key == ref or key.startswith(ref + "."):
                return True
    return False


def conditions(space: SearchSpace, groups: Mapping[str, Mapping[str, Any]], key: str = "search.space") -> Conditions:
    """Which searched values depend on a group choice. ``groups`` maps each fit group (library,
    optimizer) to the options this study fits (a searched group's choices, else the run's own),
    each as its unresolved config in plain data. SINDy's values (``env.sindy.*``,
    ``env.poly_degree``) reach a fit only through these configs' interpolations, so a value
    that some options interpolate and others do not (``env.sindy.alpha``: STLSQ's ridge weight,
    which SR3 has no use for) is sampled only in the trials with a choice that reads it;
    otherwise TPE models a dimension that changes nothing. A value that no option of the study
    reads is a one-line ``ConfigError``: every trial would ignore it."""
    out: Conditions = {}
    for p in space:
        if p.name in GROUP_PARAMS or p.name in NN_PARAMS:
            continue
        target = PARAM_KEYS[p.name]
        readers = {g: frozenset(o for o, node in options.items() if reads(node, target)) for g, options in groups.items()}
        if any(r and r == frozenset(groups[g]) for g, r in readers.items()):
            continue  # read whatever the trial chooses
        conds = tuple((g, r) for g, r in readers.items() if r)
        if not conds:
            fitted = ", ".join(f"{g}={','.join(sorted(options))}" for g, options in groups.items())
            raise ConfigError(f"{key}.{p.name}: no config this study fits interpolates {target} ({fitted} as composed "
                              f"here), so no trial would use it: remove {p.name} from the space or fit a "
                              f"{' or '.join(groups)} that reads it")
        out[p.name] = conds
    return out


def suggest(trial: Any, space: SearchSpace, when: Conditions | None = None) -> dict[str, Any]:
    """Sample every parameter of ``space`` from an Optuna trial (pure sampler function): the
    group choices first, then each value unless ``when`` gives it conditions that no choice of
    the trial meets."""
    params: dict[str, Any] = {}
    when = when or {}
    for p in sorted(space, key=lambda p: p.name not in GROUP_PARAMS):  # stable: groups first
        if p.name in when and not any(str(params.get(group)) in options for group, options in when[p.name]):
            continue
        if p.kind == "categorical":
            params[p.name] = trial.suggest_categorical(p.name, list(p.choices or ()))
        elif p.kind == "int":
            params[p.name] = trial.suggest_int(p.name, int(p.low), int(p.high), log=p.log)
        else:
            params[p.name] = trial.suggest_float(p.name, float(p.low), float(p.high), log=p.log)
    return {p.name: params[p.name] for p in space if p.name in params}


def grid_values(space: SearchSpace, key: str = "search.space") -> dict[str, list[Any]]:
    """The grid for Optuna's GridSampler: every parameter needs grid values (categorical: its
    choices; int: every integer in range when no grid is given)."""
    out: dict[str, list[Any]] = {}
    for p in space:
        if p.grid is not None:
            out[p.name] = list(p.grid)
        elif p.kind == "int":
            out[p.name] = list(range(int(p.low), int(p.high) + 1))
        else:
            raise ConfigError(f"{key}.{p.name}.grid: the grid sampler needs grid values for every parameter")
    return out


def describe_space(space: SearchSpace) -> dict[str, dict[str, Any]]:
    """The space as plain data, keyed by parameter (stored with a study, compared on resume)."""
    return {p.name: p.describe() for p in space}


def space_differences(stored: Mapping[str, Any], requested: Mapping[str, Any]) -> list[str]:
    """Human-readable differences between two described spaces (empty when equal)."""
    diffs = []
    for name in sorted(set(stored) | set(requested)):
        if name not in stored:
            diffs.append(f"{name} added")
        elif name not in requested:
            diffs.append(f"{name} removed")
        else:
            for field in sorted(set(stored[name]) | set(requested[name])):
                a, b = stored[name].get(field), requested[name].get(field)
                if a != b:
                    diffs.append(f"{name}.{field} {a!r} -> {b!r}")
    return diffs


# ---------------------------------------------------------------------- export
def _format(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return repr(value) if isinstance(value, float) else str(value)


def to_overrides(params: Mapping[str, Any], choices: Mapping[str, str] | None = None) -> list[str]:
    """``sdrl-bench`` command-line overrides that reproduce ``params`` (plus group ``choices``
    such as env and collector, which come first)."""
    out = [f"{group}={name}" for group, name in (choices or {}).items() if group not in params]
    out += [f"{PARAM_KEYS[k]}={_format(v)}" for k, v in params.items()]
    return out


def experiment_pack(
    params: Mapping[str, Any],
    choices: Mapping[str, str],
    values: Mapping[str, Any] | None = None,
    header: str = "",
) -> str:
    """An ``# @package _global_`` experiment config (``+experiment=<name>``) that sets the group
    ``choices`` (env, collector, library, optimizer), the searched ``params`` and other plain
    ``values`` (dotted keys such as ``seed`` or ``n_transitions``)."""
    groups = {**choices, **{k: v for k, v in params.items() if k in GROUP_PARAMS}}
    body: dict[str, Any] = {"defaults": [{f"override /{g}": str(n)} for g, n in groups.items()]}
    dotted = {**(values or {}), **{PARAM_KEYS[k]: v for k, v in params.items() if k not in GROUP_PARAMS}}
    for key, value in dotted.items():
        node = body
        *path, leaf = key.split(".")
        for part in path:
            node = node.setdefault(part, {})
        node[leaf] = value
    lines = [f"# {line}" for line in header.strip().splitlines()]
    return "# @package _global_\n" + "\n".join(lines + [yaml.safe_dump(body, sort_keys=False)])
