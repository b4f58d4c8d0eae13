"""Train and evaluate stable-baselines3 agents; real-env step and time accounting.

Nothing here logs: functions return curves and counts; ``tracking`` records them.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any
from collections.abc import Callable

import gymnasium as gym
import numpy as np
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv

from sdrl_bench import ConfigError
from sdrl_bench.envs.base import EnvSpec


@dataclass(frozen=True)
class AgentConfig:
    """An SB3 algorithm with its hyperparameters, built around an env at run time."""

    name: str
    """Short name (sac, ppo, td3, dqn)."""
    algo: Callable[..., BaseAlgorithm]
    """The SB3 class with its hyperparameters bound (``_partial_``); called with ``env=``, ``seed=``."""
    n_envs: int = 1
    """Parallel env copies the algorithm trains on."""
    action_space: str = "any"
    """"continuous", "discrete" or "any": what the algorithm can act in."""
    normalize_reward: bool = False
    """Train on rewards scaled by a running std of the discounted return (SB3's ``VecNormalize``
    with ``norm_obs=False``). Observations stay raw, so the trained policy acts in the real env
    as it is; the agent's gamma is the return's discount."""
    tuning_real_steps: int = 0
    """Real env steps spent tuning this recipe on the real env (as its pack records them; 0: none
    recorded). Counted in every arm that uses the recipe, real or surrogate (``rl.accounting``)."""

    def check(self, spec: EnvSpec, key: str = "agent") -> None:
        """Fail at config time when the algorithm cannot act in the env, or its settings are
        ones it does not have or values out of their domain (each one line naming the key, under
        ``key``: where the config holds this agent)."""
        if isinstance(self.n_envs, bool) or not isinstance(self.n_envs, int) or self.n_envs <= 0:
            raise ConfigError(f"{key}.n_envs: a positive integer is required, got {self.n_envs!r}")
        if not isinstance(self.normalize_reward, bool):
            raise ConfigError(f"{key}.normalize_reward: true or false, got {self.normalize_reward!r}")
        if self.action_space not in ("continuous", "discrete", "any"):  # anything else was "any"
            raise ConfigError(f"{key}.action_space: continuous, discrete or any is required, got {self.action_space!r}")
        discrete = spec.n_discrete_actions > 0
        kind = "discrete" if discrete else "continuous (Box)"
        algo = getattr(self.algo, "func", None)
        settings = dict(getattr(self.algo, "keywords", {}))
        check_settings(settings, f"{key}.algo")
        check = getattr(algo, "check_config", None)
        if callable(check):  # an algorithm that validates its own settings (rl.jax_agent.JaxPPO)
            check(settings, self.n_envs, normalize_reward=self.normalize_reward)
        elif isinstance(algo, type):  # an SB3 class: the keywords its constructor takes
            import inspect

            params = inspect.signature(algo.__init__).parameters
            if not any(p.kind is p.VAR_KEYWORD for p in params.values()):
                for k in settings:
                    if k not in params:
                        raise ConfigError(f"{key}.algo.{k}: not a setting of {algo.__name__} (its settings: "
                                          f"{', '.join(p for p in params if p not in ('self', 'env', 'seed') and not p.startswith('_'))})")
        check_policy(algo, settings, f"{key}.algo")
        if (self.action_space == "continuous" and discrete) or (self.action_space == "discrete" and not discrete):
            other = "agent=ppo or agent=dqn" if discrete else "agent=sac, agent=td3 or agent=ppo"
            raise ConfigError(
                f"agent={self.name}: {self.name.upper()} needs {self.action_space} actions but env "
                f"'{spec.name}' has {kind} actions; use {other}"
            )


# The domains of the SB3 settings the harness's recipes use (SB3 checks few of them, and only
# mid-training: a negative learning rate, a batch size "abc"); the compiled agents take the
# same names. (kind, low, high, low inclusive): "int" an integer, "count" an integer or a whole
# float (1e4: SB3 compares these with step counts), "num" a finite number.
_DOMAINS: dict[str, tuple[str, float, float, bool]] = {
    "learning_rate": ("num", 0.0, math.inf, False), "clip_range": ("num", 0.0, math.inf, False),
    "max_grad_norm": ("num", 0.0, math.inf, False), "vf_coef": ("num", 0.0, math.inf, True),
    "gamma": ("num", 0.0, 1.0, True), "gae_lambda": ("num", 0.0, 1.0, True), "tau": ("num", 0.0, 1.0, False),
    "exploration_fraction": ("num", 0.0, 1.0, True), "exploration_initial_eps": ("num", 0.0, 1.0, True),
    "exploration_final_eps": ("num", 0.0, 1.0, True), "target_policy_noise": ("num", 0.0, math.inf, True),
    "target_noise_clip": ("num", 0.0, math.inf, True),
    "batch_size": ("int", 1, math.inf, True), "n_steps": ("int", 1, math.inf, True), "n_epochs": ("int", 1, math.inf, True),
    "buffer_size": ("int", 1, math.inf, True), "learning_starts": ("count", 0, math.inf, True),
    "target_update_interval": ("count", 1, math.inf, True), "policy_delay": ("int", 1, math.inf, True),
}


def check_policy(algo: Any, settings: dict[str, Any], key: str = "agent.algo") -> None:
    """``policy`` is one the algorithm has (its ``policy_aliases``), ``policy_kwargs.net_arch`` a
    list of layer sizes or a mapping of such lists (SB3's ``pi`` / ``vf`` / ``qf``), and an SB3
    class's ``device`` one torch knows: SB3 refused each only once the agent was built, after the
    run's data and fit, with a traceback. One ConfigError naming the key."""
    policy = settings.get("policy", "MlpPolicy")
    aliases = getattr(algo, "policy_aliases", None)
    if isinstance(policy, str) and isinstance(aliases, dict) and aliases and policy not in aliases:
        raise ConfigError(f"{key}.policy: {policy!r} is not a policy of {getattr(algo, '__name__', algo)} "
                          f"(its policies: {', '.join(aliases)})")
    kwargs = settings.get("policy_kwargs")
    if kwargs is not None and not isinstance(kwargs, dict):
        raise ConfigError(f"{key}.policy_kwargs: a mapping is required, got {kwargs!r}")
    arch = (kwargs or {}).get("net_arch")

    def layers(v: Any) -> bool:
        return isinstance(v, list) and all(isinstance(n, int) and not isinstance(n, bool) and n > 0 for n in v)

    if arch is not None and not (layers(arch) or (isinstance(arch, dict) and arch and all(layers(v) for v in arch.values()))):
        raise ConfigError(f"{key}.policy_kwargs.net_arch: a list of layer sizes ([64, 64]) or a mapping of them "
                          f"({{pi: [64, 64], vf: [64, 64]}}) is required, got {arch!r}")
    if isinstance(algo, type) and issubclass(algo, BaseAlgorithm) and "device" in settings:
        from stable_baselines3.common.utils import get_device  # noqa: PLC0415

        try:
            get_device(settings["device"])
        except (RuntimeError, ValueError, TypeError) as exc:
            raise ConfigError(f"{key}.device: {' '.join(str(exc).split())}") from None


def check_settings(settings: dict[str, Any], key: str = "agent.algo") -> None:
    """The settings of ``_DOMAINS`` (a schedule, i.e. a callable, passes as it is), ``ent_coef``
    (a number >= 0, or SAC's ``"auto"``/``"auto_<x>"``), ``gradient_steps`` (>= 0, or -1: as many
    as steps) and ``train_freq`` (>= 1; SB3's (n, "episode") is a tuple, which a config cannot
    give: Hydra makes it a list, which SB3 refuses): one ConfigError naming the first bad key."""
    def number(v: Any, integer: bool) -> bool:
        if isinstance(v, bool):
            return False
        return isinstance(v, int) if integer else isinstance(v, (int, float)) and math.isfinite(v)

    def count(v: Any) -> bool:
        return number(v, True) or (number(v, False) and float(v).is_integer())

    for k, v in settings.items():
        if k in _DOMAINS and not callable(v):
            kind, low, high, closed = _DOMAINS[k]
            what = "a number" if kind == "num" else "an integer"
            ok = count(v) if kind == "count" else number(v, kind == "int")
            if not ok or v < low or v > high or (v == low and not closed):
                bound = f">= {low:g}" if closed else f"> {low:g}"
                rng = bound if math.isinf(high) else f"{bound} and <= {high:g}"
                raise ConfigError(f"{key}.{k}: {what} {rng} is required, got {v!r}")
        elif k == "ent_coef" and not (isinstance(v, str) and v.startswith("auto")) and (not number(v, False) or v < 0):
            raise ConfigError(f"{key}.ent_coef: a number >= 0 or 'auto' is required, got {v!r}")
        elif k == "gradient_steps" and (not number(v, True) or (v < 0 and v != -1)):
            raise ConfigError(f"{key}.gradient_steps: an integer >= 0, or -1, is required, got {v!r}")
        elif k == "train_freq" and not (isinstance(v, tuple) or (number(v, True) and v >= 1)):
            raise ConfigError(f"{key}.train_freq: an integer >= 1 is required, got {v!r}")


def ou_noise(sigma: float, n_actions: int):
    """Ornstein-Uhlenbeck action noise (TD3's zoo exploration on MountainCar)."""
    from stable_baselines3.common.noise import OrnsteinUhlenbeckActionNoise

    return OrnsteinUhlenbeckActionNoise(mean=np.zeros(n_actions), sigma=sigma * np.ones(n_actions))


def check_budget(key: str, steps: int) -> None:
    if int(steps) <= 0:
        raise ConfigError(f"{key} must be positive, got {steps}")


class StepCounter(gym.Wrapper):
    """Counts real-env steps into ``counts[phase]`` and resets into ``counts["resets/<phase>"]``:
    the accounting's ground truth (``rl.accounting`` names the purposes)."""

    def __init__(self, env: gym.Env, counts: Counter, phase: str):
        super().__init__(env)
        self.counts, self.phase = counts, phase

    def step(self, action):
        self.counts[self.phase] += 1
        return self.env.step(action)

    def reset(self, **kwargs):
        self.counts[f"resets/{self.phase}"] += 1
        return self.env.reset(**kwargs)


def real_vec_env(spec: EnvSpec, n_envs: int, seed: int, counts: Counter, phase: str = "train") -> VecEnv:
    """n copies of the real env, each counted and monitored, first reset with ``seed + i`` (a
    reset seed: ``seeds.reset_seed``; ``make_agent`` keeps it, where SB3 would put its own)."""

    def make(i: int):
        return lambda: Monitor(StepCounter(spec.make_env(), counts, phase))

    venv = DummyVecEnv([make(i) for i in range(n_envs)])
    venv.seed(seed)
    return venv


@dataclass
class EvalResult:
    returns: np.ndarray
    lengths: np.ndarray
    successes: np.ndarray

    @property
    def mean(self) -> float:
        return float(np.mean(self.returns))

    @property
    def std(self) -> float:
        return float(np.std(self.returns))

    @property
    def success_rate(self) -> float:
        return float(np.mean(self.successes))

    @property
    def steps(self) -> int:
        return int(np.sum(self.lengths))


def evaluate_real(
    policy: Any, spec: EnvSpec, n_episodes: int, seed: int, counts: Counter | None = None,
    phase: str = "evaluate", deterministic: bool = True, wrap_env: Callable[[gym.Env, int], gym.Env] | None = None,
    max_steps: int | None = None,
) -> EvalResult:
    """Play ``n_episodes`` in the real env (reset seeds ``seed + i``: pass the first of a
    purpose's reset seeds, ``seeds.reset_seed``) with ``policy.predict``.

    The episodes run side by side, one env each, stepped in lockstep with one batched
    ``predict`` per step: a predict call costs more than a real MountainCar step, and a fast
    recipe evaluates every few seconds of training. Measured: 10 MountainCar episodes of 999
    steps took 1.39 s batched against 3.87 s one episode at a time. Each episode is the one
    played alone, up to the float rounding of a batched forward pass (returns agreed to 9e-13).
    ``wrap_env(env, i)`` wraps episode i's counted env (Dyna records the episodes as model data).
    ``max_steps``: stop each episode there (its return so far counts, and it is no success; a
    Dyna screen spends no more real steps on an agent that hovers).
    """
    counts = counts if counts is not None else Counter()
    envs = [StepCounter(spec.make_env(), counts, phase) for _ in range(n_episodes)]
    if wrap_env is not None:
        envs = [wrap_env(env, i) for i, env in enumerate(envs)]
    rets, lens = np.zeros(n_episodes), np.zeros(n_episodes, dtype=int)
    succ = np.zeros(n_episodes, dtype=bool)
    try:
        obs = [env.reset(seed=seed + i)[0] for i, env in enumerate(envs)]
        live = list(range(n_episodes))
        while live:
            actions, _ = policy.predict(np.stack([obs[i] for i in live]), deterministic=deterministic)
            running = []
            for i, action in zip(live, actions, strict=True):
                obs[i], r, term, trunc, _ = envs[i].step(action)
                rets[i] += float(r)
                lens[i] += 1
                if term or trunc:
                    succ[i] = spec.is_success(float(rets[i]), bool(term))
                elif max_steps is None or lens[i] < max_steps:  # a cut episode stays no success
                    running.append(i)
            live = running
    finally:
        for env in envs:
            env.close()
    return EvalResult(rets, lens, succ)


@dataclass
class Curve:
    """Real-env evaluations during training."""

    steps: list[int] = field(default_factory=list)
    """Training steps (in the env the agent trains in) at each evaluation."""
    means: list[float] = field(default_factory=list)
    stds: list[float] = field(default_factory=list)
    wall: list[float] = field(default_factory=list)
    """Training wall seconds (evaluation time excluded) at each evaluation."""
    first_solved_step: int | None = None
    first_solved_wall: float | None = None
    first_solved_cpu: float | None = None
    """Training CPU seconds of this process (evaluations excluded) at the first solved point."""
    first_solved_rollout_wall: float | None = None
    """Of ``first_solved_wall``, the seconds spent collecting rollouts (env steps and the policy's
    actions); the rest went to gradient updates."""
    confirm_means: list[float] = field(default_factory=list)
    """The mean return of each confirmation played (``RealEvalCallback.confirm_episodes``), in order;
    the last one reached the threshold where ``first_solved_step`` is set."""


class RealEvalCallback(BaseCallback):
    """Every ``every`` training steps, evaluate the current policy in the real env. The
    evaluation's seconds (its episodes and ``on_point``, which records the point) are kept out
    of the training's.

    ``stop_when_solved``: end training at the first evaluation whose mean reaches the env's
    solved threshold (time-to-solve runs).

    ``confirm_episodes`` (0: none): an evaluation that reaches the threshold counts as solved only
    if ``confirm_episodes`` more real episodes, played at once from fresh reset seeds
    (``confirm_seed + k * confirm_episodes`` for the k-th confirmation of the run: no two
    confirmations share an episode), reach it too; else training goes on. Why: every curve point
    replays the same ``episodes`` reset seeds, so stopping at the first point at the threshold
    picks the checkpoint that did best on those few starts, and a policy just below the
    threshold passes by chance (about half of the time-to-solve runs' first hits failed their
    final evaluation, docs/compiled.md). A confirmation is an evaluation: its time is kept out
    of the training's, its steps count as ``evaluate`` (selection, when they stop training) and
    its mean is kept in ``curve.confirm_means``.

    ``clock`` and ``cpu_clock`` read wall and CPU
    seconds (``time.perf_counter`` and ``time.process_time``; a test passes clocks that count
    env steps, to check that evaluation time is kept out of the training time).
    """

    def __init__(self, spec: EnvSpec, every: int, episodes: int, seed: int, counts: Counter,
                 on_point: Callable[[int, float, float], None] | None = None, stop_when_solved: bool = False,
                 clock: Callable[[], float] = time.perf_counter, cpu_clock: Callable[[], float] = time.process_time,
                 confirm_episodes: int = 0, confirm_seed: int | None = None):
        super().__init__()
        if confirm_episodes and confirm_seed is None:
            raise ValueError("RealEvalCallback: confirm_episodes needs confirm_seed (the confirmations' first reset seed)")
        self.spec, self.every, self.episodes, self.seed = spec, every, episodes, seed
        self.confirm_episodes, self.confirm_seed = int(confirm_episodes), confirm_seed
        self.counts, self.on_point, self.stop_when_solved = counts, on_point, stop_when_solved
        self.clock, self.cpu_clock = clock, cpu_clock
        self.curve = Curve()
        self._next = every
        self.eval_wall_seconds = 0.0
        self.eval_cpu_seconds = 0.0
        self.rollout_wall_seconds = 0.0
        """Training wall seconds inside SB3's rollout collection (evaluations excluded): the env
        steps and action sampling; the rest of the training time is gradient updates."""
        self._t0 = self._c0 = 0.0
        self._rollout: tuple[float, float] | None = None  # (start, eval seconds at start)

    def _on_training_start(self) -> None:
        self._t0, self._c0 = self.clock(), self.cpu_clock()
        self._point()

    def _on_rollout_start(self) -> None:
        self._rollout = (self.clock(), self.eval_wall_seconds)

    def _on_rollout_end(self) -> None:
        self.rollout_wall_seconds += self._open_rollout(self.clock())
        self._rollout = None

    def _open_rollout(self, now: float) -> float:
        """Rollout seconds of the collection under way (its evaluations excluded), 0 if none."""
        if self._rollout is None:
            return 0.0
        start, eval_at_start = self._rollout
        return now - start - (self.eval_wall_seconds - eval_at_start)

    def _on_step(self) -> bool:
        if self.num_timesteps >= self._next:
            self._next += self.every
            self._point()
        return not (self.stop_when_solved and self.curve.first_solved_step is not None)

    def _on_training_end(self) -> None:
        if not self.curve.steps or self.curve.steps[-1] != self.num_timesteps:
            self._point()

    def _point(self) -> None:
        t, c = self.clock(), self.cpu_clock()
        res = evaluate_real(self.model, self.spec, self.episodes, self.seed, self.counts, "evaluate")
        solved = self.spec.solved_threshold
        hit = self.curve.first_solved_step is None and solved is not None and res.mean >= solved
        if hit and self.confirm_episodes:
            k = len(self.curve.confirm_means)
            more = evaluate_real(self.model, self.spec, self.confirm_episodes,
                                 self.confirm_seed + k * self.confirm_episodes, self.counts, "evaluate")
            self.curve.confirm_means.append(more.mean)
            hit = more.mean >= solved
        t1, c1 = self.clock(), self.cpu_clock()
        self.eval_wall_seconds += t1 - t
        self.eval_cpu_seconds += c1 - c
        wall = t1 - self._t0 - self.eval_wall_seconds
        cpu = c1 - self._c0 - self.eval_cpu_seconds
        c = self.curve
        c.steps.append(int(self.num_timesteps))
        c.means.append(res.mean)
        c.stds.append(res.std)
        c.wall.append(wall)
        if hit:
            c.first_solved_step, c.first_solved_wall, c.first_solved_cpu = int(self.num_timesteps), wall, cpu
            c.first_solved_rollout_wall = self.rollout_wall_seconds + self._open_rollout(t1)
        if self.on_point is not None:  # recording the point (an MLflow write) is the evaluation's cost too
            self.on_point(int(self.num_timesteps), res.mean, res.std)
            self.eval_wall_seconds += self.clock() - t1
            self.eval_cpu_seconds += self.cpu_clock() - c1


@dataclass
class TrainResult:
    model: BaseAlgorithm
    curve: Curve
    wall_seconds: float
    """Training wall seconds, the learning-curve evaluations excluded."""
    cpu_seconds: float
    """Training CPU seconds of this process, the learning-curve evaluations excluded."""
    eval_wall_seconds: float
    rollout_wall_seconds: float = 0.0
    """Of ``wall_seconds``, the time in rollout collection (env steps, actions); the rest is updates."""


def train(
    agent: AgentConfig, env: VecEnv, steps: int, seed: int, callback: RealEvalCallback | None = None,
    logger: Any = None, progress_bar: bool | str = False, env_seed: int | None = None,
) -> TrainResult:
    """Build the agent around ``env`` (agent seed ``seed``, env seed ``env_seed``: see
    ``make_agent``) and train it for ``steps`` env steps. ``progress_bar``: a string shows a
    progress bar named by it (e.g. "surrogate arm, SAC")."""
    model = make_agent(agent, env, seed, logger, env_seed)
    callbacks: Any = callback
    if isinstance(progress_bar, str) and progress_bar:
        callbacks = [c for c in (callback, named_progress_bar(progress_bar)) if c is not None]
        progress_bar = False
    clock, cpu_clock = (callback.clock, callback.cpu_clock) if callback is not None else (time.perf_counter, time.process_time)
    t0, c0 = clock(), cpu_clock()
    try:
        model.learn(total_timesteps=int(steps), callback=callbacks, progress_bar=bool(progress_bar))
    finally:
        close_logger(model)  # its batched rows (tracking.sb3), also when a stop signal ends the run
    wall, cpu = clock() - t0, cpu_clock() - c0
    if callback is None:
        return TrainResult(model, Curve(), wall, cpu, 0.0)
    return TrainResult(model, callback.curve, wall - callback.eval_wall_seconds, cpu - callback.eval_cpu_seconds,
                       callback.eval_wall_seconds, callback.rollout_wall_seconds)


def close_logger(model: Any) -> None:
    """Write what the agent's logger holds (``tracking.sb3`` batches its rows)."""
    logger = getattr(model, "logger", None)
    if logger is not None:
        logger.close()


def make_agent(agent: AgentConfig, env: VecEnv, seed: int, logger: Any = None, env_seed: int | None = None) -> BaseAlgorithm:
    """The untrained SB3 agent around ``env`` (inside ``VecNormalize`` when the config normalizes
    rewards), seeded with ``seed`` (torch, numpy, its action space). SB3 also seeds the env with
    the agent's seed; ``env_seed`` puts the env's own seed back (a real env's reset seeds are a
    purpose of their own: ``seeds``). Without ``logger`` the agent logs nowhere: SB3's default
    logger would make an empty ``SB3-<time>`` folder in the temp dir at every ``learn`` call (a
    Dyna run calls it every round)."""
    from stable_baselines3.common.logger import Logger

    if agent.normalize_reward:
        from stable_baselines3.common.vec_env import VecNormalize

        keywords = getattr(agent.algo, "keywords", {})
        env = VecNormalize(env, norm_obs=False, norm_reward=True, gamma=float(keywords.get("gamma", 0.99)))
    model = agent.algo(env=env, seed=seed, verbose=0)
    if env_seed is not None:
        model.get_env().seed(env_seed)
    model.set_logger(logger if logger is not None else Logger(folder=None, output_formats=[]))
    return model


def named_progress_bar(name: str):
    """SB3's progress bar (tqdm + rich) with a name in front of the count."""
    from stable_baselines3.common.callbacks import ProgressBarCallback

    class NamedProgressBar(ProgressBarCallback):
        def _on_training_start(self) -> None:
            from tqdm.rich import tqdm

            self.pbar = tqdm(total=self.locals["total_timesteps"] - self.model.num_timesteps, desc=name)

    return NamedProgressBar()
