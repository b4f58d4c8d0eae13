"""Per-environment knowledge. This package's generic modules (``base``: the spec every env
gives; ``task``: what a surrogate needs of it; ``functional``: envs from YAML and plain
functions) are all that code outside ``envs/`` may import; each env's own package
(``envs/lunar_lander``, ``envs/mountain_car``, ...) is reached through its config's ``_target_``."""

from sdrl_bench.envs.base import EnvSpec, Policy, TestSetRecipe

__all__ = ["EnvSpec", "Policy", "TestSetRecipe"]
