"""Dyna-style refits: collect with the current agent, refit the surrogate, train on in it, repeat.

The paper fits its surrogate once, from one collection. Here (after Sutton's Dyna, and the
refit loops of MBPO and SINDy-RL) the agent's own behaviour brings back the real transitions
its surrogate lacks:

* round 0: collect ``fit.n_transitions`` with the job's collector (eps-greedy), fit the model
  (and the learned event model, ``surrogate.events``), build the agent inside the surrogate;
* round k >= 1: train the *same* agent ``surrogate_steps_per_round`` more steps in the
  surrogate (round 1: ``first_round_steps``); screen it on ``eval_episodes`` real episodes; when
  the screen reaches the solved threshold, confirm on ``final_episodes`` fresh real episodes:
  solved when their mean does; otherwise collect ``collect_per_round`` real transitions with
  the agent (deterministic action, eps-greedy), refit everything on all real data so far and
  swap the new surrogate under the agent;
* the loop ends solved, at ``max_real_transitions`` real steps, or after ``max_rounds``.

Accounting that cannot flatter: every real step is counted by a wrapper on the real env, by
phase: ``collect`` (model data), ``evaluate`` (screens), ``final`` (confirmations). With
``data_from_evaluations`` the evaluation episodes join the model data too (recorded, never
counted twice). The headline ``real_transitions_total`` is every real step the loop took,
including those that decided it was done. After the loop, an ``audit`` of ``audit_episodes``
more real episodes (fresh reset seeds) measures the final agent without selection: a loop that
stops at its first lucky confirmation shows it there. The audit is outside the loop's count
and reported apart.

Plain functions over typed arguments; ``run_dyna`` hands each round to a ``DynaRecorder``
(``tracking.dyna_runs.DynaRunRecorder``: a parent run with a child run per round).
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np

from sdrl_bench import ConfigError, seeds
from sdrl_bench.envs.base import CHECK_RESETS
from sdrl_bench.fidelity import evaluate as evaluate_fidelity
from sdrl_bench.data import TransitionRecorder, Transitions, collect, concat, held_out_test_set, random_policy, recorded
from sdrl_bench.pipeline import FitJob, FitResult, check, fit_transitions
from sdrl_bench.rl.accounting import expert_of, headline
from sdrl_bench.rl.agents import AgentConfig, EvalResult, StepCounter, close_logger, evaluate_real, make_agent

LOOP_PHASES = ("collect", "evaluate", "final")
"""The phases whose real steps the loop counts (the audit is reported apart)."""


@dataclass(frozen=True)
class DynaConfig:
    """The loop's budgets (``rl.dyna.*``)."""

    collect_per_round: int = 2000
    """Real transitions collected with the agent (eps-greedy) after each unsolved round (0: none;
    the screens' episodes are then the only new data)."""
    surrogate_steps_per_round: int = 100_000
    """Surrogate training steps of rounds 2, 3, ..."""
    first_round_steps: int = 300_000
    """Surrogate training steps of round 1 (from an untrained agent)."""
    max_real_transitions: int = 50_000
    """The loop stops once it has taken this many real steps (collect + evaluate + final)."""
    max_rounds: int = 20
    eval_episodes: int = 5
    """Real episodes of each round's screen."""
    screen_max_steps: int | None = None
    """Cut each screen episode after this many steps (None: play it out). A screen only decides
    whether to confirm; the confirmation's episodes always play out."""
    final_episodes: int = 20
    """Real episodes of a confirmation (solved: their mean reaches the env's threshold)."""
    epsilon: float = 0.2
    """Exploration of the agent's collection: a uniform random action with this probability."""
    data_from_evaluations: bool = True
    """The screens' and confirmations' episodes join the model data."""
    learn_events: bool = True
    """Refit the env's learned event models (``surrogate.events``) every round; False: the
    task's rules alone decide events."""
    min_events: int = 8
    """Real events needed before an event model is fitted (every declared event)."""
    audit_episodes: int = 100
    """Real episodes of the post-loop audit (0: none)."""

    def check(self) -> None:
        for key in ("surrogate_steps_per_round", "first_round_steps", "max_real_transitions",
                    "max_rounds", "eval_episodes", "final_episodes", "min_events"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ConfigError(f"rl.dyna.{key}: a positive integer is required, got {value!r}")
        for key in ("collect_per_round", "audit_episodes"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
                raise ConfigError(f"rl.dyna.{key}: an integer >= 0 is required, got {value!r}")
        if self.screen_max_steps is not None and (isinstance(self.screen_max_steps, bool) or not isinstance(
                self.screen_max_steps, (int, np.integer)) or self.screen_max_steps < 1):
            raise ConfigError(f"rl.dyna.screen_max_steps: a positive integer or null is required, got {self.screen_max_steps!r}")
        if self.collect_per_round == 0 and not self.data_from_evaluations:
            raise ConfigError("rl.dyna.collect_per_round: 0 with data_from_evaluations false leaves the loop no new data")
        if isinstance(self.epsilon, bool) or not isinstance(self.epsilon, (int, float)) or not 0.0 <= self.epsilon <= 1.0:
            raise ConfigError(f"rl.dyna.epsilon must be within [0, 1], got {self.epsilon!r}")
        for key in ("data_from_evaluations", "learn_events"):
            if not isinstance(getattr(self, key), bool):
                raise ConfigError(f"rl.dyna.{key}: true or false, got {getattr(self, key)!r}")


@dataclass(frozen=True)
class DynaJob:
    fit: FitJob
    """The initial collection and the model recipe every round refits."""
    agent: AgentConfig
    dyna: DynaConfig = DynaConfig()
    seed: int = 0

    def check(self) -> tuple[Any, Any]:
        """Config-time validation, before any env step."""
        self.dyna.check()
        spec = self.fit.spec
        if not spec.defines_task:
            raise ConfigError(f"env.spec.reward_fn: env '{spec.name}' defines no reward (nor termination): "
                              "task=dyna trains in the surrogate")
        if spec.solved_threshold is None:
            raise ConfigError(f"env.spec.solved_threshold: env '{spec.name}' has none; task=dyna stops when solved")
        self.agent.check(spec)
        if self.fit.dataset_path:
            raise ConfigError("dataset.path: task=dyna collects its own data (the loop counts every real step)")
        if self.dyna.max_real_transitions < self.fit.n_transitions:  # the first collection alone is over it
            raise ConfigError(f"rl.dyna.max_real_transitions: {self.dyna.max_real_transitions:,} is below the first "
                              f"collection's n_transitions={self.fit.n_transitions:,}")
        return check(self.fit)


@dataclass
class RoundResult:
    """One round: its refit (round 0: the first fit), the agent's real returns, the running account."""

    round: int
    fit: FitResult
    new_data: Transitions
    """The real rows this round added to the model data."""
    counts: dict[str, int]
    """Real steps per phase, cumulative (collect, evaluate, final)."""
    surrogate_steps: int
    """Surrogate training steps, cumulative."""
    seconds: dict[str, float]
    """This round's wall and CPU seconds per phase (``<phase>_wall``, ``<phase>_cpu``)."""
    screen: EvalResult | None = None
    final: EvalResult | None = None
    solved: bool = False
    learned_events: dict = field(default_factory=dict)
    """{event: {outcome: count}}: the learned event models' draws in this round's training."""
    screened_at: int = 0
    """Real steps of the loop when this round's screen ended (the learning curve's x)."""
    refit: bool = True
    """Whether this round refitted (the last round does not: ``fit`` is the previous round's)."""

    @property
    def events(self) -> dict:
        """{event name: its learned model or None} of this round's fit."""
        return self.fit.events

    @property
    def real_transitions(self) -> int:
        return int(sum(self.counts.get(p, 0) for p in LOOP_PHASES))

    def metrics(self) -> dict[str, float]:
        m: dict[str, float] = {
            "round": self.round, "real_transitions_total": self.real_transitions,
            "real_transitions_model": len(self.fit.data), "surrogate_steps": self.surrogate_steps,
            **{f"real_steps_{p}": self.counts.get(p, 0) for p in LOOP_PHASES},
            "new_rows": len(self.new_data), "solved": float(self.solved),
            **{f"{k}_seconds": v for k, v in self.seconds.items()},
            **{f"surrogate_events/{e}/{o}": n for e, outs in self.learned_events.items() for o, n in outs.items()},
        }
        for name, res in (("screen", self.screen), ("final", self.final)):
            if res is not None:
                m.update({f"{name}_return_mean": res.mean, f"{name}_return_std": res.std,
                          f"{name}_success_rate": res.success_rate, f"{name}_steps": res.steps})
        return {k: float(v) for k, v in m.items()}


class DynaRecorder(Protocol):
    """Where ``run_dyna`` puts each round the moment it ends, and SB3's own training metrics."""

    def round_done(self, result: RoundResult, agent: Any) -> None: ...

    def sb3_logger(self) -> Any: ...


@dataclass
class DynaOutcome:
    rounds: list[RoundResult]
    agent: Any
    summary: dict[str, float]
    audit: EvalResult | None = None
    curve: list[tuple[int, float, float]] = field(default_factory=list)
    """(real transitions so far, screen mean, screen std) per round: the learning curve."""
    audit_data: Transitions | None = None
    """The audit's real transitions (held out: no fit saw them)."""


class _Clock:
    """Wall and CPU seconds of named phases."""

    def __init__(self):
        self.seconds: dict[str, float] = {}

    def run(self, phase: str, fn, *args, **kwargs):
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            return fn(*args, **kwargs)
        finally:
            self.seconds[f"{phase}_wall"] = self.seconds.get(f"{phase}_wall", 0.0) + time.perf_counter() - t0
            self.seconds[f"{phase}_cpu"] = self.seconds.get(f"{phase}_cpu", 0.0) + time.process_time() - c0


def agent_policy(agent: Any):
    """A collector policy factory (``data.collect``) acting with the agent's deterministic action."""
    def factory(spec, env):
        return lambda obs: agent.predict(obs, deterministic=True)[0]

    return factory


class _Loop:
    """The state one Dyna run carries between rounds."""

    def __init__(self, job: DynaJob, checked: tuple[Any, Any]):
        self.job, self.library = job, checked[0]
        self.counts: Counter = Counter()
        self.data: Transitions | None = None
        self.next_episode = 0
        self.collected_episodes = 0
        """Episodes the agent's collections have played (their reset seeds go on from here)."""
        self.finals = 0
        """Confirmations so far (each takes the next ``final_episodes`` reset seeds)."""
        self.test = held_out_test_set(job.fit.spec)

    def real_steps(self) -> int:
        """Real steps the loop has taken so far (the audit apart)."""
        return sum(self.counts[p] for p in LOOP_PHASES)

    def counted(self, phase: str):
        return lambda env: StepCounter(env, self.counts, phase)

    def evaluate(self, agent: Any, n: int, seed: int, phase: str, max_steps: int | None = None
                 ) -> tuple[EvalResult, Transitions | None]:
        """``n`` real episodes with reset seeds ``seed + i``, and their transitions (model data unless
        the caller holds them out, as the audit does)."""
        spec, recorders = self.job.fit.spec, []

        def wrap(env, i):
            rec = TransitionRecorder(env, spec, self.next_episode + i)
            recorders.append(rec)
            return rec

        res = evaluate_real(agent, spec, n, seed, self.counts, phase, wrap_env=wrap, max_steps=max_steps)
        self.next_episode += n
        return res, recorded(recorders)

    def refit(self, clock: _Clock) -> FitResult:
        """The model and the learned event models on all real data so far."""
        job = self.job
        fit_job = replace(job.fit, learn_events=job.dyna.learn_events, min_events=job.dyna.min_events)
        return clock.run("fit", fit_transitions, fit_job, self.library, self.data, test=self.test)


def run_dyna(job: DynaJob, checked: tuple[Any, Any], recorder: DynaRecorder | None = None) -> DynaOutcome:
    """The loop of the module docstring; every round goes to ``recorder`` as it ends."""
    from sdrl_bench.surrogate.vec import SurrogateVecEnv

    cfg, spec, seed = job.dyna, job.fit.spec, job.seed
    loop = _Loop(job, checked)
    clock = _Clock()
    fj = job.fit
    loop.data = clock.run("collect", collect, spec, fj.policy or random_policy, fj.n_transitions, fj.epsilon,
                          seeds.reset_seed(fj.seed, "collect"), max_steps_per_episode=fj.max_steps_per_episode,
                          wrap_env=loop.counted("collect"))
    loop.next_episode = int(loop.data.episode.max()) + 1
    first = loop.refit(clock)
    venv = SurrogateVecEnv(first.model, first.spec, job.agent.n_envs, seed=seed, events=first.events)
    loop.counts["resets/check"] += CHECK_RESETS  # the task's functions on real reset states (pipeline.check)
    loop.counts["resets/reset_pool"] += venv.surrogate.real_resets
    agent = make_agent(job.agent, venv, seeds.int_seed(seed, "agent"), recorder.sb3_logger() if recorder is not None else None,
                       env_seed=seed)
    rounds = [RoundResult(0, first, first.data, dict(loop.counts), 0, clock.seconds)]
    if recorder is not None:
        recorder.round_done(rounds[0], agent)
    curve: list[tuple[int, float, float]] = []
    for k in range(1, cfg.max_rounds + 1):
        clock = _Clock()
        drawn0 = {e: dict(outs) for e, outs in venv.event_counts.items()}
        steps = cfg.first_round_steps if k == 1 else cfg.surrogate_steps_per_round
        clock.run("train", agent.learn, total_timesteps=int(steps), reset_num_timesteps=False)
        close_logger(agent)
        screen, new = clock.run("evaluate", loop.evaluate, agent, cfg.eval_episodes,
                                seeds.reset_seed(seed, "dyna_screen", (k - 1) * cfg.eval_episodes), "evaluate",
                                cfg.screen_max_steps)
        new_parts = [new] if cfg.data_from_evaluations else []
        screened_at = loop.real_steps()
        curve.append((screened_at, screen.mean, screen.std))
        final = None
        if screen.mean >= spec.solved_threshold:
            final, new = clock.run("final", loop.evaluate, agent, cfg.final_episodes,
                                   seeds.reset_seed(seed, "dyna_final", loop.finals * cfg.final_episodes), "final")
            loop.finals += 1
            new_parts += [new] if cfg.data_from_evaluations else []
        left = cfg.max_real_transitions - loop.real_steps()
        solved = final is not None and final.mean >= spec.solved_threshold and left >= 0
        last = solved or left <= 0 or k == cfg.max_rounds
        if not last and cfg.collect_per_round:
            got = clock.run("collect", _collect, loop, agent, min(cfg.collect_per_round, left))
            new_parts.append(got)
        new_parts = [p for p in new_parts if p is not None and len(p)]
        new_rows = concat(new_parts) if new_parts else loop.data.subset(slice(0, 0))
        if len(new_rows):
            loop.data = concat([loop.data, new_rows])
        fit = rounds[-1].fit if last else loop.refit(clock)
        if not last:
            venv.swap_model(fit.model, fit.events, seed=int(seeds.generator(seed, "surrogate", 100 + k).integers(2**31)),
                            spec=fit.spec)
        drawn = {e: {o: n - drawn0.get(e, {}).get(o, 0) for o, n in outs.items()} for e, outs in venv.event_counts.items()}
        result = RoundResult(k, fit, new_rows, dict(loop.counts), int(agent.num_timesteps), clock.seconds,
                             screen, final, solved, drawn, screened_at, not last)
        rounds.append(result)
        if recorder is not None:
            recorder.round_done(result, agent)
        if last:
            break
    audit, audit_data = None, None
    if cfg.audit_episodes:  # recorded as the screens are, but never model data: held out
        audit, audit_data = loop.evaluate(agent, cfg.audit_episodes, seeds.reset_seed(seed, "dyna_audit"), "audit")
    summary = summarize(rounds, audit, spec.solved_threshold, cfg, job)
    for key in ("compile_seconds", "compile_programs", "compile_cache_hits", "lowering_cache_hits", "rollout_compiles", "rollout_swaps",
                "pool_threads"):  # a compiled agent's (rl.jax_agent)
        if getattr(agent, key, None) is not None:
            summary[f"agent_{key}"] = float(getattr(agent, key))
    if audit_data is not None:
        summary.update(audit_fidelity(rounds[-1].fit, audit_data))
    return DynaOutcome(rounds, agent, summary, audit, curve, audit_data)


AUDIT_HORIZONS = (10, 100)


def audit_fidelity(fit: FitResult, audit: Transitions) -> dict[str, float]:
    """The fidelity of the model the final agent last trained in, on the audit's episodes: held-out
    real transitions of the final policy's own state distribution (on-policy), that no fit saw
    (``audit_fidelity/mse/<state>``, k-step rollouts ``audit_fidelity/rollout<k>_mse/<state>``, ...)."""
    rep = evaluate_fidelity(fit.model, fit.spec, audit, horizons=AUDIT_HORIZONS)
    return {f"audit_fidelity/{k}": float(v) for k, v in rep.metrics.items() if np.isscalar(v)}


def _collect(loop: _Loop, agent: Any, n: int) -> Transitions:
    """``n`` real transitions with the agent, episodes reset with the run's ``dyna_collect``
    seeds in order (each collection goes on where the last one stopped)."""
    job = loop.job
    got = collect(job.fit.spec, agent_policy(agent), n, job.dyna.epsilon,
                  seeds.reset_seed(job.seed, "dyna_collect", loop.collected_episodes), first_episode=loop.next_episode,
                  wrap_env=loop.counted("collect"))
    loop.collected_episodes += len(np.unique(got.episode))
    loop.next_episode = int(got.episode.max()) + 1
    return got


def summarize(rounds: list[RoundResult], audit: EvalResult | None, threshold: float, cfg: DynaConfig,
              job: DynaJob | None = None) -> dict[str, float]:
    """The run's headline metrics: solved or not (the loop's own stop, and ``judged_solved``: the
    audit, on a seed stream nothing trained or stopped on), what it cost in real steps (by phase,
    and by purpose: this run's data and every real step the result rests on), surrogate steps
    and seconds, the last confirmation and the audit."""
    last = rounds[-1]
    seconds: Counter = Counter()
    for r in rounds:
        seconds.update(r.seconds)
    m: dict[str, float] = {
        "solved": float(last.solved), "rounds": float(last.round),
        "real_transitions_total": last.real_transitions, "real_transitions_model": len(last.fit.data),
        **{f"real_steps_{p}": last.counts.get(p, 0) for p in LOOP_PHASES},
        "surrogate_steps": last.surrogate_steps, "budget_real_transitions": cfg.max_real_transitions,
        **{f"{k}_seconds": v for k, v in seconds.items()},
    }
    m["wall_seconds"] = sum(v for k, v in seconds.items() if k.endswith("_wall"))
    m["cpu_seconds"] = sum(v for k, v in seconds.items() if k.endswith("_cpu"))
    if last.solved:
        m["solved_real_transitions"] = last.real_transitions
    screens = [r.screen.mean for r in rounds if r.screen is not None]
    if screens:
        m["best_screen_return"] = max(screens)
    finals = [r for r in rounds if r.final is not None]
    if finals:
        m.update(final_return_mean=finals[-1].final.mean, final_return_std=finals[-1].final.std,
                 final_success_rate=finals[-1].final.success_rate)
    if audit is not None:
        m.update(audit_return_mean=audit.mean, audit_return_std=audit.std, audit_success_rate=audit.success_rate,
                 audit_episodes=len(audit.returns), audit_steps=audit.steps,
                 audit_solved=float(audit.mean >= threshold), judged_solved=float(audit.mean >= threshold))
    if job is not None:
        c = last.counts
        # the evaluations' rows that reached a fit: the last round's screens are never refitted
        reused = (sum(len(r.new_data) for r in rounds if r.refit) - c.get("collect", 0)
                  if cfg.data_from_evaluations else 0)
        purposes = {"model_data": c.get("collect", 0), "selection": c.get("evaluate", 0) + c.get("final", 0),
                    "judge": (audit.steps if audit is not None else 0) + len(last.fit.test),  # + the held-out set
                    "reused_as_model_data": max(reused, 0),
                    **{k: v for k, v in c.items() if k.startswith("resets/")}}
        spec = last.fit.spec  # the last refit's: with own_data, the priors its learned constants replaced are gone
        m.update(headline(purposes, spec.declared_priors, [expert_of(job.fit.policy, spec.name)],
                          job.agent.tuning_real_steps + job.fit.tuning_real_steps))
    return {k: float(v) for k, v in m.items()}
