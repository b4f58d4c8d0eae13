"""Transitions from a real environment: collection, CSV storage, hashing, held-out sets.

A dataset CSV has one row per transition: ``episode, step``, the state ``s_<name>`` (the spec's
states: with an observation map, angles rather than their cos and sin), the raw action ``a_<i>``
(a discrete action's index; the spec's ``action_encoding`` makes model inputs of it), the reward
``r``, the flags ``terminated, truncated`` and the next state ``ns_<name>``. A JSON sidecar (``<file>.stats.json``) holds the normalization statistics and
the content hash.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Callable

import gymnasium as gym
import numpy as np
import pandas as pd

from sdrl_bench import ConfigError
from sdrl_bench.envs.base import EnvSpec, Policy, TestSetRecipe

PolicyFactory = Callable[[EnvSpec, gym.Env], Policy]


@dataclass(frozen=True)
class Transitions:
    """(s_t, a_t, r_t, s_{t+1}, terminated, truncated) rows with their episode ids."""

    states: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_states: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    episode: np.ndarray
    step: np.ndarray

    def __len__(self) -> int:
        return len(self.states)

    def subset(self, mask_or_index: np.ndarray) -> Transitions:
        return Transitions(**{k: getattr(self, k)[mask_or_index] for k in _FIELDS})

    def to_frame(self, spec: EnvSpec) -> pd.DataFrame:
        values = np.column_stack(
            [self.episode, self.step, self.states, self.actions, self.rewards,
             self.terminated, self.truncated, self.next_states]
        )
        df = pd.DataFrame(values, columns=columns(spec))
        return df.astype({c: int for c in ("episode", "step", "terminated", "truncated")})

    def content_hash(self) -> str:
        """sha256 of the data (values as float64 little-endian, in column order)."""
        h = hashlib.sha256()
        for k in _FIELDS:
            h.update(np.ascontiguousarray(getattr(self, k), dtype="<f8").tobytes())
        return h.hexdigest()

    def normalization(self, spec: EnvSpec) -> dict[str, dict[str, float]]:
        """Per state variable mean and std (std of a constant column reported as 1)."""
        stats = {}
        for i, n in enumerate(spec.state_names):
            col = np.concatenate([self.states[:, i], self.next_states[:, i]])
            std = float(col.std())
            stats[n] = {"mean": float(col.mean()), "std": std if std > 0 else 1.0}
        return stats


_FIELDS = ("states", "actions", "rewards", "next_states", "terminated", "truncated", "episode", "step")


def concat(parts: list[Transitions]) -> Transitions:
    """The rows of ``parts`` one after the other (episode ids kept as they are)."""
    parts = [p for p in parts if p is not None and len(p)]
    if not parts:
        raise ValueError("concat: no rows")
    return Transitions(**{k: np.concatenate([getattr(p, k) for p in parts]) for k in _FIELDS})


def columns(spec: EnvSpec) -> list[str]:
    """Dataset CSV columns for ``spec``, in file order."""
    return (
        ["episode", "step"]
        + [f"s_{n}" for n in spec.state_names]
        + [f"a_{i}" for i in range(spec.raw_action_width)]
        + ["r", "terminated", "truncated"]
        + [f"ns_{n}" for n in spec.state_names]
    )


def save_csv(transitions: Transitions, spec: EnvSpec, path: str | Path) -> Path:
    """Write the CSV (full float precision) and its ``.stats.json`` sidecar."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    transitions.to_frame(spec).to_csv(path, index=False, float_format="%.17g")
    sidecar = {
        "env": spec.name,
        "n_transitions": len(transitions),
        "sha256": transitions.content_hash(),
        "normalization": transitions.normalization(spec),
    }
    Path(f"{path}.stats.json").write_text(json.dumps(sidecar, indent=2))
    return path


def load_csv(spec: EnvSpec, path: str | Path) -> Transitions:
    """Read a dataset CSV, checking columns and values; errors name the file."""
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"dataset.path: {path} is a folder, not a CSV file")
    if not path.is_file():
        raise ConfigError(f"dataset.path: no such file: {path}")
    try:
        df = pd.read_csv(path)
    except Exception as exc:  # pandas raises several types for unreadable files
        raise ConfigError(f"dataset.path: cannot read {path} as CSV ({exc.__class__.__name__})") from exc
    missing = [c for c in columns(spec) if c not in df.columns]
    if missing:
        raise ConfigError(f"dataset.path: {path} lacks columns {missing} for env '{spec.name}'")
    df = df[columns(spec)]
    bad = df.isna() | ~np.isfinite(df.apply(pd.to_numeric, errors="coerce").astype(float))
    if bad.to_numpy().any():
        row, col = np.argwhere(bad.to_numpy())[0]
        raise ConfigError(
            f"dataset.path: {path} has a missing or non-numeric value in column "
            f"'{df.columns[col]}' (data row {row + 1})"
        )
    if len(df) == 0:
        raise ConfigError(f"dataset.path: {path} has no rows")
    v = df.to_numpy(dtype=float)
    ns, na = len(spec.state_names), spec.raw_action_width
    for col, allowed in ((0, "a whole number >= 0"), (1, "a whole number >= 0"),
                         (3 + ns + na, "0 or 1"), (4 + ns + na, "0 or 1")):  # episode, step, terminated, truncated
        x = v[:, col]
        wrong = (x != np.floor(x)) | (x < 0) | ((x > 1) if allowed == "0 or 1" else False)
        if wrong.any():
            row = int(np.argmax(wrong))
            raise ConfigError(f"dataset.path: {path} column '{df.columns[col]}' must be {allowed}, got {x[row]:g} "
                              f"(data row {row + 1})")
    return Transitions(
        states=v[:, 2 : 2 + ns],
        actions=v[:, 2 + ns : 2 + ns + na],
        rewards=v[:, 2 + ns + na],
        next_states=v[:, 5 + ns + na :],
        terminated=v[:, 3 + ns + na].astype(bool),
        truncated=v[:, 4 + ns + na].astype(bool),
        episode=v[:, 0].astype(int),
        step=v[:, 1].astype(int),
    )


# ---------------------------------------------------------------------- collection
def heuristic_policy(spec: EnvSpec, env: gym.Env) -> Policy:
    """The env's hand-written controller (see each spec's ``heuristic_policy``)."""
    return spec.heuristic_policy(env)


def random_policy(spec: EnvSpec, env: gym.Env) -> None:
    """Uniform random actions: eps-greedy with any eps around "no policy" is random."""
    return None


def collect(
    spec: EnvSpec,
    policy_factory: PolicyFactory,
    n_transitions: int,
    epsilon: float,
    seed: int,
    max_steps_per_episode: int | None = None,
    first_episode: int = 0,
    wrap_env: Callable[[gym.Env], gym.Env] | None = None,
) -> Transitions:
    """Collect ``n_transitions`` from the real env with eps-greedy exploration.

    With probability ``epsilon`` the action is uniform random, else the policy's. Episodes are
    played back to back (the first reset with ``seed``, the next with ``seed + 1``, ...) until
    ``n_transitions`` rows are recorded; the last episode is cut there. Same arguments, same data.
    ``wrap_env`` wraps each real env (e.g. a step counter for the accounting).
    """
    if n_transitions <= 0:
        raise ConfigError(f"n_transitions must be positive, got {n_transitions}")
    if not 0.0 <= epsilon <= 1.0:
        raise ConfigError(f"collector.epsilon must be in [0, 1], got {epsilon}")
    rows: list[tuple] = []
    episode = first_episode
    while len(rows) < n_transitions:
        rows += _play_episode(
            spec, policy_factory, epsilon, seed + episode - first_episode, episode,
            min(n_transitions - len(rows), max_steps_per_episode or np.inf), wrap_env,
        )
        episode += 1
    return _stack(rows)


def _play_episode(spec, policy_factory, epsilon, seed, episode, limit, wrap_env=None) -> list[tuple]:
    env = spec.make_env()
    env = wrap_env(env) if wrap_env is not None else env
    env = TransitionRecorder(env, spec, episode)  # the rows: states (angles from their cos / sin), raw actions
    try:
        policy = policy_factory(spec, env)
        rng = np.random.default_rng(seed)
        obs, _ = env.reset(seed=seed)
        for _ in range(int(min(limit, spec.max_episode_steps + 1))):
            explore = policy is None or rng.random() < epsilon
            action = spec.random_action(rng, env) if explore else policy(obs)
            obs, _, term, trunc, _ = env.step(action)
            if term or trunc:
                break
        return env.rows
    finally:
        env.close()


class TransitionRecorder(gym.Wrapper):
    """Records every step of a real env as a dataset row (``Transitions`` layout), under the
    episode id ``episode`` (the next reset starts episode ``episode + 1``): real transitions
    spent on something else (an evaluation) become model data without being counted twice."""

    def __init__(self, env: gym.Env, spec: EnvSpec, episode: int):
        super().__init__(env)
        self.env_spec, self.rows, self.episode, self._t = spec, [], episode - 1, 0
        self._state = None

    def _coords(self, obs, reference=None):
        spec = self.env_spec
        return spec.coordinates(obs, reference=reference) if spec.maps_observations else np.asarray(obs)

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self.episode, self._t, self._state = self.episode + 1, 0, self._coords(obs)
        return obs, info

    def step(self, action):
        nxt, reward, term, trunc, info = self.env.step(action)
        # the next angle unwrapped next to the current one (the step's change stays continuous)
        next_state = self._coords(nxt, self._state)
        self.rows.append((self._state, np.atleast_1d(np.asarray(action, dtype=float)), reward, next_state, term, trunc,
                          self.episode, self._t))
        self._t, self._state = self._t + 1, self._coords(nxt)
        return nxt, reward, term, trunc, info


def recorded(recorders: list[TransitionRecorder]) -> Transitions | None:
    """The rows the recorders hold, in recorder order (None: no rows)."""
    rows = [r for rec in recorders for r in rec.rows]
    return _stack(rows) if rows else None


def _stack(rows: list[tuple]) -> Transitions:
    cols = list(zip(*rows, strict=True))
    return Transitions(
        states=np.asarray(cols[0], dtype=float),
        actions=np.asarray(cols[1], dtype=float),
        rewards=np.asarray(cols[2], dtype=float),
        next_states=np.asarray(cols[3], dtype=float),
        terminated=np.asarray(cols[4], dtype=bool),
        truncated=np.asarray(cols[5], dtype=bool),
        episode=np.asarray(cols[6], dtype=int),
        step=np.asarray(cols[7], dtype=int),
    )


_POLICIES: dict[str, PolicyFactory] = {"heuristic": heuristic_policy, "random": random_policy}


def held_out_test_set(spec: EnvSpec, recipe: TestSetRecipe | None = None) -> tuple[str, Transitions]:
    """The env's fixed, named held-out test set, (name, transitions); regenerated deterministically."""
    recipe = recipe or spec.test_set_recipe()
    rows: list[tuple] = []
    for i, (policy, eps) in enumerate(recipe.episodes):
        limit = recipe.max_steps or spec.max_episode_steps + 1
        rows += _play_episode(spec, _POLICIES[policy], eps, recipe.seed + i, i, limit)
    return recipe.name, _stack(rows)

