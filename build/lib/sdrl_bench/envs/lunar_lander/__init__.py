"""LunarLander-v3: spec (``spec``), task rules (``task``) and the compiled batched step (``kernels``)."""

from sdrl_bench.envs.lunar_lander.spec import LunarLanderContinuousSpec, LunarLanderSpec

__all__ = ["LunarLanderContinuousSpec", "LunarLanderSpec"]
