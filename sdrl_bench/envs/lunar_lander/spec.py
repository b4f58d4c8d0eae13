"""LunarLander-v3, discrete (four actions, one-hot encoded as model inputs) or continuous.

The real env does not clip its observation, so no bounds are applied after a predicted step.
The two leg-contact flags are booleans: the dynamics model takes them as given inputs
(``exogenous_names``) and never regresses them; the surrogate environment derives them
(``lunar_lander_task``: leg contacts, crash and rest are approximated there, and documented).
Engine impulses carry random dispersion and the terrain is random per episode, so one-step
prediction has a noise floor no deterministic model beats (measured by replay: README, fidelity results).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from collections.abc import Callable

import numpy as np
from gymnasium.envs.box2d.lunar_lander import heuristic

from sdrl_bench import ConfigError
from sdrl_bench.envs.base import EnvSpec, Policy, StepOne, TestSetRecipe
from sdrl_bench.envs.functional import array_namespace
from sdrl_bench.envs.lunar_lander import array_rules, task
from sdrl_bench.envs.lunar_lander.events import in_flight
from sdrl_bench.envs.lunar_lander.task import LanderRules
from sdrl_bench.envs.task import ArrayStep, Task, parse_uncertainty

STATE_NAMES = ("x", "y", "vx", "vy", "angle", "angvel", "leg_left", "leg_right")
LEGS = ("leg_left", "leg_right")
HELDOUT_NOISE_FLOOR = {
    "all": (3.21e-9, 2.07e-8, 2.98e-5, 4.08e-5, 8.14e-8, 3.25e-5),
    "flight": (5.78e-9, 3.56e-8, 5.37e-5, 7.02e-5, 1.30e-7, 5.21e-5),
    "contact": (1.48e-9, 1.06e-8, 1.37e-5, 2.09e-5, 4.85e-8, 1.93e-5),
}
"""The replay noise floor (variance) per regime and regressed state on ``lunar_lander-heldout-v1``
(``fidelity.replay_noise_floor``, 400 rows per episode, 2 redraws each: 2518 rows, 1015 in
flight). The contact floor is a lower bound (terrain and leg joints kept). No-op flight steps
have zero variance: the noise is the engines'. Provenance: studies/noise_floor.py
(`.venv/bin/python studies/noise_floor.py --rows 400 --k 2`); data: lunar_lander-heldout-v1
(12 episodes, reset seeds 20000-20011, 3,841 steps) and 1,274,197 replayed steps from saved
states (simulator only)."""
FLIGHT_NOISE_FLOOR = HELDOUT_NOISE_FLOOR["flight"]


@dataclass(frozen=True)
class LunarLanderSpec(EnvSpec):
    """Discrete LunarLander: actions noop, left engine, main engine, right engine."""

    name: str = "lunar_lander"
    gym_id: str = "LunarLander-v3"
    state_names: tuple[str, ...] = STATE_NAMES
    action_names: tuple[str, ...] = ("a_noop", "a_left", "a_main", "a_right")
    n_discrete_actions: int = 4
    exogenous_names: tuple[str, ...] = LEGS
    max_episode_steps: int = 1000
    solved_threshold: float | None = 200.0
    rules: LanderRules = LanderRules()
    """Constants of the surrogate's task rules (touchdown event, settle, rest)."""
    crash_reward: float | None = -100.0
    """The real env's crash reward (a knowledge prior: the documented reward)."""
    terrain: bool = False
    """Random terrain off the pad in the surrogate, drawn per episode as the real env draws it
    (``task.draw_terrain``); off: the flat world at the pad's height."""
    touchdown_set: str | None = None
    """Path of a saved touchdown test set (``touchdowns.TouchdownSet``, made by
    ``studies/touchdown_set.py``): every fit scores the touchdown prior and the sleep counter
    on it. A path that names no file is a config error."""
    action_labels: tuple[str, ...] = ("noop", "left engine", "main engine", "right engine")
    # policy maps: a lander descending slowly above the pad, legs up, over three slices
    policy_map_slices: tuple = (("x", (-1.0, 1.0), "y", (0.0, 1.4)), ("vx", (-1.0, 1.0), "vy", (-1.5, 0.5)),
                                ("angle", (-0.8, 0.8), "angvel", (-1.0, 1.0)))
    policy_map_hold: dict = field(default_factory=lambda: {"y": 0.7, "vy": -0.3})

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.touchdown_set is not None and not Path(self.touchdown_set).is_file():
            raise ConfigError(f"env.spec.touchdown_set: no such file: {self.touchdown_set}")

    def build_task(self) -> Task:
        """The surrogate's task: the rules of ``task`` (leg flags, the touchdown prior, settling,
        rest, the shaped reward) in this env's kernels; the flight law's regime (both legs up)
        is where the ensemble's disagreement is penalized, in units of the flight noise floor's
        standard deviation (unless the config names a scale); the touchdown event as declared."""
        discrete = bool(self.n_discrete_actions)
        return Task(
            reward_terminated=lambda s, a, ns: task.reward_terminated(self.rules, discrete, s, a, ns),
            exogenous=lambda s, a, ns: task.leg_contacts(self.rules, s, ns),
            regime_dynamics=self.regime_dynamics, model_regime=in_flight,
            step_one=self.make_step_one, step_batch=self.make_step_batch,
            termination_causes=self.termination_causes, observed_causes=self.observed_termination_causes,
            crash_reward=self.crash_reward,
            uncertainty=parse_uncertainty(self.uncertainty, np.sqrt(np.array(FLIGHT_NOISE_FLOOR)).tolist()),
            events=self._events, array_step=self.array_step())

    def array_step(self) -> ArrayStep | None:
        """The kernels' step and the settle step as array functions (``array_rules``: numpy or
        jax), for a jax step; with terrain each episode's ground is its memory, drawn from a key
        (``init_aux(n, key)``), and the settle step has no floor of its own (the step's is the
        ground's), as ``regime_dynamics`` below."""
        discrete = bool(self.n_discrete_actions)
        settle = replace(self.rules, floor=-np.inf) if self.terrain else self.rules
        return ArrayStep(step=partial(array_rules.make_step, self.rules, discrete, terrain=self.terrain),
                         init_aux=partial(array_rules.init_aux, terrain=self.terrain),
                         regime_dynamics=partial(array_rules.regime_dynamics, settle, discrete))

    def learned_constants(self, data) -> tuple[dict, dict[str, float]]:
        """The contact rules the run's own transitions identify (``own_data.learn_rules``): the
        leg rule and floor, the settle model, the stiction; no touchdown speed (the touchdown
        event's model, learned from the same data, decides)."""
        from sdrl_bench.envs.lunar_lander.own_data import learn_rules  # noqa: PLC0415

        rules, learned = learn_rules(self.rules, data, bool(self.n_discrete_actions))
        return {"rules": rules}, learned

    def heuristic_policy(self, env) -> Policy:
        """gymnasium's built-in heuristic lander controller."""

        def policy(obs: np.ndarray):
            return heuristic(env, obs)

        return policy

    def divergence_limit(self) -> np.ndarray:
        # x, y in about +-2.5 (|x| >= 1 ends an episode), velocities and angle rates in +-10.
        return np.array([25.0, 25.0, 100.0, 100.0, 100.0, 100.0])

    # ------------------------------------------------------------------ the task
    def termination_causes(self, states, actions, next_states) -> dict[str, np.ndarray]:
        """Why the surrogate ends each transition: crash (or |x'| >= 1) and rest (one step of
        the sleep counter: rest only when ``rules.rest_frames`` <= 1; ``task.sleep_counts``
        follows whole episodes)."""
        crash, out, quiet = task.events(self.rules, states, next_states, actions, bool(self.n_discrete_actions))
        return {"crash": crash | out, "rest": quiet & (self.rules.rest_frames <= 1)}

    def observed_termination_causes(self, rewards: np.ndarray, terminated: np.ndarray) -> dict[str, np.ndarray]:
        """Why the real env ended each transition, read off its reward (-100 crash or out, +100 rest)."""
        return {"crash": terminated & (rewards == -100), "rest": terminated & (rewards == 100)}

    def make_step_one(self, predictor: Callable[..., Callable], obs_low=None, obs_high=None) -> StepOne | None:
        if self.terrain:  # per-episode terrain lives in the batched step (the surrogate uses it with N = 1)
            return None
        n = len(self.state_names)
        low = obs_low if obs_low is not None else [-np.inf] * n
        high = obs_high if obs_high is not None else [np.inf] * n
        return task.make_step_one(
            self.rules, bool(self.n_discrete_actions), predictor, self.divergence_limit(), low, high
        )

    def make_step_batch(self, limit, obs_low, obs_high, rng=None) -> Callable:
        return task.make_step_batch(self.rules, bool(self.n_discrete_actions), limit, obs_low, obs_high,
                                    terrain=self.terrain, rng=rng)

    def test_set_recipe(self) -> TestSetRecipe:
        """Twelve full episodes: the heuristic at eps 0 / 0.2 / 0.5 and uniform random actions,
        three of each (landings, crashes and flights off-screen)."""
        mix = (("heuristic", 0.0), ("heuristic", 0.2), ("heuristic", 0.5), ("random", 1.0)) * 3
        return TestSetRecipe(name=f"{self.name}-heldout-v1", seed=20_000, episodes=mix)

    # ------------------------------------------------------------------ regimes
    def regimes(self, episode, states, rewards, next_states) -> dict[str, np.ndarray]:
        """flight: rows before each episode's first touchdown (the first row whose s' has a leg
        flag, or that ends in a crash inside the screen: reward -100 with |x'| < 1); contact: the
        touchdown row and every row after it. Rows in episode order."""
        episode, ns = np.asarray(episode), np.asarray(next_states, dtype=float)
        hit = (ns[:, 6] > 0.5) | (ns[:, 7] > 0.5) | ((np.asarray(rewards) == -100) & (np.abs(ns[:, 0]) < 1.0))
        flight = np.zeros(len(ns), dtype=bool)
        starts = np.flatnonzero(np.r_[True, episode[1:] != episode[:-1]])
        for a, b in zip(starts, np.r_[starts[1:], len(ns)], strict=True):
            h = np.flatnonzero(hit[a:b])
            flight[a:a + (h[0] if len(h) else b - a)] = True
        return {"flight": flight, "contact": ~flight}

    def regime_dynamics(self, states, actions, predicted) -> np.ndarray:
        """Landers on their legs take the settle step (``task``); in flight, the model's prediction.
        With terrain the floor is the ground's, applied in the batched step."""
        rules = replace(self.rules, floor=-np.inf) if self.terrain else self.rules
        return task.regime_dynamics(rules, bool(self.n_discrete_actions), states, actions, predicted)

    def noise_floor(self, test_name: str) -> dict | None:
        return HELDOUT_NOISE_FLOOR if test_name == self.test_set_recipe().name else None

    def task_fidelity(self, test) -> dict[str, float]:
        """The sleep counter along the test set's real episodes (rest: the first row whose count
        reaches ``rest_frames``, against the real +100 rows: precision, recall, timing error in
        steps), and, with ``touchdown_set``, the touchdown event's confusion matrix on it (its
        odd seeds: the half the constants were not fitted on) and the counter on its landings."""
        rules = self.rules
        counts = task.sleep_counts(rules, test.episode, test.next_states, test.actions, bool(self.n_discrete_actions))
        real = np.asarray(test.terminated, bool) & (np.asarray(test.rewards) == 100)
        pred = np.zeros(len(test), bool)
        errs = []
        for ep in np.unique(test.episode):
            idx = np.flatnonzero(test.episode == ep)
            fire, true = idx[counts[idx] >= rules.rest_frames], idx[real[idx]]
            if len(fire):
                pred[fire[0]] = True
            if len(fire) and len(true):
                errs.append(int(fire[0] - true[0]))
        tp = float(np.sum(pred & real))
        m = {"rest_counter_precision": tp / pred.sum() if pred.any() else float("nan"),
             "rest_counter_recall": tp / real.sum() if real.any() else float("nan"),
             "rest_counter_n_real": float(real.sum()),
             "rest_counter_timing_abs_mean": float(np.mean(np.abs(errs))) if errs else float("nan")}
        if self.touchdown_set:
            from sdrl_bench.envs.lunar_lander import touchdowns  # noqa: PLC0415

            d = touchdowns.TouchdownSet.load(self.touchdown_set)
            held = np.flatnonzero(d.seed % 2 == 1)
            m.update({f"touchdown/{k}": v for k, v in touchdowns.score_events(rules, d, held).items()})
            m.update({f"touchdown/rest_{k}": v for k, v in touchdowns.score_rest(rules, d).items()})
        return m


@dataclass(frozen=True)
class LunarLanderContinuousSpec(LunarLanderSpec):
    """Continuous LunarLander: main and lateral engine throttles in [-1, 1]."""

    name: str = "lunar_lander_continuous"
    action_names: tuple[str, ...] = ("main", "lateral")
    n_discrete_actions: int = 0
    action_labels: tuple[str, ...] = ()
    gym_kwargs: dict = field(default_factory=lambda: {"continuous": True})

    def encode_actions(self, actions: np.ndarray) -> np.ndarray:
        """Throttles as the real env uses them: clipped to [-1, 1] (numpy or jax arrays)."""
        enc = super().encode_actions(actions)
        return array_namespace(enc).clip(enc, -1.0, 1.0)
