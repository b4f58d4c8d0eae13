"""Surrogate environments: a real env's task with a fitted dynamics model in place of its physics.

The names below load on first use (PEP 562): ``SurrogateVecEnv`` imports SB3 and torch (about 1 s),
which a fit that only reads ``surrogate.events`` does not need."""

import importlib

_WHERE = {"ModelEnv": "model_env", "resolve_spec": "model_env", "SurrogateEnv": "env", "SurrogateVecEnv": "vec"}
__all__ = list(_WHERE)


def __getattr__(name: str):
    if name in _WHERE:
        return getattr(importlib.import_module(f"sdrl_bench.surrogate.{_WHERE[name]}"), name)
    raise AttributeError(f"module 'sdrl_bench.surrogate' has no attribute {name!r}")
