"""Per-environment knowledge: specs with bounds, action encodings and held-out test sets."""

from sdrl_bench.envs.base import EnvSpec, Policy, TestSetRecipe
from sdrl_bench.envs.lunar_lander.spec import LunarLanderContinuousSpec, LunarLanderSpec
from sdrl_bench.envs.mountain_car import MountainCarSpec

__all__ = [
    "EnvSpec",
    "LunarLanderContinuousSpec",
    "LunarLanderSpec",
    "MountainCarSpec",
    "Policy",
    "TestSetRecipe",
]
