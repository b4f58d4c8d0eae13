"""Policy maps over state slices and their agreement score."""

from __future__ import annotations

import numpy as np
import pytest

from sdrl_bench.envs.lunar_lander import LunarLanderSpec
from sdrl_bench.envs.mountain_car import MountainCarSpec
from sdrl_bench.rl.policy_maps import agreement, compute_maps, figure


class SignOfVelocity:
    def predict(self, obs, deterministic=True):
        return np.where(obs[:, 1:2] >= 0, 1.0, -1.0), None


class Half:
    def predict(self, obs, deterministic=True):
        return np.full((len(obs), 1), 0.5), None


class MainEngineBelow:
    """Discrete: main engine (2) when y < 0.5, else noop (0)."""

    def predict(self, obs, deterministic=True):
        return np.where(obs[:, 1] < 0.5, 2, 0), None


def test_mountain_car_map_covers_the_state_grid():
    (m,) = compute_maps(SignOfVelocity(), MountainCarSpec(), resolution=11)
    assert (m.x_name, m.y_name) == ("x", "v")
    assert m.xs[0] == pytest.approx(-1.2) and m.ys[-1] == pytest.approx(0.07)
    assert np.all(m.actions[m.ys >= 0] == 1.0) and np.all(m.actions[m.ys < 0] == -1.0)


def test_continuous_agreement_is_mean_absolute_difference():
    spec = MountainCarSpec()
    a, b = compute_maps(SignOfVelocity(), spec, 11), compute_maps(Half(), spec, 11)
    # |1 - 0.5| = 0.5 on the upper rows, |-1 - 0.5| = 1.5 on the lower: 6 of 11 rows have v >= 0
    assert agreement(a, b, discrete=False) == pytest.approx((6 * 0.5 + 5 * 1.5) / 11)
    assert agreement(a, a, discrete=False) == 0.0


def test_lunar_lander_slices_and_discrete_agreement():
    spec = LunarLanderSpec()
    maps = compute_maps(MainEngineBelow(), spec, resolution=21)
    assert [(m.x_name, m.y_name) for m in maps] == [("x", "y"), ("vx", "vy"), ("angle", "angvel")]
    # y varies only in the first slice; elsewhere y is held at 0.7 (noop everywhere)
    assert np.all(maps[1].actions == 0) and maps[1].hold["y"] == 0.7
    noop = [type(m)(m.x_name, m.y_name, m.xs, m.ys, np.zeros_like(m.actions), m.hold) for m in maps]
    frac_main = np.mean(maps[0].actions == 2)
    assert agreement(maps, noop, discrete=True) == pytest.approx(1 - frac_main / 3)
    fig = figure({"a": maps, "b": noop}, spec, "t")
    assert len(fig.axes) == 7  # 3 slices x 2 arms + the shared color bar


def test_lunar_lander_figure_titles_and_labels_do_not_overlap():
    """Every panel's title, tick labels and axis labels (its tight box) stay clear of every
    other panel's, and of the suptitle: no title over the row above, no label under the next."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    spec = LunarLanderSpec()
    maps = compute_maps(MainEngineBelow(), spec, resolution=11)
    fig = figure({"trained in the real env": maps, "trained in the sindy surrogate": maps}, spec,
                 "lunar_lander policy maps (fraction of equal actions: 1.000)")
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    panels = fig.axes[:6]
    boxes = [ax.get_tightbbox(renderer) for ax in panels]
    for i in range(len(boxes)):
        for j in range(i + 1, len(boxes)):
            ov = boxes[i].intersection(boxes[i], boxes[j])
            assert ov is None or ov.width * ov.height < 1.0, (i, j)
    sup = fig._suptitle.get_window_extent(renderer)
    assert all(sup.y0 >= b.y1 - 0.5 for b in boxes)
