"""Surrogate environments: a real env's task with a fitted dynamics model in place of its physics."""

from sdrl_bench.surrogate.env import SurrogateEnv
from sdrl_bench.surrogate.model_env import ModelEnv, resolve_spec
from sdrl_bench.surrogate.vec import SurrogateVecEnv

__all__ = ["ModelEnv", "SurrogateEnv", "SurrogateVecEnv", "resolve_spec"]
