"""A real env that counts its own steps: gymnasium's continuous MountainCar, registered as
``CountingMountainCarContinuous-v0``, with a class-level step counter (every instance adds to
it), and a record of the reset seeds it was given. The Dyna test checks the loop's accounting
against this counter, and the seeds test the runs' reset seeds against their streams; none of
the code under test reads either."""

from __future__ import annotations

import gymnasium as gym
from gymnasium.envs.classic_control.continuous_mountain_car import Continuous_MountainCarEnv

ENV_ID = "CountingMountainCarContinuous-v0"


class CountingMountainCar(Continuous_MountainCarEnv):
    steps = 0
    reset_seeds: list = []
    """Every seeded reset's seed, in order (unseeded resets go on from the last seed's generator)."""

    def step(self, action):
        CountingMountainCar.steps += 1
        return super().step(action)

    def reset(self, *, seed=None, options=None):
        if seed is not None:
            CountingMountainCar.reset_seeds.append(int(seed))
        return super().reset(seed=seed, options=options)


if ENV_ID not in gym.registry:
    gym.register(ENV_ID, entry_point=CountingMountainCar, max_episode_steps=999, reward_threshold=90.0)
