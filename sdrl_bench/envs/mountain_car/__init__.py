"""MountainCarContinuous-v0: its spec (bounds, wall, exact task) and its one-state kernel."""

from sdrl_bench.envs.mountain_car.spec import MountainCarSpec

__all__ = ["MountainCarSpec"]
