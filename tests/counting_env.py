"""A real env that counts its own steps: gymnasium's continuous MountainCar, registered as
``CountingMountainCarContinuous-v0``, with a class-level step counter (every instance adds to
it). The Dyna test checks the loop's accounting against this counter, which none of the code
under test reads."""

from __future__ import annotations

import gymnasium as gym
from gymnasium.envs.classic_control.continuous_mountain_car import Continuous_MountainCarEnv

ENV_ID = "CountingMountainCarContinuous-v0"


class CountingMountainCar(Continuous_MountainCarEnv):
    steps = 0

    def step(self, action):
        CountingMountainCar.steps += 1
        return super().step(action)


if ENV_ID not in gym.registry:
    gym.register(ENV_ID, entry_point=CountingMountainCar, max_episode_steps=999, reward_threshold=90.0)
