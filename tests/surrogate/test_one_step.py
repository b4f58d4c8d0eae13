"""One surrogate step everywhere: the single env, the vector env (its one-state path and its
batched path, before and after a model swap) and the evaluation inside a surrogate follow the
same trajectories, rewards and learned events from the same seed, with step noise, the
ensemble's pessimism and a learned event model all on (LunarLander: the flight law with its
engine noise and 5 members, the touchdown event drawn at 50%)."""

from __future__ import annotations

import numpy as np
import pytest
from gymnasium.envs.box2d.lunar_lander import heuristic

from helpers import compose_cfg
from sdrl_bench.cli.build import build_fit_job
from sdrl_bench.pipeline import fit_dynamics
from sdrl_bench.rl.transfer import evaluate_surrogate
from sdrl_bench.surrogate.env import SurrogateEnv
from sdrl_bench.surrogate.events import EventModel
from sdrl_bench.surrogate.model_env import ModelEnv
from sdrl_bench.surrogate.vec import SurrogateVecEnv


def _coin_flip(event) -> EventModel:
    """An event model that says crash with probability 1/2 whatever the features."""
    from sklearn.dummy import DummyClassifier
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    x = np.zeros((2, len(event.feature_names)))
    clf = make_pipeline(StandardScaler(), DummyClassifier(strategy="prior")).fit(x, [0, 1])
    return EventModel(event.name, event.outcome_names, event.feature_names, clf, 2, {"survive": 1, "crash": 1}, 0.5, 0.69)


@pytest.fixture(scope="module")
def fits():
    """Two flight-law fits (seeds 0 and 1), with their noise and members; pessimism without a
    free band, so that every flight step is penalized."""
    out = []
    for seed in (0, 1):
        cfg = compose_cfg("env=lunar_lander", "collector=heuristic", "n_transitions=1500", f"seed={seed}",
                          "env.spec.uncertainty.free=0.0")
        out.append(fit_dynamics(build_fit_job(cfg)))
    spec = out[0].job.spec
    events = {"touchdown": _coin_flip(spec.task.events[0])}
    return out[0], out[1], spec, events


class Heuristic:
    """gymnasium's heuristic lander as a ``predict`` policy (deterministic in the observation)."""

    def __init__(self, spec):
        self.env = spec.make_env().unwrapped

    def predict(self, obs, deterministic=True):
        obs = np.asarray(obs)
        if obs.ndim == 1:
            return np.asarray(heuristic(self.env, obs)), None
        return np.array([heuristic(self.env, o) for o in obs]), None


def _single(core: ModelEnv, seed: int, policy, swap=None, steps: int = 1000):
    env = SurrogateEnv(core)
    obs, _ = env.reset(seed=seed)
    traj, rewards, events = [obs], [], []
    for t in range(steps):
        if swap is not None and t == swap[0]:
            core.swap(*swap[1:])
        obs, r, term, trunc, _ = env.step(policy.predict(obs)[0])
        traj.append(obs), rewards.append(r)
        events.append({k: (v[1].tolist()) for k, v in core.last_events.items()})
        core.last_events = {}
        if term or trunc:
            break
    return np.array(traj), np.array(rewards), events, (term, trunc)


def _vector(venv: SurrogateVecEnv, seed: int, policy, swap=None, steps: int = 1000):
    venv.seed(seed)
    obs = venv.reset()
    traj, rewards, events = [obs[0]], [], []
    for t in range(steps):
        if swap is not None and t == swap[0]:
            venv.swap_model(*swap[1:])
        obs, r, done, infos = venv.step(policy.predict(obs)[0])
        traj.append(infos[0]["terminal_observation"] if done[0] else obs[0]), rewards.append(r[0])
        events.append({k: (v[1].tolist()) for k, v in venv.surrogate.last_events.items()})
        venv.surrogate.last_events = {}
        if done[0]:
            return np.array(traj), np.array(rewards), events, (not infos[0]["TimeLimit.truncated"], infos[0]["TimeLimit.truncated"])
    return np.array(traj), np.array(rewards), events, (False, False)


@pytest.mark.parametrize("swap_at", [None, 40])
def test_single_vector_and_evaluator_step_alike(fits, swap_at):
    fit0, fit1, spec, events = fits
    policy = Heuristic(spec)
    swap = None if swap_at is None else (swap_at, fit1.model, events, 99)
    seen_event, seen_penalty = False, False
    for seed in range(6):
        single = _single(ModelEnv(fit0.model, spec, events=events, seed=0), seed, policy, swap)
        scalar = _vector(SurrogateVecEnv(fit0.model, spec, 1, seed=0, events=events), seed, policy, swap)
        batched = _vector(SurrogateVecEnv(fit0.model, spec, 1, seed=0, events=events, scalar_max_envs=0), seed, policy, swap)
        # the one-state path of the vector env is the single env's: bit for bit (SB3's float32 rewards)
        assert np.array_equal(single[0], scalar[0]) and np.array_equal(single[1].astype(np.float32), scalar[1])
        assert single[2] == scalar[2] and single[3] == scalar[3]
        # the batched path: the same step in numpy and the compiled kernel (float32 observations)
        assert len(batched[0]) == len(single[0]) and np.abs(batched[0] - single[0]).max() <= 1e-12
        assert np.allclose(batched[1], single[1].astype(np.float32), rtol=1e-6, atol=1e-6)
        assert batched[2] == single[2] and batched[3] == single[3]
        seen_event |= any(e for e in single[2])
        # the pessimism is on: flight rewards are below the task's own reward
        plain = _single(ModelEnv(fit0.model, spec, events=events, seed=0, penalty=False), seed, policy, swap)
        seen_penalty |= bool(len(plain[1]) == len(single[1]) and np.all(single[1] <= plain[1] + 1e-12)
                             and np.any(single[1] < plain[1] - 1e-6))
        if swap_at is None:  # evaluation inside a surrogate: the same episode, the same return
            got = evaluate_surrogate(policy, ModelEnv(fit0.model, spec, events=events, seed=0), 1, seed)
            assert got[0] == pytest.approx(single[1].sum(), abs=1e-9)
    assert seen_event and seen_penalty


def test_a_swap_keeps_noise_pessimism_and_kernels(fits):
    """``swap_model`` rebuilds the step with the flags the env was built with (a vector env
    built without noise stays without noise after a refit)."""
    fit0, fit1, spec, events = fits
    quiet = SurrogateVecEnv(ModelEnv(fit0.model, spec, noise=False, penalty=False, fused=False), n_envs=16, seed=1)
    quiet.swap_model(fit1.model, events, seed=2)
    core = quiet.surrogate
    assert core._chol is None and core._members is None and core._step_batch is None and core.events == events
    loud = SurrogateVecEnv(fit0.model, spec, 16, seed=1)
    loud.swap_model(fit1.model, None, seed=2)
    sur = loud.surrogate
    z = sur.model_inputs(sur.initial_states(3), np.zeros(3, dtype=int))
    assert sur._chol is not None and sur._members(z).shape[0] == 5 and sur._step_batch is not None
