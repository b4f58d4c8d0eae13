"""An RL-transfer run: collect -> fit -> surrogate -> agent trained in it -> judged on the REAL env,
beside the baseline arm (the same agent trained in the real env).

Plain functions over typed arguments; every real-env step is counted by a wrapper, per phase.
Nothing here logs: ``run_transfer`` hands every result to a ``TransferRecorder`` as soon as it
exists (``tracking.transfer.RunRecorder`` writes them into an MLflow run), and asks it for a
finished real arm to reuse.
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol
from collections.abc import Callable

import numpy as np

from sdrl_bench import ConfigError, seeds
from sdrl_bench.envs.base import CHECK_RESETS, EnvSpec
from sdrl_bench.pipeline import FitJob, FitResult, check, fit_dynamics
from sdrl_bench.plots import learning_curves
from sdrl_bench.rl.policy_maps import PolicyMap, agreement, compute_maps, figure
from sdrl_bench.rl.accounting import expert_of, headline
from sdrl_bench.rl.agents import AgentConfig, Curve, RealEvalCallback, StepCounter, check_budget, evaluate_real, real_vec_env, train

ARMS = ("surrogate", "real")


@dataclass(frozen=True)
class TransferJob:
    """One seed of the paper's comparison."""

    fit: FitJob
    """How the surrogate's model is made (collection + fit)."""
    agent: AgentConfig
    """The agent both arms train."""
    arms: tuple[str, ...] = ARMS
    """Which arms to run: "surrogate", "real" or both."""
    surrogate_steps: int = 65_000
    """Training steps inside the surrogate."""
    real_steps: int = 100_000
    """Training steps of the baseline arm in the real env."""
    eval_every: int = 5_000
    """Training steps between real-env evaluations (the learning curve)."""
    eval_episodes: int = 5
    """Real-env episodes per learning-curve point."""
    final_episodes: int = 20
    """Real-env episodes of the final, deterministic evaluation."""
    stop_when_solved: bool = False
    """End an arm's training at its first learning-curve evaluation at the solved threshold
    (time-to-solve runs; the final evaluation still follows)."""
    confirm_episodes: int = 0
    """Real episodes that confirm a learning-curve evaluation at the threshold before it counts
    as solved (``RealEvalCallback``; 0: none)."""
    seed: int = 0
    """The run seed: every stream of the run derives from it (``seeds``: the agent, the real
    arm's envs, the curve's and the final evaluation's reset seeds; the fit has its own seed,
    usually the same)."""
    progress_bar: bool = False

    def check(self) -> tuple[Any, Any]:
        """Config-time validation, before any env step."""
        unknown = set(self.arms) - set(ARMS)
        if unknown or not self.arms:
            raise ConfigError(f"rl.arms: {sorted(unknown) or 'empty'}; choose from {list(ARMS)}")
        spec = self.fit.spec
        self.agent.check(spec)
        spec.map_slices()  # the policy maps' slices (a ConfigError names env.spec.policy_map_slices)
        if "surrogate" in self.arms:
            if not spec.defines_task:
                raise ConfigError(f"env.spec.reward_fn: env '{spec.name}' defines no reward (nor termination): the "
                                  "surrogate arm needs env.spec.reward_fn and termination_fn (dotted paths) or an "
                                  "EnvSpec subclass with reward(); or run rl.arms=[real]")
            check_budget("rl.surrogate_steps", self.surrogate_steps)
        if "real" in self.arms:
            check_budget("rl.real_steps", self.real_steps)
        for key in ("eval_every", "eval_episodes", "final_episodes"):
            check_budget(f"rl.{key}", getattr(self, key))
        if self.confirm_episodes < 0:
            raise ConfigError(f"rl.confirm_episodes: an integer >= 0, got {self.confirm_episodes}")
        return check(self.fit) if "surrogate" in self.arms else (None, None)


@dataclass
class ArmResult:
    """What one arm produced and what it cost."""

    arm: str
    model: Any
    curve: Curve
    final_returns: list[float]
    final_successes: list[bool]
    final_steps: int
    counts: dict[str, int]
    seconds: dict[str, float]
    maps: list[PolicyMap] = field(default_factory=list)
    fit: FitResult | None = None
    surrogate_stats: dict[str, float] = field(default_factory=dict)
    xla_pool_threads: int | None = None
    """A compiled agent's (``rl.jax_agent``): the threads of XLA's CPU pool that ran its programs."""
    compiles: dict[str, int] = field(default_factory=dict)
    """A compiled agent's: ``compile_programs`` (programs it compiled), ``compile_cache_hits``
    (those loaded from JAX's persistent compilation cache: 0 is a cold compile),
    ``lowering_cache_hits`` (those whose lowering came from the lowering cache,
    ``rl.jax_compile.compile_program``) and
    ``rollout_compiles`` (rollouts compiled with the surrogate's step: 0 where the rollout stepped
    in Python, in real envs or in a surrogate the compiled step does not cover)."""

    def metrics(self, spec: EnvSpec, train_steps: int, stop_when_solved: bool = False, expert: str | None = None,
                tuning: int = 0) -> dict[str, float]:
        """The accounting, as the paper counts it (real transitions + surrogate steps), and by
        purpose (``rl.accounting``: this run's data, every real step the result rests on)."""
        rets = np.asarray(self.final_returns)
        real_model = self.counts.get("collect", 0)
        real_train = self.counts.get("train", 0)
        m = {
            "real_transitions_model": real_model,
            "real_transitions_train": real_train,
            "surrogate_steps": train_steps if self.arm == "surrogate" else 0,
            "total_steps": real_model + real_train + (train_steps if self.arm == "surrogate" else 0),
            "eval_episodes": self.counts.get("eval_episodes", 0),
            "eval_steps": self.counts.get("evaluate", 0),
            **({"confirmations": self.counts["confirmations"]} if "confirmations" in self.counts else {}),
            **({"xla_pool_threads": self.xla_pool_threads} if self.xla_pool_threads is not None else {}),
            **self.compiles,
            "final_eval_episodes": len(rets),
            "final_eval_steps": self.final_steps,
            "final_return_mean": float(rets.mean()),
            "final_return_std": float(rets.std()),
            "success_rate": float(np.mean(self.final_successes)),
            "judged_solved": float(spec.solved_threshold is not None and rets.mean() >= spec.solved_threshold),
            **{f"{k}_seconds": v for k, v in self.seconds.items()},
        }
        purposes = {"model_data": real_model, "train": real_train,
                    ("selection" if stop_when_solved else "monitor"): self.counts.get("evaluate", 0),
                    "judge": self.counts.get("final", 0) + (len(self.fit.test) if self.fit is not None else 0),
                    **{f"resets/{k[7:]}": v for k, v in self.counts.items() if k.startswith("resets/")}}
        surrogate = self.arm == "surrogate"
        priors = (self.fit.spec if self.fit is not None else spec).declared_priors if surrogate else ()
        m.update(headline(purposes, priors, [expert] if surrogate else (), tuning))
        c = self.curve
        if c.first_solved_step is not None:
            # real-env interactions spent when the threshold was first met during training
            m["solved_real_steps"] = real_model + (c.first_solved_step if self.arm == "real" else 0)
            m["solved_train_steps"] = c.first_solved_step
            m["solved_wall_seconds"] = c.first_solved_wall + self.seconds.get("collect_wall", 0.0) + self.seconds.get("fit_wall", 0.0)
            if c.first_solved_cpu is not None:
                m["solved_cpu_seconds"] = c.first_solved_cpu + self.seconds.get("collect_cpu", 0.0) + self.seconds.get("fit_cpu", 0.0)
            if c.first_solved_rollout_wall is not None:
                m["solved_rollout_wall_seconds"] = c.first_solved_rollout_wall
            if self.arm == "surrogate":
                m["solved_surrogate_steps"] = c.first_solved_step
        return {k: float(v) for k, v in m.items()}


def surrogate_vec_env(model: Any, spec: EnvSpec, n_envs: int, seed: int, events: dict | None = None):
    """The default env of the surrogate arm: n copies stepped by one batched model call."""
    from sdrl_bench.surrogate.vec import SurrogateVecEnv  # noqa: PLC0415

    return SurrogateVecEnv(model, spec, n_envs, seed=seed, events=events)


def evaluate_surrogate(policy: Any, surrogate: Any, n_episodes: int, seed: int) -> np.ndarray:
    """Returns of ``policy`` (deterministic) in ``surrogate`` (a ``ModelEnv``: the same step the
    agent trained in, noise, pessimism and learned events included), episode i reset with seed
    ``seed + i``."""
    from sdrl_bench.surrogate.env import SurrogateEnv  # noqa: PLC0415

    env, rets = SurrogateEnv(surrogate), []
    for i in range(n_episodes):
        obs, _ = env.reset(seed=seed + i)
        total, done = 0.0, False
        while not done:
            action, _ = policy.predict(obs, deterministic=True)
            obs, r, term, trunc, _ = env.step(action)
            total += float(r)
            done = term or trunc
        rets.append(total)
    return np.asarray(rets)


def run_arm(
    job: TransferJob, arm: str, checked: tuple[Any, Any] | None = None,
    logger_factory: Callable[[str], Any] | None = None,
    on_point: Callable[[str, int, float, float], None] | None = None,
    make_surrogate: Callable[..., Any] | None = None,
    on_fit: Callable[[FitResult], None] | None = None,
) -> ArmResult:
    """Run one arm end to end. ``make_surrogate(model, spec, n_envs, seed)`` builds the vector
    env the agent trains in (default: ``surrogate_vec_env``); ``on_fit`` receives the
    surrogate's fit before the agent trains (so a run stopped during training keeps it)."""
    spec = job.fit.spec
    counts: Counter = Counter()
    seconds: dict[str, float] = {}
    fit_result, stats = None, {}
    if arm == "surrogate":
        fit_job = replace(job.fit, wrap_env=lambda env: StepCounter(env, counts, "collect"))
        fit_result = fit_dynamics(fit_job, checked)
        if on_fit is not None:
            on_fit(fit_result)
        seconds.update({k: v for k, v in fit_result.seconds.items() if not k.startswith("evaluate")})
        venv = (make_surrogate or surrogate_vec_env)(fit_result.model, fit_result.spec, job.agent.n_envs, job.seed,
                                                     events=fit_result.events)
        counts["resets/check"] += CHECK_RESETS  # the task's functions on real reset states (pipeline.check)
        counts["resets/reset_pool"] += getattr(getattr(venv, "surrogate", None), "real_resets", 0)
        steps, env_seed = job.surrogate_steps, job.seed
    else:
        env_seed = seeds.reset_seed(job.seed, "real_train")
        venv = real_vec_env(spec, job.agent.n_envs, env_seed, counts, "train")
        steps = job.real_steps
    callback = RealEvalCallback(
        spec, job.eval_every, job.eval_episodes, seed=seeds.reset_seed(job.seed, "curve_eval"), counts=counts,
        on_point=(lambda s, m, sd: on_point(arm, s, m, sd)) if on_point else None,
        stop_when_solved=job.stop_when_solved, confirm_episodes=job.confirm_episodes,
        confirm_seed=seeds.reset_seed(job.seed, "curve_confirm") if job.confirm_episodes else None,
    )
    logger = logger_factory(arm) if logger_factory else None
    bar = f"{arm} arm, {job.agent.name.upper()}" if job.progress_bar else False
    result = train(job.agent, venv, steps, seeds.int_seed(job.seed, "agent"), callback, logger, bar, env_seed=env_seed)
    counts["eval_episodes"] = (job.eval_episodes * len(result.curve.steps)
                               + job.confirm_episodes * len(result.curve.confirm_means))
    if job.confirm_episodes:
        counts["confirmations"] = len(result.curve.confirm_means)
    seconds.update(train_wall=result.wall_seconds, train_cpu=result.cpu_seconds, curve_eval_wall=result.eval_wall_seconds,
                   train_rollout_wall=result.rollout_wall_seconds)
    if hasattr(result.model, "compile_seconds"):  # a compiled agent (rl.jax_agent): its compiles, inside train_wall
        seconds["compile_wall"] = float(result.model.compile_seconds)
    sur = getattr(venv, "surrogate", None)
    if arm == "surrogate" and sur is not None:
        # a compiled agent steps its own copy of the surrogate and counts its divergences itself
        stats = {"diverged_episodes": float(sum(venv.n_diverged) + getattr(result.model, "diverged_episodes", 0))}
        stats.update({f"events/{e}/{o}": float(n) for e, outs in sur.event_counts.items() for o, n in outs.items()})
    venv.close()
    t0, c0 = time.perf_counter(), time.process_time()
    final = evaluate_real(result.model, spec, job.final_episodes, seed=seeds.reset_seed(job.seed, "final_eval"),
                          counts=counts, phase="final")
    seconds.update(evaluate_wall=time.perf_counter() - t0, evaluate_cpu=time.process_time() - c0)
    if sur is not None:
        # the optimism gap: the agent's return in its own surrogate (the same step, same episode
        # count) minus its return in the real env
        own = evaluate_surrogate(result.model, sur, job.final_episodes, seeds.int_seed(job.seed, "surrogate_eval"))
        stats.update(return_mean=float(own.mean()), optimism_gap=float(own.mean() - final.returns.mean()))
    maps = compute_maps(result.model, spec)
    return ArmResult(
        arm=arm, model=result.model, curve=result.curve, final_returns=final.returns.tolist(),
        final_successes=final.successes.tolist(), final_steps=final.steps, counts=dict(counts),
        seconds=seconds, maps=maps, fit=fit_result, surrogate_stats=stats,
        xla_pool_threads=getattr(result.model, "pool_threads", None),
        compiles={k: int(getattr(result.model, k)) for k in ("compile_programs", "compile_cache_hits", "lowering_cache_hits",
                                                              "rollout_compiles")
                  if hasattr(result.model, k)},
    )


@dataclass
class ReusedArm:
    """A finished real arm found in the store: its agent (SB3 zip), curve and metrics."""

    agent_path: Path
    curve: Curve
    metrics: dict[str, float]
    """The ``real/*`` metrics as that run recorded them."""


class TransferRecorder(Protocol):
    """Where ``run_transfer`` puts what it produces, the moment it exists."""

    def reusable_real_arm(self) -> ReusedArm | None: ...

    def sb3_logger(self, arm: str) -> Any: ...

    def curve_point(self, arm: str, step: int, mean: float, std: float) -> None: ...

    def fit_done(self, fit: FitResult) -> None: ...

    def arm_done(self, result: ArmResult, metrics: dict[str, float]) -> None: ...

    def figure(self, fig: Any, artifact_file: str) -> None: ...

    def metrics(self, metrics: dict[str, float]) -> None: ...


@dataclass
class TransferOutcome:
    summary: dict[str, float]
    """Every arm's metrics, keyed ``<arm>/<metric>``, and ``policy_map_agreement``."""
    model_text: str
    """The surrogate's equations (or summary), empty without a surrogate arm."""


def run_transfer(job: TransferJob, checked: tuple[Any, Any] | None, recorder: TransferRecorder,
                 reuse_real_arm: bool = True) -> TransferOutcome:
    """Run the job's arms (reusing a finished real arm the recorder finds), then the learning
    curves, the policy maps and their agreement."""
    spec = job.fit.spec
    maps: dict[str, list[PolicyMap]] = {}
    curves: dict[str, tuple] = {}
    summary: dict[str, float] = {}
    model_text = ""
    for arm in job.arms:
        found = recorder.reusable_real_arm() if arm == "real" and reuse_real_arm else None
        if found is not None:
            algo_cls = getattr(job.agent.algo, "func", job.agent.algo)
            maps["real"] = compute_maps(algo_cls.load(found.agent_path, device="cpu"), spec)
            curves["real"] = (found.curve.steps, found.curve.means, found.curve.stds)
            summary.update(found.metrics)
            continue
        result = run_arm(job, arm, checked if arm == "surrogate" else None, logger_factory=recorder.sb3_logger,
                         on_point=recorder.curve_point, on_fit=recorder.fit_done)
        # the steps the agent took (SB3 rounds a budget up to whole rollouts / train_freq)
        metrics = result.metrics(spec, int(result.model.num_timesteps), job.stop_when_solved,
                                 expert_of(job.fit.policy, spec.name),
                                 job.agent.tuning_real_steps + (job.fit.tuning_real_steps if arm == "surrogate" else 0))
        recorder.arm_done(result, metrics)
        if result.fit is not None:
            model_text = result.fit.model.describe()
        summary.update({f"{arm}/{k}": v for k, v in metrics.items()})
        maps[arm] = result.maps
        curves[arm] = (result.curve.steps, result.curve.means, result.curve.stds)
    if curves:
        recorder.figure(learning_curves(curves, spec.solved_threshold, f"{spec.name}: {job.agent.name}, seed {job.seed}"),
                        "figures/learning_curves.png")
    kind = job.fit.names.get("surrogate", "surrogate")
    if len(maps) == 2:
        score = agreement(maps["surrogate"], maps["real"], discrete=bool(spec.n_discrete_actions))
        summary["policy_map_agreement"] = score
        recorder.metrics({"policy_map_agreement": score})
        label = "fraction of equal actions" if spec.n_discrete_actions else "mean |action difference|"
        fig = figure({"trained in the real env": maps["real"], f"trained in the {kind} surrogate": maps["surrogate"]},
                     spec, f"{spec.name} policy maps ({label}: {score:.3f})")
        recorder.figure(fig, "figures/policy_maps.png")
    elif maps:
        arm = next(iter(maps))
        recorder.figure(figure({arm: maps[arm]}, spec, f"{spec.name} policy map ({arm} arm)"), "figures/policy_maps.png")
    return TransferOutcome(summary, model_text)
