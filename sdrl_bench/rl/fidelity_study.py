"""Which fidelity predicts transfer: one cluster of the study (``task=fidelity``).

A *cluster* is one data set collected from the real env (its own run seed, number of transitions,
collector and observation noise) and the surrogates fitted on it (``Variant``: SINDy with a
library and threshold, an NN, an ensemble). Surrogates of one cluster share their data, so they
are not independent; the analysis (``report.fidelity_study``) resamples clusters, never single
surrogates.

For each surrogate ``score_variant`` measures every candidate predictor of transfer (``CANDIDATES``,
all errors: lower should mean a better agent) and then the thing to predict: the real return of
``agent_seeds`` agents trained in it with a fixed recipe and budget, judged on the final-evaluation
stream. On-policy errors are measured on the agents' own real episodes from a stream of their own
(``fidelity_onpolicy``: neither the final evaluation nor any test set); the reference check plays
one fixed policy (the env's heuristic, an expert or random actions) in the real env (once per
cluster, stream ``fidelity_reference``) and in each surrogate. Every real step is counted by purpose.

Hand-written, and why: no library scores a surrogate by the transfer of agents trained in it; the
pieces (fits, fidelity, agents, evaluations) are the harness's own.
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, replace
from typing import Any
from collections.abc import Callable

import numpy as np

from sdrl_bench import ConfigError, seeds
from sdrl_bench.data import PolicyFactory, Transitions, TransitionRecorder, collect, concat, held_out_test_set, random_policy, recorded
from sdrl_bench.envs.base import EnvSpec
from sdrl_bench.fidelity import POLICY_METRICS, ROLLOUT_CAP, align_angles, episode_error, normalized_error, rollout_error
from sdrl_bench.pipeline import FitJob, FitResult, check, fit_transitions
from sdrl_bench.rl.agents import AgentConfig, StepCounter, check_budget, evaluate_real, train
from sdrl_bench.rl.transfer import evaluate_surrogate, surrogate_vec_env

CANDIDATES: dict[str, str] = {
    "one_step": "one-step MSE on the held-out test set, per state in units of the data's variance, mean over states",
    "one_step_max": "the same, the worst state",
    "floor_ratio": "one-step MSE over the replay noise floor, worst state of the env's first regime (envs with a floor)",
    "rollout10": "10-step open-loop error on the test set (normalized, mean over states; a diverged rollout counts as the cap)",
    "rollout50": "50-step open-loop error, as rollout10",
    "rollout_episode": "open loop over whole test episodes: normalized error averaged over time and states (cap after divergence)",
    "termination_error": "1 - F1 of the surrogate's termination on the test set's real transitions (envs whose test set terminates)",
    "reward_error": "MSE of the surrogate's one-step reward along the test set's real trajectories, over the rewards' variance",
    "onpolicy_one_step": "one-step error (as one_step) on the trained agents' own real episodes",
    "onpolicy_reward": "reward error (as reward_error) on the trained agents' own real episodes",
    "reference_gap": "|return of the reference policy in the surrogate - its return in the real env|",
    "optimism_gap": "|agents' return in their own surrogate - their real return| (needs the real return: diagnostic, not a selector)",
    "n_terms": "model size: active terms (SINDy) or parameters (NN)",
}
"""The candidate predictors, each an error (lower: better). The analysis correlates ``-metric``
with the real return, so a positive Spearman means the metric ranks surrogates the right way."""

NEEDS_POLICY = ("onpolicy_one_step", "onpolicy_reward", "optimism_gap")
"""Candidates that need trained agents (real steps per surrogate beyond its data)."""

@dataclass(frozen=True)
class Variant:
    """One surrogate of a cluster: a label, its model family and the fit that makes it."""

    label: str
    family: str
    """``sindy``, ``nn``, ``pe`` (the colour in the figures)."""
    fit: FitJob


@dataclass(frozen=True)
class ClusterJob:
    """One data set and the surrogates fitted on it."""

    data_job: FitJob
    """How the data are collected (env, collector, n_transitions, seed)."""
    variants: tuple[Variant, ...]
    agent: AgentConfig
    """The fixed recipe every surrogate's agents train with."""
    train_steps: int
    """Surrogate steps per agent (a fixed budget: nothing stops on a real evaluation)."""
    agent_seeds: int = 3
    final_episodes: int = 10
    """Real episodes of each agent's final evaluation (deterministic policy)."""
    onpolicy_episodes: int = 2
    """Real episodes per agent for the on-policy errors (0: skip them)."""
    reference: PolicyFactory | None = None
    """The fixed reference policy (None: uniform random actions)."""
    reference_name: str = "random"
    reference_episodes: int = 10
    data_noise: float = 0.0
    """Gaussian noise added to the regressed states of the data (states and next states), in units
    of each state's standard deviation over the data."""
    seed: int = 0

    def check(self) -> list[tuple[Any, Any]]:
        """Config-time validation of every variant, before any real step."""
        if not self.variants:
            raise ConfigError("fidelity.models: no surrogate to fit")
        for key in ("train_steps", "agent_seeds", "final_episodes", "reference_episodes"):
            check_budget(f"fidelity.{key}", getattr(self, key))
        if self.onpolicy_episodes < 0:
            raise ConfigError(f"fidelity.onpolicy_episodes must be >= 0, got {self.onpolicy_episodes}")
        if not 0.0 <= self.data_noise < 1.0:
            raise ConfigError(f"fidelity.data_noise must be within [0, 1), got {self.data_noise}")
        labels = [v.label for v in self.variants]
        if len(set(labels)) != len(labels):
            raise ConfigError(f"fidelity.models: labels repeat: {labels}")
        spec = self.data_job.spec
        if not spec.defines_task:
            raise ConfigError(f"env.spec.reward_fn: env '{spec.name}' defines no reward: a surrogate needs a task")
        self.agent.check(spec)
        return [check(v.fit) for v in self.variants]


@dataclass
class ClusterData:
    """What a cluster's surrogates share: the (noisy) data, the test set, the reference's real return."""

    data: Transitions
    test_name: str
    test: Transitions
    reference_real: np.ndarray
    counts: Counter
    norm_std: np.ndarray
    """Per regressed state: the std over the data (the normalization of every error)."""
    reward_var: float


def collect_cluster(job: ClusterJob) -> ClusterData:
    """Collect the data (counted ``collect``), add the observation noise, build the test set,
    play the reference policy in the real env (counted ``reference``)."""
    spec, counts = job.data_job.spec, Counter()
    d = job.data_job
    data = collect(spec, d.policy or random_policy, d.n_transitions, d.epsilon, seeds.reset_seed(job.seed, "collect"),
                   max_steps_per_episode=d.max_steps_per_episode, wrap_env=lambda env: StepCounter(env, counts, "collect"))
    tgt = spec.target_index
    std = np.array([data.normalization(spec)[spec.state_names[i]]["std"] for i in tgt])
    if job.data_noise > 0:
        rng = seeds.generator(job.seed, "data_noise")
        states, nxt = data.states.copy(), data.next_states.copy()
        states[:, tgt] += rng.normal(size=(len(data), len(tgt))) * std * job.data_noise
        nxt[:, tgt] += rng.normal(size=(len(data), len(tgt))) * std * job.data_noise
        data = replace(data, states=states, next_states=nxt)
    test_name, test = held_out_test_set(spec)
    ref = evaluate_real(_Reference(spec, job.reference), spec, job.reference_episodes,
                        seed=seeds.reset_seed(job.seed, "fidelity_reference"), counts=counts, phase="reference")
    reward_var = float(np.var(test.rewards)) or 1.0
    return ClusterData(data, test_name, test, ref.returns, counts, std, reward_var)


class _Reference:
    """A policy factory's policy behind SB3's ``predict`` (batched over the rows of ``obs``)."""

    def __init__(self, spec: EnvSpec, factory: PolicyFactory | None):
        env = spec.make_env()
        try:
            self._policy = factory(spec, env) if factory is not None else None
            self._space = env.action_space
            self._space.seed(0)  # a random reference: the same fixed action stream in every cluster
        finally:
            env.close()

    def predict(self, obs, deterministic: bool = True):
        obs = np.asarray(obs)
        batched = obs.ndim == 2
        rows = obs if batched else obs[None]
        if self._policy is None:
            acts = [self._space.sample() for _ in rows]
        else:
            acts = [self._policy(o) for o in rows]
        out = np.asarray(acts)
        return (out if batched else out[0]), None


def one_step_errors(model: Any, spec: EnvSpec, rows: Transitions, std: np.ndarray, reward_var: float) -> tuple[float, float]:
    """(normalized one-step error, normalized reward error) of the full surrogate step of ``model``
    (on ``spec``'s task) on real ``rows``."""
    from sdrl_bench.surrogate.model_env import ModelEnv  # noqa: PLC0415

    sur = ModelEnv(model, spec, noise=False, penalty=False)
    nxt, reward, _, _ = sur.step(rows.states, rows.actions)
    tgt = spec.target_index
    e = normalized_error(rows.next_states[:, tgt], align_angles(spec, rows.next_states[:, tgt], nxt[:, tgt]), std)
    return float(np.mean(e)), float(np.mean((np.asarray(reward) - rows.rewards) ** 2) / reward_var)


def fidelity_candidates(fit: FitResult, cluster: ClusterData) -> dict[str, float]:
    """The candidates that need no agent, from the fit's own metrics and the test set."""
    spec, m, std = fit.spec, fit.fidelity.metrics, cluster.norm_std
    names = spec.target_names
    per_state = [m[f"mse/{n}"] / s**2 for n, s in zip(names, std, strict=True)]
    out = {"one_step": float(np.mean(per_state)) if np.all(np.isfinite(per_state)) else ROLLOUT_CAP,
           "one_step_max": float(np.max(per_state)) if np.all(np.isfinite(per_state)) else ROLLOUT_CAP}
    if m["one_step/nonfinite_fraction"] > 0:
        out["one_step"] = out["one_step_max"] = ROLLOUT_CAP
    floors = [k for k in m if k.startswith("floor_ratio_") and k.endswith("/max")]
    if floors:
        out["floor_ratio"] = float(m[sorted(floors)[0]])
    for k in (10, 50):
        out[f"rollout{k}"] = rollout_error(fit.model, spec, cluster.test, k, std)
    out["rollout_episode"] = episode_error(fit.model, spec, cluster.test, std)
    p, r = m.get("surrogate/one_step/terminated_precision"), m.get("surrogate/one_step/terminated_recall")
    if cluster.test.terminated.any():
        p, r = (0.0 if p is None or not np.isfinite(p) else p), (0.0 if r is None or not np.isfinite(r) else r)
        out["termination_error"] = 1.0 - (2 * p * r / (p + r) if p + r > 0 else 0.0)
    out["reward_error"] = one_step_errors(fit.model, fit.spec, cluster.test, std, cluster.reward_var)[1]
    summary = fit.model.summary_metrics()
    out["n_terms"] = float(summary.get("n_active_terms", summary.get("n_parameters", np.nan)))
    return out


@dataclass
class VariantScore:
    """One surrogate's candidates, its agents' real returns and the real steps they took."""

    fit: FitResult
    candidates: dict[str, float]
    returns: list[list[float]]
    """Per agent: its final real episodes' returns."""
    surrogate_returns: list[float]
    counts: Counter
    seconds: dict[str, float]

    @property
    def real_return(self) -> float:
        """The mean over agents of their final real mean return (the thing to predict)."""
        return float(np.mean([np.mean(r) for r in self.returns]))


def score_variant(job: ClusterJob, variant: Variant, cluster: ClusterData, library: Any,
                  on_fit: Callable[[FitResult], None] | None = None) -> VariantScore:
    """Fit the variant on the cluster's data, measure its candidates, train its agents and judge them.
    ``library``: the variant's feature library, as ``ClusterJob.check`` built it."""
    spec, counts, seconds = job.data_job.spec, Counter(), {}
    fit = fit_transitions(variant.fit, library, cluster.data, test=(cluster.test_name, cluster.test))
    if on_fit is not None:
        on_fit(fit)
    t0 = time.perf_counter()
    cand = fidelity_candidates(fit, cluster)
    seconds["candidates_wall"] = time.perf_counter() - t0
    from sdrl_bench.surrogate.model_env import ModelEnv  # noqa: PLC0415

    ref_sur = evaluate_surrogate(_Reference(spec, job.reference), ModelEnv(fit.model, fit.spec, events=fit.events),
                                 job.reference_episodes, seeds.int_seed(job.seed, "surrogate_eval"))
    cand["reference_gap"] = abs(float(ref_sur.mean()) - float(cluster.reference_real.mean()))
    returns, own, onpolicy = [], [], []
    t_train = t_eval = 0.0
    for k in range(job.agent_seeds):
        agent_seed = int(seeds.generator(job.seed, "agent", k).integers(2**31))
        venv = surrogate_vec_env(fit.model, fit.spec, job.agent.n_envs, agent_seed, events=fit.events)
        counts["resets/reset_pool"] += getattr(getattr(venv, "surrogate", None), "real_resets", 0)
        t0 = time.perf_counter()
        result = train(job.agent, venv, job.train_steps, agent_seed, env_seed=agent_seed)
        t_train += time.perf_counter() - t0
        sur = venv.surrogate
        venv.close()
        t0 = time.perf_counter()
        final = evaluate_real(result.model, spec, job.final_episodes,
                              seed=seeds.reset_seed(job.seed, "final_eval", k * job.final_episodes), counts=counts, phase="judge")
        returns.append(final.returns.tolist())
        own.append(float(evaluate_surrogate(result.model, sur, job.final_episodes,
                                            seeds.int_seed(job.seed, "surrogate_eval") + 1 + k).mean()))
        if job.onpolicy_episodes:
            onpolicy.append(own_episodes(result.model, spec, job.onpolicy_episodes,
                                         seeds.reset_seed(job.seed, "fidelity_onpolicy", k * job.onpolicy_episodes), counts))
        t_eval += time.perf_counter() - t0
    seconds.update(train_wall=t_train, evaluate_wall=t_eval)
    if onpolicy:
        rows = concat(onpolicy)
        cand["onpolicy_one_step"], cand["onpolicy_reward"] = one_step_errors(fit.model, fit.spec, rows, cluster.norm_std, cluster.reward_var)
    real_means = np.array([np.mean(r) for r in returns])
    cand["optimism_gap"] = float(np.mean(np.abs(np.array(own) - real_means)))
    return VariantScore(fit, cand, returns, own, counts, seconds)


def own_episodes(policy: Any, spec: EnvSpec, episodes: int, seed: int, counts: Counter) -> Transitions:
    """``episodes`` real episodes of ``policy`` (deterministic; reset seeds ``seed + i``), recorded
    as transitions and counted under ``onpolicy``."""
    recorders: list[TransitionRecorder] = []

    def wrap(env, i):
        rec = TransitionRecorder(env, spec, i)
        recorders.append(rec)
        return rec

    evaluate_real(policy, spec, episodes, seed=seed, counts=counts, phase="onpolicy", wrap_env=wrap)
    return recorded(recorders)


class PolicyProbe:
    """A search objective that needs a policy (``search.objective=onpolicy_one_step`` or
    ``reference_gap``): scores one fitted model per trial and counts the real steps it takes.

    * ``onpolicy_one_step``: an agent (``agent``, ``train_steps``) trains in the model's surrogate and
      plays ``episodes`` real episodes (stream ``fidelity_onpolicy``, a block per trial); the score
      is the model's normalized one-step error on them (``episodes x episode length`` real steps per trial).
    * ``reference_gap``: the reference policy plays ``episodes`` episodes in the surrogate; the score
      is the gap to its real return over ``episodes`` real episodes (stream ``fidelity_reference``,
      played once per study).
    """

    def __init__(self, metric: str, agent: AgentConfig, train_steps: int, episodes: int,
                 reference: PolicyFactory | None, seed: int, reference_name: str = "random"):
        if metric not in POLICY_METRICS:
            raise ConfigError(f"search.objective: a policy objective is one of {list(POLICY_METRICS)}, got {metric!r}")
        check_budget("search.policy.train_steps", train_steps)
        check_budget("search.policy.episodes", episodes)
        self.metric, self.agent, self.train_steps, self.episodes = metric, agent, train_steps, episodes
        self.reference, self.seed, self.reference_name = reference, seed, reference_name
        self._reference_real: float | None = None

    def describe(self) -> dict[str, Any]:
        """What the scores depend on (a resumed study must match it)."""
        return {"metric": self.metric, "agent": self.agent.name, "train_steps": self.train_steps, "episodes": self.episodes,
                "reference": self.reference_name, "seed": self.seed}

    def score(self, model: Any, spec: EnvSpec, data: Transitions, trial: int, counts: Counter) -> float:
        """The objective for ``model`` fitted on ``data`` (trial number ``trial``); real steps added to ``counts``."""
        from sdrl_bench.surrogate.model_env import ModelEnv  # noqa: PLC0415

        if self.metric == "reference_gap":
            if self._reference_real is None:
                real = evaluate_real(_Reference(spec, self.reference), spec, self.episodes,
                                     seed=seeds.reset_seed(self.seed, "fidelity_reference"), counts=counts, phase="reference")
                self._reference_real = float(real.returns.mean())
            own = evaluate_surrogate(_Reference(spec, self.reference), ModelEnv(model, spec), self.episodes,
                                     seeds.int_seed(self.seed, "surrogate_eval"))
            return abs(float(own.mean()) - self._reference_real)
        agent_seed = int(seeds.generator(self.seed, "agent", trial).integers(2**31))
        venv = surrogate_vec_env(model, spec, self.agent.n_envs, agent_seed)
        counts["resets/reset_pool"] += getattr(getattr(venv, "surrogate", None), "real_resets", 0)
        result = train(self.agent, venv, self.train_steps, agent_seed, env_seed=agent_seed)
        venv.close()
        rows = own_episodes(result.model, spec, self.episodes,
                            seeds.reset_seed(self.seed, "fidelity_onpolicy", trial * self.episodes), counts)
        stats = data.normalization(spec)
        std = np.array([stats[spec.state_names[i]]["std"] for i in spec.target_index])
        return one_step_errors(model, spec, rows, std, 1.0)[0]
