"""Surrogate environments: a real env's task with a fitted dynamics model in place of its physics."""

from sdrl_bench.surrogate.env import Surrogate, SurrogateEnv, resolve_spec
from sdrl_bench.surrogate.vec import SurrogateVecEnv

__all__ = ["Surrogate", "SurrogateEnv", "SurrogateVecEnv", "resolve_spec"]
