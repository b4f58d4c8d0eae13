"""Policy maps (the paper's Figures 1-2): a policy's action over 2-D slices of the state space.

The slices and the values held off their axes are the env spec's (``EnvSpec.map_slices``,
``policy_map_hold``): MountainCar's (position, velocity) grid, LunarLander's (x, y), (vx, vy)
and (angle, angular velocity) slices of a lander descending slowly above the pad.
"""

from __future__ import annotations

import textwrap
from dataclasses import dataclass

import matplotlib
import numpy as np
from matplotlib.colors import BoundaryNorm, ListedColormap, Normalize
from matplotlib.figure import Figure

from sdrl_bench.envs.base import EnvSpec



@dataclass
class PolicyMap:
    """Actions over one slice: ``actions[i, j]`` at (``ys[i]``, ``xs[j]``)."""

    x_name: str
    y_name: str
    xs: np.ndarray
    ys: np.ndarray
    actions: np.ndarray
    hold: dict[str, float]


def compute_maps(policy, spec: EnvSpec, resolution: int = 41) -> list[PolicyMap]:
    """Deterministic actions of ``policy.predict`` over each slice (first action component)."""
    hold = {n: float(spec.policy_map_hold.get(n, 0.0)) for n in spec.state_names}
    maps = []
    for xn, (x0, x1), yn, (y0, y1) in spec.map_slices():
        xs, ys = np.linspace(x0, x1, resolution), np.linspace(y0, y1, resolution)
        gx, gy = np.meshgrid(xs, ys)
        states = np.tile(np.array([hold[n] for n in spec.state_names], dtype=float), (gx.size, 1))
        states[:, spec.state_names.index(xn)] = gx.ravel()
        states[:, spec.state_names.index(yn)] = gy.ravel()
        obs = np.asarray(spec.observe(states), dtype=np.float32)  # what the policy sees (e.g. cos, sin of an angle)
        actions, _ = policy.predict(obs, deterministic=True)
        actions = np.asarray(actions, dtype=float).reshape(gx.size, -1)[:, 0]
        maps.append(PolicyMap(xn, yn, xs, ys, actions.reshape(gx.shape), {k: v for k, v in hold.items() if k not in (xn, yn)}))
    return maps


def agreement(a: list[PolicyMap], b: list[PolicyMap], discrete: bool) -> float:
    """Fraction of equal actions (discrete) or mean absolute action difference (continuous)."""
    x = np.concatenate([m.actions.ravel() for m in a])
    y = np.concatenate([m.actions.ravel() for m in b])
    return float(np.mean(x == y)) if discrete else float(np.mean(np.abs(x - y)))


def figure(maps_by_arm: dict[str, list[PolicyMap]], spec: EnvSpec, title: str) -> Figure:
    """One row per slice, one column per arm, one color scale for all panels."""
    arms = list(maps_by_arm)
    n_slices = len(next(iter(maps_by_arm.values())))
    # constrained layout: two-line panel titles and axis labels get their own room (no overlap
    # with the row above or below), the colorbar and the suptitle too
    fig = Figure(figsize=(4.0 * len(arms) + 1.2, 3.6 * n_slices + 0.6), layout="constrained")
    axes = fig.subplots(n_slices, len(arms), squeeze=False)
    if spec.n_discrete_actions:
        cmap = ListedColormap(["#d9d9d9", "#2c7bb6", "#fdae61", "#d7191c"][: spec.n_discrete_actions])
        norm = BoundaryNorm(np.arange(spec.n_discrete_actions + 1) - 0.5, cmap.N)
    else:
        cmap, norm = matplotlib.colormaps["coolwarm"], Normalize(-1.0, 1.0)
    for j, arm in enumerate(arms):
        for i, m in enumerate(maps_by_arm[arm]):
            ax = axes[i, j]
            im = ax.pcolormesh(m.xs, m.ys, m.actions, cmap=cmap, norm=norm, shading="auto")
            ax.set_xlabel(m.x_name)
            ax.set_ylabel(m.y_name)
            held = ", ".join(f"{k}={v:g}" for k, v in m.hold.items())
            held = "\n".join(textwrap.wrap(held, 44))  # the held values of LunarLander fit the panel's width
            ax.set_title(f"{arm}" + (f"\n{held}" if held else ""), fontsize=8)
    cbar = fig.colorbar(im, ax=axes.ravel().tolist(), shrink=0.9)
    if spec.n_discrete_actions:
        cbar.set_ticks(range(spec.n_discrete_actions))
        cbar.set_ticklabels(spec.discrete_action_labels())
    else:
        cbar.set_label(f"action: {spec.action_names[0]}")  # the maps show the first action component
    fig.suptitle(title)
    return fig
