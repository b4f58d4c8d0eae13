"""The expert collector's per-step action (``experts.deterministic_policy``) against SB3's own
``predict(obs, deterministic=True)``: the same actions, bit for bit, for the three kinds of
policy the packs' experts are (a categorical PPO, a Gaussian PPO clipped to its Box, a squashed
SAC unscaled to its Box)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from stable_baselines3 import PPO, SAC

from sdrl_bench.rl.experts import act_only_load, deterministic_policy


@pytest.mark.parametrize("env_id,algo,discrete", [
    ("LunarLander-v3", PPO, True),
    ("Pendulum-v1", PPO, False),
    ("MountainCarContinuous-v0", SAC, False),
])
def test_the_collectors_action_is_sb3s_predict(env_id, algo, discrete):
    env = gym.make(env_id)
    model = algo("MlpPolicy", env, seed=3, device="cpu", policy_kwargs={"net_arch": [32, 32]})
    # weights away from their initialisation, so the actions spread over the space
    noise = np.random.default_rng(0)
    with torch.no_grad():
        for p in model.policy.parameters():
            p.add_(torch.as_tensor(0.5 * noise.standard_normal(tuple(p.shape)), dtype=torch.float32))
    rng = np.random.default_rng(1)
    low, high = env.observation_space.low, env.observation_space.high
    obs = rng.uniform(np.maximum(low, -3), np.minimum(high, 3), size=(400, *low.shape)).astype(np.float32)
    act = deterministic_policy(model, discrete)
    ours = [act(o) for o in obs]
    sb3 = [model.predict(o, deterministic=True)[0] for o in obs]
    if discrete:
        assert all(isinstance(a, int) for a in ours)
        assert ours == [int(a) for a in sb3] and len(set(ours)) > 1
    else:
        assert all(a.shape == env.action_space.shape and a.dtype == np.float32 for a in ours)
        assert np.array_equal(np.stack(ours), np.stack(sb3))
        spread = np.ptp(np.stack(ours))
        assert spread > 0.1 and np.all(np.stack(ours) <= env.action_space.high)


@pytest.mark.parametrize("env_id,algo", [("LunarLander-v3", PPO), ("MountainCarContinuous-v0", SAC)])
def test_an_expert_loaded_to_act_has_sb3s_weights_and_actions_and_refuses_to_train(tmp_path, env_id, algo):
    env = gym.make(env_id)
    saved = algo("MlpPolicy", env, seed=5, device="cpu", policy_kwargs={"net_arch": [16]},
                 **({"n_steps": 64, "batch_size": 32} if algo is PPO else {"learning_starts": 10}))
    saved.learn(64)  # optimizer states in the archive (SAC: its entropy coefficient's optimizer too)
    saved.save(tmp_path / "expert.zip")
    ours, sb3 = act_only_load(algo, tmp_path / "expert.zip"), algo.load(tmp_path / "expert.zip", device="cpu")
    a, b = ours.policy.state_dict(), sb3.policy.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    obs = np.stack([env.reset(seed=i)[0] for i in range(50)])
    discrete = algo is PPO
    assert np.array_equal(np.stack([deterministic_policy(ours, discrete)(o) for o in obs]),
                          np.stack([deterministic_policy(sb3, discrete)(o) for o in obs]))
    if algo is SAC:  # an optimizer SB3 builds itself keeps its state
        assert torch.equal(ours.log_ent_coef, sb3.log_ent_coef) and ours.log_ent_coef.item() != 0.0
        a, b = ours.ent_coef_optimizer.state_dict()["state"], sb3.ent_coef_optimizer.state_dict()["state"]
        assert a.keys() == b.keys() == {0} and all(torch.equal(a[0][k], b[0][k]) for k in b[0])
    optimizer = ours.policy.optimizer if algo is PPO else ours.actor.optimizer  # SAC: one per network
    with pytest.raises(RuntimeError, match="loaded to act only"):
        optimizer.step()


def test_observations_that_are_no_box_go_through_sb3s_predict():
    """A Discrete observation is one-hot encoded by SB3's preprocessing: the collector's action
    is then ``predict``'s own."""
    env = gym.make("FrozenLake-v1")
    model = PPO("MlpPolicy", env, seed=2, device="cpu", policy_kwargs={"net_arch": [8]})
    with torch.no_grad():
        for p in model.policy.parameters():
            p.add_(torch.linspace(-2, 2, p.numel()).reshape(p.shape))
    act = deterministic_policy(model, True)
    ours = [act(np.int64(s)) for s in range(16)]
    assert ours == [int(model.predict(np.int64(s), deterministic=True)[0]) for s in range(16)]
    assert all(isinstance(a, int) for a in ours)
