"""Independent seeds: every random stream of a run is named by its purpose and derived from the
run seed (``sdrl_bench.seeds``); no real reset seed is shared between two (run seed, purpose)
pairs, nor with a fixed test set. Checked by derivation for run seeds 0..999 and every purpose,
and on the reset seeds real runs actually used."""

from __future__ import annotations

import numpy as np
import pytest

from helpers import compose_cfg
from sdrl_bench import seeds
from sdrl_bench.envs.base import find_spec


def _test_set_seeds() -> set[int]:
    from pathlib import Path

    out = set()
    for path in (Path(seeds.__file__).parent / "conf" / "env").glob("*.yaml"):
        recipe = find_spec(path.stem).test_set_recipe()
        out |= {recipe.seed + i for i in range(len(recipe.episodes))}
    return out


def test_no_reset_seed_is_shared_between_runs_purposes_or_test_sets():
    blocks = np.array([[seeds.block(r, p) for p in seeds.PURPOSES] for r in range(1000)], dtype=object)
    flat = [int(b) for b in blocks.ravel()]
    # each (run seed, purpose) owns the reset seeds [block << 24, (block + 1) << 24): disjoint iff
    # the blocks differ
    assert len(set(flat)) == len(flat) == 1000 * len(seeds.PURPOSES)
    lowest = min(flat) << seeds.BLOCK_BITS
    fixed = _test_set_seeds()
    assert fixed and max(fixed) < lowest and lowest >= 2**63
    # the layout: episode i of a purpose is block + i, inside the block
    r0 = seeds.reset_seed(7, "collect")
    assert [seeds.reset_seed(7, "collect", i) - r0 for i in range(3)] == [0, 1, 2]
    assert seeds.episode_of(seeds.reset_seed(7, "dyna_screen", 12345)) == 12345
    with pytest.raises(ValueError):
        seeds.reset_seed(7, "collect", 2**seeds.BLOCK_BITS)
    with pytest.raises(KeyError):
        seeds.reset_seed(7, "nonsense")


def test_generators_of_two_purposes_or_runs_differ_and_repeat():
    a = seeds.generator(3, "surrogate", 1).random(4)
    assert np.array_equal(a, seeds.generator(3, "surrogate", 1).random(4))
    for other in (seeds.generator(3, "surrogate", 2), seeds.generator(4, "surrogate", 1), seeds.generator(3, "collect")):
        assert not np.array_equal(a, other.random(4))
    assert seeds.int_seed(0, "agent") != seeds.int_seed(1, "agent") and 0 <= seeds.int_seed(0, "agent") < 2**32


def test_two_run_seeds_share_no_real_data_or_reset_seed(store):
    """Two tiny transfer runs (seeds 0 and 1, both arms, real env = a counting MountainCar that
    records its reset seeds): every reset seed a run gave the real env is one of its own
    streams', the two runs share none, and their model data share no transition."""
    import counting_env
    from sdrl_bench.cli.build import build_fit_job
    from sdrl_bench.cli.train import run_train

    used, data = {}, {}
    for seed in (0, 1):
        cfg = compose_cfg("experiment=quick_mountain_car", f"seed={seed}", f"tracking.uri={store}",
                          f"+env.spec.gym_id=counting_env:{counting_env.ENV_ID}", "rl.surrogate_steps=64",
                          "rl.real_steps=64", "rl.eval_every=64", "rl.eval_episodes=2", "rl.final_episodes=2",
                          "agent.algo.train_freq=16", "agent.algo.gradient_steps=1", "agent.algo.batch_size=32",
                          "agent.algo.policy_kwargs.net_arch=[16]", "rl.reuse_real_arm=false", "progress_bar=false")
        counting_env.CountingMountainCar.reset_seeds = []
        job = build_fit_job(cfg)
        run_train(cfg, job, None)
        used[seed] = set(counting_env.CountingMountainCar.reset_seeds)
        from sdrl_bench.data import collect

        data[seed] = collect(job.spec, job.policy, job.n_transitions, job.epsilon, seeds.reset_seed(seed, "collect"))
    for seed in (0, 1):
        own = {seeds.block(seed, p) for p in seeds.PURPOSES}
        fixed = _test_set_seeds()
        assert all((s >> seeds.BLOCK_BITS) in own or s in fixed for s in used[seed]), sorted(used[seed])[:5]
        purposes = {p for p in seeds.PURPOSES if seeds.block(seed, p) in {s >> seeds.BLOCK_BITS for s in used[seed]}}
        assert {"collect", "curve_eval", "final_eval", "real_train"} <= purposes  # (no reset pool: the task resets)
    assert not (used[0] - _test_set_seeds()) & (used[1] - _test_set_seeds())
    rows = [{tuple(np.r_[d.states[i], d.actions[i]]) for i in range(len(d))} for d in (data[0], data[1])]
    assert not rows[0] & rows[1]
