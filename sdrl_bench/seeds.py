"""Every random stream of a run, named and derived from (run seed, purpose).

A run has one seed (``seed=`` on the command line). Everything random it does, real or
simulated, draws from a stream named by its *purpose*, derived through
``numpy.random.SeedSequence(entropy=run_seed, spawn_key=(purpose code,))``: two purposes of one
run, or one purpose of two runs, never share a stream. Numpy's ``SeedSequence`` is the field's
tool for independent streams; what it cannot give by itself is a guarantee that the *reset
seeds* handed to real environments (plain integers) never coincide, so those are laid out in
blocks:

* ``reset_seed(run_seed, purpose, i)``: the reset seed of the i-th real episode of a purpose,
  ``(block << BLOCK_BITS) + i`` with ``block`` a 40-bit number drawn from the stream (bit 39
  set) and ``i < 2 ** BLOCK_BITS``. Every reset seed is >= 2 ** 63: disjoint from the fixed,
  documented test-set seeds (``EnvSpec.test_set_recipe``: small integers such as 10000-10011)
  and from any seed a user types. ``tests/test_seeds.py`` derives the blocks of run seeds
  0..999 for every purpose and checks that no two coincide.
* ``generator(run_seed, purpose)``: a ``numpy.random.Generator`` on the stream (a surrogate's
  resets, step noise and event draws; exploration draws).
* ``int_seed(run_seed, purpose)``: a 32-bit integer from the stream, for libraries that take
  one (an SB3 agent's torch and numpy seeding, an Optuna sampler).

The purposes (their codes are part of the streams' identity: never renumber one):
"""

from __future__ import annotations

import numpy as np

PURPOSES: dict[str, int] = {
    "collect": 1,          # the model data's episodes (fit.n_transitions); exploration seeded per episode
    "reset_pool": 2,       # real resets whose first observations make a surrogate's default reset pool
    "curve_eval": 3,       # learning-curve evaluations during training (they may stop training)
    "final_eval": 4,       # the final evaluation of a trained agent (judges; nothing stops on it)
    "dyna_screen": 5,      # Dyna: each round's screen
    "dyna_final": 6,       # Dyna: confirmations (they stop the loop)
    "dyna_collect": 7,     # Dyna: the agent's collections (model data)
    "dyna_audit": 8,       # Dyna: the post-loop audit (judges)
    "real_train": 9,       # the real arm's training envs
    "surrogate": 10,       # a surrogate env's own draws (resets from its pool, step noise, events)
    "surrogate_eval": 11,  # evaluations inside a surrogate (the optimism gap)
    "agent": 12,           # the RL agent's own seeding (torch, numpy)
    "search": 13,          # an Optuna study's sampler (per worker: purpose of the worker's seed)
    "expert": 14,          # training an expert collector
    "events": 15,          # the learned event models' fits (cross-validation folds)
    "data_noise": 16,      # the fidelity study's observation noise on a cluster's data
    "fidelity_reference": 17,  # the fidelity study's reference policy in the real env
    "fidelity_onpolicy": 18,   # the fidelity study's agents' own real episodes (on-policy errors)
    "curve_confirm": 19,   # confirmations of a learning-curve evaluation at the threshold (they may stop training)
}
__doc__ += "".join(f"\n* ``{name}`` ({code})" for name, code in PURPOSES.items())

BLOCK_BITS = 24
"""Each (run seed, purpose) owns 2 ** 24 consecutive reset seeds."""
_BLOCK_TOP = 1 << 39


def sequence(run_seed: int, purpose: str) -> np.random.SeedSequence:
    """The stream of ``purpose`` in run ``run_seed``."""
    if purpose not in PURPOSES:
        raise KeyError(f"seeds: unknown purpose {purpose!r}; known: {', '.join(PURPOSES)}")
    if isinstance(run_seed, bool) or not isinstance(run_seed, (int, np.integer)) or run_seed < 0:
        raise ValueError(f"seeds: a run seed is an integer >= 0, got {run_seed!r}")
    return np.random.SeedSequence(entropy=int(run_seed), spawn_key=(PURPOSES[purpose],))


def generator(run_seed: int, purpose: str, *sub: int) -> np.random.Generator:
    """A generator on the stream (``sub``: a numbered sub-stream, e.g. one per Dyna round)."""
    seq = sequence(run_seed, purpose)
    if sub:
        seq = np.random.SeedSequence(entropy=seq.entropy, spawn_key=seq.spawn_key + tuple(int(s) for s in sub))
    return np.random.default_rng(seq)


def int_seed(run_seed: int, purpose: str) -> int:
    """A 32-bit integer seed from the stream."""
    return int(sequence(run_seed, purpose).generate_state(1, np.uint32)[0])


def block(run_seed: int, purpose: str) -> int:
    """The 40-bit block index of the purpose's reset seeds (bit 39 set)."""
    return int(sequence(run_seed, purpose).generate_state(1, np.uint64)[0]) >> 24 | _BLOCK_TOP


def reset_seed(run_seed: int, purpose: str, i: int = 0) -> int:
    """The real reset seed of episode ``i`` of ``purpose`` in run ``run_seed``."""
    if not 0 <= i < 1 << BLOCK_BITS:
        raise ValueError(f"seeds: episode index {i} outside the block of 2**{BLOCK_BITS} reset seeds")
    return (block(run_seed, purpose) << BLOCK_BITS) + int(i)


def episode_of(reset: int) -> int:
    """The episode index within its block (inverse of ``reset_seed`` for the index)."""
    return int(reset) & ((1 << BLOCK_BITS) - 1)
