"""An env described by YAML and plain functions: dotted paths resolved once, specs found by name.

A spec's task can be given as functions instead of an ``EnvSpec`` subclass (as mbrl-lib injects
``reward_fn`` and ``termination_fn`` into its model env): ``env.spec.reward_fn:
my_envs.task.reward`` names a module-level function that ``resolve`` imports at config time, so a
missing module or a typo fails in one line naming the key and the cause, before any env step.

``spec_from_config`` finds ``env/<name>.yaml`` in the user's config directories and the package's
own, and builds the spec of its ``spec:`` node without Hydra (the node is plain data and a
``_target_``): ``gym.make("sdrl/Surrogate-v0", spec="pendulum")`` knows every env of the config
tree, the user's included (``config_dir=`` or ``$SDRL_BENCH_CONFIG_DIR``).
"""

from __future__ import annotations

import importlib
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sdrl_bench import ConfigError

CONFIG_DIR_VAR = "SDRL_BENCH_CONFIG_DIR"
"""Environment variable: user config directories (``os.pathsep``-separated) searched by name."""


def one_line(exc: BaseException) -> str:
    """An exception as one line: its type, message and, for an error raised in a user's file,
    where (the innermost frame outside importlib)."""
    text = " ".join(str(exc).split())
    where = ""
    tb = exc.__traceback__
    frames = []
    while tb is not None:
        frames.append(tb.tb_frame.f_code.co_filename + f":{tb.tb_lineno}")
        tb = tb.tb_next
    user = [f for f in frames if "importlib" not in f and "/sdrl_bench/" not in f and "/hydra/" not in f]
    if user and not isinstance(exc, SyntaxError):  # a SyntaxError names its file and line itself
        where = f" (at {user[-1]})"
    return (f"{type(exc).__name__}: {text}" if text else type(exc).__name__) + where


def import_object(path: str, key: str) -> Any:
    """The object at dotted ``path`` (``pkg.module.name`` or ``pkg.module:name``); a failure is
    a ``ConfigError`` naming ``key``, the path and the cause (the module's own import error)."""
    if not isinstance(path, str) or not path.strip():
        raise ConfigError(f"{key}: expected a dotted path 'package.module.function', got {path!r}")
    module_name, sep, attr = path.partition(":")
    if not sep:
        module_name, _, attr = path.rpartition(".")
    if not module_name or not attr:
        raise ConfigError(f"{key}: {path!r} is not a dotted path 'package.module.function'")
    try:
        module = importlib.import_module(module_name)
    except Exception as exc:  # a user module may raise anything while importing
        raise ConfigError(f"{key}: cannot import module '{module_name}' for {path!r}: {one_line(exc)}") from exc
    obj = module
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise ConfigError(f"{key}: module '{module_name}' ({getattr(module, '__file__', '?')}) has no '{attr}'")
        obj = getattr(obj, part)
    return obj


def resolve(value: str | Callable | None, key: str) -> Callable | None:
    """A task function from a dotted path (or a callable as it is); None stays None."""
    if value is None or callable(value):
        return value
    obj = import_object(value, key)
    if not callable(obj):
        raise ConfigError(f"{key}: {value!r} is a {type(obj).__name__}, not a function")
    return obj


# ---------------------------------------------------------------------- numpy or jax
def _is_jax(value: Any) -> bool:
    jax = sys.modules.get("jax")  # never imported here: a jax array means the caller imported jax
    return jax is not None and isinstance(value, jax.Array)


def array_namespace(*arrays: Any) -> Any:
    """The array module for ``arrays``: ``jax.numpy`` when any of them is a jax array (or a
    tracer inside ``jax.jit``; a jax PRNG key too), else ``numpy``. A task function written
    with ``xp = array_namespace(states, ...)`` runs on both; its numpy path is plain numpy."""
    if any(_is_jax(a) for a in arrays):
        import jax.numpy as jnp  # noqa: PLC0415  (already imported: the arrays are jax's)

        return jnp
    return np


def round_through(values: Any, dtype: Any) -> Any:
    """``values`` rounded to ``dtype`` (a float type) and back to float64, in their own array module.

    On numpy: ``astype(dtype).astype(float64)``. On jax arrays and tracers:
    ``jax.lax.reduce_precision`` to ``dtype``'s exponent and mantissa bits: the same bits as jax's
    own pair of conversions on the CPU, and as numpy's but for float32's subnormals (below 1.2e-38),
    which XLA's CPU flushes to zero either way; but an op that XLA keeps: inside ``jit`` its GPU
    compiler removes a float64 -> float32 -> float64 pair of conversions (excess precision, allowed
    by default), and the compiled step then skipped the real env's float32 observation
    (docs/compiled.md, On a GPU). To float64: a float64 copy."""
    if not np.issubdtype(np.dtype(dtype), np.floating):
        raise TypeError(f"round_through: {dtype!r} is not a float type")
    xp = array_namespace(values)
    values = xp.asarray(values, dtype=xp.float64)
    if np.dtype(dtype) == np.float64:
        return values.copy() if xp is np else values
    if xp is np:
        return values.astype(dtype).astype(np.float64)
    import jax  # noqa: PLC0415  (already imported: the values are jax's)

    info = np.finfo(dtype)
    return jax.lax.reduce_precision(values, exponent_bits=info.nexp, mantissa_bits=info.nmant)


def wrap_angle(values: Any) -> Any:
    """Angles wrapped to [-pi, pi) in their own array module (``envs.base.wrap_angle``, for numpy
    and jax arrays: the same operations, so numpy gives the same bits)."""
    xp = array_namespace(values)
    return (xp.asarray(values) + np.pi) % (2 * np.pi) - np.pi


def split_rng(rng: Any, n: int) -> tuple:
    """``n`` random sources from ``rng`` for ``n`` draws in a row: a numpy ``Generator`` n times
    (its draws follow one another, as before), a jax PRNG key split into ``n`` keys."""
    if _is_jax(rng):
        import jax  # noqa: PLC0415  (already imported: rng is a jax key)

        return tuple(jax.random.split(rng, n))
    return (rng,) * n


def uniform(rng: Any, low: Any, high: Any, shape: int | tuple) -> Any:
    """U[low, high) of ``shape`` from a numpy ``Generator`` (``rng.uniform``) or a jax PRNG key."""
    if _is_jax(rng):
        import jax  # noqa: PLC0415

        shape = (shape,) if isinstance(shape, int) else tuple(shape)
        return jax.random.uniform(rng, shape, minval=low, maxval=high)
    return rng.uniform(low, high, shape)


def standard_normal(rng: Any, shape: int | tuple) -> Any:
    """N(0, 1) of ``shape`` from a numpy ``Generator`` (``rng.standard_normal``) or a jax PRNG key."""
    if _is_jax(rng):
        import jax  # noqa: PLC0415

        shape = (shape,) if isinstance(shape, int) else tuple(shape)
        return jax.random.normal(rng, shape)
    return rng.standard_normal(shape)


# ---------------------------------------------------------------------- specs by name
def config_dirs(extra: Sequence[str | Path] = ()) -> list[Path]:
    """Where env configs are looked up: ``extra``, then ``$SDRL_BENCH_CONFIG_DIR``, then the package's."""
    dirs = [Path(d) for d in extra]
    dirs += [Path(d) for d in os.environ.get(CONFIG_DIR_VAR, "").split(os.pathsep) if d]
    dirs.append(Path(__file__).resolve().parent.parent / "conf")
    return dirs


def spec_from_config(name: str, dirs: Sequence[str | Path] = ()) -> Any | None:
    """The spec of ``env/<name>.yaml`` in the first config dir that has one (None: no such file)."""
    import yaml  # PyYAML, a dependency of hydra-core and of this package

    for d in config_dirs(dirs):
        path = d / "env" / f"{name}.yaml"
        if path.is_file():
            break
    else:
        return None
    try:
        node = (yaml.safe_load(path.read_text()) or {}).get("spec")
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"spec '{name}': cannot read {path}: {one_line(exc)}") from exc
    if not isinstance(node, dict) or "_target_" not in node:
        raise ConfigError(f"spec '{name}': {path} has no 'spec:' mapping with a _target_")
    kwargs = {k: v for k, v in node.items() if k != "_target_"}
    if any(isinstance(v, str) and "${" in v for v in kwargs.values()):
        raise ConfigError(f"spec '{name}': {path} uses interpolations in spec:, which need Hydra; pass an EnvSpec")
    cls = import_object(node["_target_"], f"{path}: spec._target_")
    try:
        return cls(**kwargs)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from exc
    except TypeError as exc:
        raise ConfigError(f"{path}: spec: {one_line(exc)}") from exc


# ---------------------------------------------------------------------- what the report knows of an env
def references(dirs: Sequence[str | Path] = ()) -> dict[str, dict]:
    """{env name: the mapping of ``reference/<name>.yaml``} over the config dirs (the first dir
    that has a name wins): the paper's figures for the env, the paper pack's choices, and notes
    that only the env explains, for the report to set beside the env's runs. A user's env gets
    the same by putting ``reference/<name>.yaml`` in its config dir."""
    import yaml  # PyYAML, a dependency of hydra-core and of this package

    out: dict[str, dict] = {}
    for d in config_dirs(dirs):
        for path in sorted((d / "reference").glob("*.yaml")) if (d / "reference").is_dir() else ():
            if path.stem in out:
                continue
            try:
                node = yaml.safe_load(path.read_text()) or {}
            except (OSError, yaml.YAMLError) as exc:
                raise ConfigError(f"reference '{path.stem}': cannot read {path}: {one_line(exc)}") from exc
            if not isinstance(node, dict):
                raise ConfigError(f"reference '{path.stem}': {path} is not a mapping")
            out[path.stem] = node
    return out
