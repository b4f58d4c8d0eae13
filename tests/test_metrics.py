"""Metrics against hand-computed values; rollouts and divergence counting."""

from __future__ import annotations

import numpy as np
import pytest

from sdrl_bench.data import held_out_test_set
from sdrl_bench.envs.lunar_lander import LunarLanderSpec
from sdrl_bench.envs.mountain_car import MountainCarSpec
from sdrl_bench.fidelity import evaluate, rollouts
from sdrl_bench.metrics import mse, pearson, r2


def test_metrics_match_hand_computation():
    y = np.array([[1.0, 0.0], [2.0, 1.0], [3.0, 2.0], [4.0, 3.0]])
    p = np.array([[1.5, 0.0], [2.0, 2.0], [2.0, 2.0], [4.0, 4.0]])
    # column 0: errors .5, 0, -1, 0 -> mse 1.25/4; column 1: 0, 1, 0, 1 -> 0.5
    assert mse(y, p) == pytest.approx([0.3125, 0.5])
    # SST: column 0 = 5, column 1 = 5
    assert r2(y, p) == pytest.approx([1 - 1.25 / 5, 1 - 2 / 5])
    # Pearson of column 1: y = (0,1,2,3), p = (0,2,2,4): cov 5/..., computed by hand
    yc, pc = np.array([-1.5, -0.5, 0.5, 1.5]), np.array([-2.0, 0.0, 0.0, 2.0])
    assert pearson(y, p)[1] == pytest.approx(yc @ pc / np.sqrt((yc @ yc) * (pc @ pc)))
    assert pearson(y, p)[1] == pytest.approx(6 / np.sqrt(5 * 8))
    assert np.isnan(pearson(np.ones((3, 1)), np.arange(3.0)[:, None])[0])


class Copy:
    """Predicts that nothing changes."""

    def predict(self, x, u):
        return x


class Exploding:
    def predict(self, x, u):
        return 50.0 * x + 1.0


def test_copy_model_metrics_equal_direct_computation():
    spec = MountainCarSpec()
    _, test = held_out_test_set(spec)
    m = evaluate(Copy(), spec, test, norm_std={"x": 0.5, "v": 0.01}).metrics
    expected = np.mean((test.next_states - spec.round_obs(np.clip(test.states, spec.state_low, spec.state_high))) ** 2, axis=0)
    assert m["mse/x"] == pytest.approx(expected[0], rel=1e-12)
    assert m["mse_norm/v"] == pytest.approx(expected[1] / 0.01**2, rel=1e-12)


def test_rollout_final_state_and_divergence_fraction():
    spec = LunarLanderSpec()
    _, test = held_out_test_set(spec)
    true, pred, diverged = rollouts(Copy(), spec, test, k=10, stride=5)
    assert not diverged.any()
    # copying for 10 steps predicts the start state: compare with the recorded start
    starts = []
    for ep in np.unique(test.episode):
        idx = np.flatnonzero(test.episode == ep)
        starts += [idx[j] for j in range(0, len(idx) - 10 + 1, 5)]
    np.testing.assert_array_equal(pred, spec.round_obs(test.states[starts][:, :6]))
    np.testing.assert_array_equal(true, test.next_states[np.array(starts) + 9][:, :6])
    m = evaluate(Exploding(), spec, test).metrics
    assert m["rollout10/diverged_fraction"] == 1.0
    assert np.isnan(m.get("rollout10_mse/x", np.nan))


def test_smooth_subset_excludes_contact_and_terminal_transitions():
    spec = LunarLanderSpec()
    _, test = held_out_test_set(spec)
    m = evaluate(Copy(), spec, test, horizons=()).metrics
    legs = (test.states[:, 6:] != 0).any(axis=1) | (test.next_states[:, 6:] != 0).any(axis=1)
    smooth = ~legs & ~test.terminated
    assert 0.2 < smooth.mean() < 0.9
    assert m["one_step/smooth_fraction"] == pytest.approx(smooth.mean())
    err = (spec.round_obs(test.states[smooth, 5]) - test.next_states[smooth, 5]) ** 2
    assert m["mse_smooth/angvel"] == pytest.approx(err.mean(), rel=1e-12)
