"""The compiled PPO behind stable-baselines3's interface (``rl.jax_ppo``, ``agent=ppo_jax``,
``JaxPPO``, described below), and what it shares with the compiled SAC (``rl.jax_sac_agent.JaxSAC``):
``CompiledAgent`` (the compile counters, callbacks, the timed compile) and the agents' file
format (``write_agent``, ``read_agent``). The compiles' caches and XLA's CPU pool are
``rl.jax_compile``'s.

``JaxPPO(policy="MlpPolicy", env=..., seed=..., **ppo_kwargs)`` takes SB3's PPO keyword arguments
(``n_steps``, ``batch_size``, ``n_epochs``, ``gamma``, ``use_sde``, ``policy_kwargs.log_std_init``,
...; ``rl.jax_ppo.PPOConfig.from_kwargs`` refuses the rest in one line) and offers what the harness
calls on an SB3 agent: ``learn(total_timesteps, callback, progress_bar, reset_num_timesteps)``,
``predict``, ``save`` / ``load``, ``get_env``, ``set_logger``, ``num_timesteps``. So every
runner that builds an agent with ``rl.agents.make_agent`` (a transfer run's arms, Dyna, the real
env's control) trains this PPO when the config says ``agent=ppo_jax``, and its evaluations, counts
and records are the ones SB3's agents get.

Where it steps:

* **compiled** (the surrogate arm): when the vector env is the harness's surrogate
  (``surrogate.vec.SurrogateVecEnv``, maybe inside ``VecNormalize``) and ``surrogate.jax_step``
  covers its ``ModelEnv``, each rollout is one compiled call (``jax_ppo.make_rollout``: the
  surrogate's step, resets, gSDE noise and the reward scaling inside it; the vector env itself is
  not stepped) and each update another. The surrogate model's numbers are an argument of the
  compiled rollout: a Dyna refit (``SurrogateVecEnv.swap_model``) of the same structure (term
  table, terms used, members, noise, events: ``JaxStepper.key``) steps through the same program
  (``rollout_swaps``), another structure compiles again (``rollout_compiles``); the episodes
  under way go on. ``compile_seconds`` sums the compile times (ahead-of-time, timed apart; they are inside the
  training wall the callbacks see); ``compile_programs`` counts the programs compiled and
  ``compile_cache_hits`` those JAX's persistent compilation cache (``use_compilation_cache``) held
  already, so a reader tells a cold compile from a cached one; ``lowering_cache_hits`` those
  whose lowering came from the lowering cache beside it (``compile_program``: traced, not
  lowered again). The programs are compiled with ``jax_ppo.COMPILER_OPTIONS``.
* **Python** (the real env's control, a surrogate ``jax_step`` does not cover, or
  ``compiled_rollout=False``: ``agent.algo.compiled_rollout=false``, an ablation that keeps the
  networks and the update and steps the surrogate's vector env in Python instead): the rollout
  steps the vector env in Python as SB3's ``collect_rollouts`` does (the sampled action stored
  unclipped and stepped clipped; the timeout bootstrap from ``terminal_observation``;
  ``VecNormalize``'s own reward scaling); the update is the same compiled one.

Callbacks (``rl.agents.RealEvalCallback``) are SB3's: in the Python path ``on_step`` follows
every vector step, as in SB3; in the compiled path once per rollout, after it and before the
update (where SB3's last ``on_step`` of a rollout falls), with ``num_timesteps`` advanced by the
whole rollout. An evaluation cadence that is a multiple of ``n_envs x n_steps`` therefore sees
the same policies in both. ``on_rollout_start`` / ``on_rollout_end`` bracket each rollout.

Hand-written, and why: SB3's ``BaseAlgorithm`` ties its policy to torch modules and its rollout to
a ``VecEnv``; sbx (SB3's JAX port) keeps the VecEnv outside the compiled code. The harness needs
the rollout inside the compiled program (``jax_ppo``) behind the interface its runners use, which
is this class; SB3's callback classes are used as they are.
"""


from __future__ import annotations

import io
import json
import os
import time
import warnings
import zipfile
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np

from sdrl_bench import ConfigError
from sdrl_bench.rl import jax_nets
from sdrl_bench.rl import jax_ppo
from sdrl_bench.rl.jax_compile import cache_hits, compile_program, cpu_pool_threads
from sdrl_bench.rl.jax_ppo import PPOConfig

FORMAT = "sdrl-bench-jax-ppo-v1"


def _surrogate_of(env: Any) -> tuple[Any, Any]:
    """(the ModelEnv under ``env`` or None, the VecNormalize around it or None)."""
    from stable_baselines3.common.vec_env import VecNormalize  # noqa: PLC0415

    norm = env if isinstance(env, VecNormalize) else None
    inner = env.venv if norm is not None else env
    return getattr(inner, "surrogate", None), norm


def _compiled_rollout(kwargs: dict[str, Any]) -> bool:
    """``compiled_rollout`` in ``kwargs`` (this class's own setting, not SB3's; ``PPOConfig``
    passes over it): a bool, True unless given; anything else is one line naming the key."""
    value = kwargs.get("compiled_rollout", True)
    if not isinstance(value, bool):
        raise ConfigError(f"agent.algo.compiled_rollout: true or false, got {value!r}")
    return value


def write_agent(path: str | Path, meta: dict[str, Any], leaves: list, optimizer: list) -> None:
    """A compiled agent's file: a zip of ``config.json`` (``meta``), ``params.npz`` (the
    parameters' arrays in pytree order) and ``optimizer.npz`` (the optimisers' states, Adam's
    moments and step counts, in pytree order: as SB3's ``save`` keeps its optimisers', so that a
    loaded agent trains on where it stopped). Written beside ``path`` and renamed onto it, so an
    interrupted save leaves the file that was there, not half of a new one."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with zipfile.ZipFile(tmp, "w") as zf:
            zf.writestr("config.json", json.dumps(meta, indent=1))
            for name, arrays in (("params.npz", leaves), ("optimizer.npz", optimizer)):
                buf = io.BytesIO()
                np.savez(buf, *[np.asarray(x) for x in arrays])
                zf.writestr(name, buf.getvalue())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def read_agent(path: str | Path, fmt: str, name: str) -> tuple[dict[str, Any], list[np.ndarray], list[np.ndarray] | None]:
    """(meta, parameters, optimiser states or None) of a file ``write_agent`` wrote (None: a
    file from before the optimisers were kept); another format, or a file that is not a whole
    agent (cut short, or without its parameters), is one error naming the file."""
    try:
        with zipfile.ZipFile(path) as zf:
            missing = [part for part in ("config.json", "params.npz") if part not in zf.namelist()]
            if missing:
                raise ValueError(f"{path}: not a whole {name} agent file (no {' or '.join(missing)} in it: "
                                 f"cut short, or another kind of file)")
            meta = json.loads(zf.read("config.json"))
            got = [np.load(io.BytesIO(zf.read(part))) if part in zf.namelist() else None
                   for part in ("params.npz", "optimizer.npz")]
    except (zipfile.BadZipFile, EOFError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: not a readable {name} agent file ({type(e).__name__}: {e})") from None
    if meta.get("format") != fmt:
        raise ValueError(f"{path}: not a {name} agent ({meta.get('format')!r})")
    leaves, opt = ([a[f"arr_{i}"] for i in range(len(a.files))] if a is not None else None for a in got)
    return meta, leaves, opt


def restore_leaves(jax: Any, fresh: Any, saved: list[np.ndarray] | None) -> Any:
    """``fresh``'s pytree with ``saved``'s arrays (jax arrays), or ``fresh`` where nothing was saved;
    a file whose arrays do not fit it is one error."""
    if saved is None:
        return fresh
    treedef = jax.tree_util.tree_structure(fresh)
    if treedef.num_leaves != len(saved):
        raise ValueError(f"a saved compiled agent holds {len(saved)} arrays where its config builds {treedef.num_leaves}")
    return jax.tree_util.tree_unflatten(treedef, [jax.numpy.asarray(x) for x in saved])


def check_loaded_env(who: str, path: Any, env: Any, n_envs: int, n_obs: int, n_act: int,
                      bounds: tuple[np.ndarray | None, np.ndarray | None], normalize_reward: bool) -> None:
    """The env a saved agent is loaded to train on fits the file, each mismatch one line naming
    it: the copy count, the observation's size, the action space (a categorical agent's count, a
    Box agent's size and bounds: the file's bounds scale its actions), and the reward scaling
    (``VecNormalize``'s ``norm_reward``). SB3's ``check_for_correct_spaces`` compares two gymnasium
    spaces; the file keeps sizes and bounds, not spaces, so the comparison is written here."""
    if env.num_envs != n_envs:
        raise ConfigError(f"{who}.load: {path} was trained with {n_envs} env copies, the env has {env.num_envs}")
    got_obs = int(np.prod(env.observation_space.shape))
    if got_obs != n_obs:
        raise ConfigError(f"{who}.load: {path} takes observations of size {n_obs}, the env's are {got_obs}")
    space, (low, high) = env.action_space, bounds
    if low is None:
        if getattr(space, "n", None) != n_act or hasattr(space, "low"):
            raise ConfigError(f"{who}.load: {path} acts in Discrete({n_act}), the env in {space}")
    elif not hasattr(space, "low") or int(np.prod(space.shape)) != n_act or not (
            np.array_equal(np.asarray(space.low, np.float32).ravel(), np.ravel(low))
            and np.array_equal(np.asarray(space.high, np.float32).ravel(), np.ravel(high))):
        raise ConfigError(f"{who}.load: {path} acts in a Box of size {n_act} between {np.ravel(low).tolist()} and "
                          f"{np.ravel(high).tolist()}, the env in {space}")
    _, norm = _surrogate_of(env)
    scaled = norm is not None and bool(norm.norm_reward)
    if scaled != normalize_reward:
        raise ConfigError(f"{who}.load: {path} was trained {'with' if normalize_reward else 'without'} reward scaling "
                          f"(agent.normalize_reward), the env is {'wrapped in' if scaled else 'not in'} VecNormalize's")


class CompiledAgent:
    """What the compiled agents (``JaxPPO``, ``JaxSAC``) share behind SB3's interface: the
    compile counters the runners record, ``get_env``, ``set_logger``, the callback's set-up, and
    the ahead-of-time, timed compile of a program (``compile_program``)."""

    USES_JAX = True
    """Read by the CLI (``cli.train.prepare``): size XLA's CPU pool and turn the compilation cache
    on before anything creates JAX's backend."""
    LABEL = "a compiled agent (sdrl_bench.rl.jax_agent)"
    """What a missing extra's message names."""
    policy_aliases = {"MlpPolicy": "MlpPolicy"}
    """The policies it has, under SB3's attribute name (``rl.agents.check_policy`` reads it)."""

    def _init_counters(self) -> None:
        self.num_timesteps = 0
        self.compile_seconds = 0.0
        """Seconds spent compiling (counted inside ``learn``'s wall)."""
        self.compile_programs = 0
        """Programs compiled ahead of time."""
        self.compile_cache_hits = 0
        """Of ``compile_programs``, those loaded from JAX's persistent compilation cache
        (``use_compilation_cache``) instead of compiled: a cold compile has none."""
        self.lowering_cache_hits = 0
        """Of ``compile_programs``, those whose lowering came from the lowering cache
        (``compile_program``): traced, not lowered."""
        self.pool_threads: int | None = None
        """Threads in XLA's CPU pool when the networks were built (``cpu_pool_threads``; config
        ``jax_threads``): they run every compiled program."""
        self.rollout_compiles = 0
        """Rollouts compiled with the surrogate's step (0: every rollout stepped in Python)."""
        self.logger: Any = None
        self._predict_rng = np.random.default_rng(np.random.SeedSequence([self.seed, 61]))
        """Stochastic ``predict``'s draws: a stream of its own, so that sampling actions never moves
        what training draws next."""
        self._noise: np.ndarray | None = None
        """gSDE's matrices for stochastic ``predict`` (``reset_noise``): row 0 for a single
        observation, rows 1.. one per env copy."""

    def _exploration(self, rng: np.random.Generator, n: int) -> np.ndarray | None:
        """gSDE: ``n`` exploration matrices (n, features, actions) drawn from ``rng``, entries
        N(0, exp(log_std)^2); None without gSDE."""
        raise NotImplementedError

    def reset_noise(self, n_envs: int = 1) -> None:
        """gSDE: draw the exploration matrices stochastic ``predict`` uses, as SB3's
        ``policy.reset_noise(n_envs)`` does. A batch of ``n_envs`` observations gets one matrix
        per row; a single observation, or a batch of another size, one matrix for every row.
        They stay until the next call or the next ``learn`` (whose trained log_std the next
        draw uses), so an episode played by stochastic ``predict`` follows one perturbed policy,
        as under SB3. SB3 keeps its last rollout's matrices after training; these are drawn
        afresh from this agent's own predict stream. Without gSDE it does nothing."""
        self._noise = self._exploration(self._predict_rng, int(n_envs) + 1)

    def _sde_matrices(self, rows: int) -> np.ndarray | None:
        """The held gSDE matrices for a batch of ``rows`` observations (``reset_noise``; drawn for
        the config's copies on first use), (rows, features, actions); None without gSDE."""
        if self._noise is None:
            self.reset_noise(self.cfg.n_envs)
        if self._noise is None:  # no gSDE
            return None
        per_copy = self._noise[1:]
        if rows > 1 and rows == len(per_copy):
            return per_copy
        return np.broadcast_to(self._noise[0], (rows, *self._noise.shape[1:]))

    def _timed_compile(self, fn: Any, *args: Any) -> Any:
        hits, t0 = cache_hits(), time.perf_counter()
        out, lowered = compile_program(fn, args, jax_ppo.COMPILER_OPTIONS)
        self.compile_seconds += time.perf_counter() - t0
        self.compile_programs += 1
        self.compile_cache_hits += cache_hits() - hits
        self.lowering_cache_hits += lowered
        return out

    def get_env(self) -> Any:
        return self.env

    def set_logger(self, logger: Any) -> None:
        self.logger = logger

    def _logger(self) -> Any:
        if self.logger is None:
            from stable_baselines3.common.logger import Logger  # noqa: PLC0415

            self.logger = Logger(folder=None, output_formats=[])
        return self.logger

    def _callback(self, callback: Any, progress_bar: bool) -> Any:
        """SB3's callback handling in ``learn``: a list, a function or None made one callback,
        with a progress bar when asked, initialised with this agent."""
        from stable_baselines3.common.callbacks import CallbackList, ConvertCallback, ProgressBarCallback  # noqa: PLC0415

        if isinstance(callback, list):
            callback = CallbackList(callback)
        if not hasattr(callback, "init_callback"):
            callback = ConvertCallback(callback)
        if progress_bar:
            callback = CallbackList([callback, ProgressBarCallback()])
        callback.init_callback(self)
        return callback


class JaxPPO(CompiledAgent):
    """PPO with the rollout and the update compiled by jax, behind SB3's interface (module
    docstring)."""

    LABEL = "the compiled PPO (agent=ppo_jax, sdrl_bench.rl.jax_agent.JaxPPO)"
    """What a missing extra's message names."""

    def __init__(self, policy: str = "MlpPolicy", env: Any = None, seed: int | None = None, verbose: int = 0,
                 device: Any = None, **kwargs: Any):
        if policy != "MlpPolicy":
            raise ConfigError(f"agent.algo.policy: JaxPPO has MlpPolicy only, got {policy!r}")
        self._kwargs = dict(kwargs)
        self.compiled_rollout = _compiled_rollout(self._kwargs)
        """Whether a surrogate the compiled step covers is stepped compiled (the default) or in
        Python like a real env (``agent.algo.compiled_rollout=false``)."""
        self.env = env
        self.seed = int(seed or 0)
        self.verbose = verbose
        self._init_counters()  # compile_programs: the env's start, the rollout, the update
        self.rollout_swaps = 0
        """Surrogate models (a Dyna refit) stepped by a rollout compiled before: the same
        structure (``JaxStepper.key``) and spec, new numbers, no compile."""
        self.diverged_episodes = 0
        """Surrogate episodes ended by the model's divergence guard in compiled rollouts."""
        self.rollout_backend: str | None = None
        """"compiled" or "python": where the last ``learn`` stepped."""
        self._jax, self._jnp, _ = jax_nets.modules()
        self._key = self._jax.random.key(self.seed)
        self._host_rng = np.random.default_rng(np.random.SeedSequence([self.seed, 31]))
        """The compiled loop's draws made on the host (``_host_key``, ``_host_perms``): its own stream, from the seed."""
        self.cfg: PPOConfig | None = None
        self.net: dict | None = None
        self._opt = None
        self._compiled: tuple | None = None  # (model, spec, compiled rollout, jax_ppo.Surrogate of the model)
        self._cenv = self._cobs = None  # the compiled loop's env state and observations
        self._last_obs = None  # the Python loop's
        self._act = self._value = None
        self._host: tuple | None = None  # (the net it was made of, jax_nets.HostPolicy): predict's deterministic action
        self._bounds: tuple[np.ndarray, np.ndarray] | None = None
        if env is not None:
            self._setup(env)
            env.seed(self.seed)

    @staticmethod
    def check_config(kwargs: dict[str, Any], n_envs: int, normalize_reward: bool = False) -> None:
        """Config-time validation (``rl.agents.AgentConfig.check``, before any env step): the
        optional extra is installed and the recipe's keyword arguments are ones this PPO has,
        each failure one line naming the key. Reward scaling it has (``normalize_reward``)."""
        try:
            jax_nets.modules(JaxPPO.LABEL)
        except ImportError as exc:
            raise ConfigError(f"agent.algo: {exc}") from None
        _compiled_rollout(kwargs)
        PPOConfig.from_kwargs(dict(kwargs), n_envs, False, "agent.algo")

    # ------------------------------------------------------------------ set-up
    def _split(self) -> Any:
        self._key, k = self._jax.random.split(self._key)
        return k

    def _exploration(self, rng: np.random.Generator, n: int) -> np.ndarray | None:
        """As ``jax_nets.exploration_matrices``, drawn by numpy (``CompiledAgent.reset_noise``)."""
        log_std = None if self.net is None else self.net.get("log_std")
        if log_std is None or log_std.ndim == 1:
            return None
        return (np.exp(np.asarray(log_std)) * rng.standard_normal((n, *log_std.shape))).astype(np.float32)

    def _host_key(self) -> np.ndarray:
        """A jax key's data (uint32 (2,)) drawn by numpy, for a compiled program to wrap. Why on the
        host: an eager ``jax.random.split`` costs 83 us, a numpy draw 1 us (MountainCar's fast pack,
        whose iteration takes 14-18 ms; measured on this 2-core machine)."""
        return self._host_rng.integers(0, 2**32, size=2, dtype=np.uint32)

    def _host_perms(self) -> np.ndarray:
        """The update's epoch permutations, (n_epochs, rollout size) int32, drawn by numpy
        (``jax_ppo.make_update``'s ``shuffled_outside``): 0.15 ms against the 0.53 ms of the
        in-program sort (measured as ``_host_key``)."""
        n = self.cfg.rollout_size
        return np.stack([self._host_rng.permutation(n).astype(np.int32) for _ in range(self.cfg.n_epochs)])

    def _setup(self, env: Any) -> None:
        """The config (the env's copy count, VecNormalize's scaling), the networks, the
        optimiser and the compiled update, once."""
        space = env.action_space
        discrete = hasattr(space, "n") and not hasattr(space, "low")
        if not discrete and not hasattr(space, "low"):
            raise ConfigError(f"agent=ppo_jax: the compiled PPO acts in Box or Discrete spaces, not {type(space).__name__}")
        _, norm = _surrogate_of(env)
        cfg = PPOConfig.from_kwargs(self._kwargs, env.num_envs, norm is not None and bool(norm.norm_reward), "agent.algo")
        if norm is not None:
            cfg = replace(cfg, clip_reward=float(norm.clip_reward))
        n_obs = int(np.prod(env.observation_space.shape))
        if discrete:
            self._init(cfg, n_obs, int(space.n), None, None)
        else:
            self._init(cfg, n_obs, int(np.prod(space.shape)), np.asarray(space.low, np.float32),
                       np.asarray(space.high, np.float32))

    def _init(self, cfg: PPOConfig, n_obs: int, n_act: int, low: np.ndarray | None, high: np.ndarray | None) -> None:
        """Networks (a categorical policy when ``low`` is None), optimiser, compiled functions."""
        jax = self._jax
        self.cfg, self._bounds, self._n_obs, self._n_act = cfg, (low, high), n_obs, n_act
        self.discrete = low is None
        self.net = jax_nets.init_net(self._split(), n_obs, n_act, cfg, self.discrete)
        self.pool_threads = cpu_pool_threads()
        self._opt = jax_ppo.optimizer(cfg).init(self.net)
        update = jax_ppo.make_update(cfg, shuffled_outside=True)  # the epochs' permutations: _host_perms

        def learn_step(net, opt, traj, last_value, perms):
            return update(net, opt, jax_ppo.make_batch(cfg, traj, last_value), perms)

        self._update_fn = jax.jit(learn_step)
        self._updates: dict[str, Any] = {}

        def act(net, obs, key, explore):
            action, logp, _ = jax_nets.sample_action(net, obs, key, explore)
            return action, logp, jax_nets.value(net, obs)

        self._act = jax.jit(act)
        self._value = jax.jit(jax_nets.value)
        self._explore = jax.jit(lambda net, key: jax_nets.exploration_matrices(net, key, cfg.n_envs))

    # ------------------------------------------------------------------ SB3's interface
    def learn(self, total_timesteps: int, callback: Any = None, log_interval: int = 1, tb_log_name: str = "JaxPPO",
              reset_num_timesteps: bool = True, progress_bar: bool = False) -> JaxPPO:
        """Train for at least ``total_timesteps`` more env steps (whole rollouts), as SB3's
        ``learn``: a callback returning False from ``on_step`` ends it."""
        if self.env is None:
            raise ValueError("JaxPPO.learn: no env (load(path, env=...) to train on)")
        if reset_num_timesteps:
            self.num_timesteps = 0
            self._cenv = self._last_obs = None
        callback = self._callback(callback, progress_bar)
        total_timesteps = target = self.num_timesteps + int(total_timesteps)  # SB3's locals: the target, not the increment
        callback.on_training_start(locals(), globals())
        menv, _ = _surrogate_of(self.env)
        compiled = self.compiled_rollout and menv is not None and self._compile_for(menv)
        self.rollout_backend = "compiled" if compiled else "python"
        while self.num_timesteps < target:
            got = self._rollout_compiled(callback) if compiled else self._rollout_python(callback)
            if got is None:
                break
            traj, last_value, episodes = got
            args = (self.net, self._opt, traj, last_value, self._host_perms())
            update = self._updates.get(self.rollout_backend)
            if update is None:  # compiled ahead of time, once per rollout layout, and timed
                update = self._updates[self.rollout_backend] = self._timed_compile(self._update_fn, *args)
            self.net, self._opt, stats = update(*args)
            log = self._logger()
            if episodes:
                log.record("rollout/ep_rew_mean", float(np.mean(episodes)))
            for k, v in stats.items():
                log.record(f"train/{k}", float(v))
            log.dump(step=self.num_timesteps)
        self._noise = None  # stochastic predict's next gSDE draw uses the trained log_std
        callback.on_training_end()
        return self

    def compiled_iteration(self) -> tuple[float, float]:
        """One training iteration in the surrogate, bare: the compiled rollout, then the compiled
        update, each waited for, with no callback and no logging (what ``benchmarks/eval_interlude.py``
        and ``studies/compiled_recipe.py`` time). It draws its keys and permutations as ``learn``
        does, so it trains what another ``learn`` iteration would. Needs an earlier ``learn`` whose
        rollout ran compiled. Returns (rollout seconds, update seconds)."""
        if self.rollout_backend != "compiled" or self._compiled is None or "compiled" not in self._updates:
            raise RuntimeError("JaxPPO.compiled_iteration: no compiled rollout and update yet (call learn first, "
                               "in a surrogate the compiled rollout covers)")
        _, _, rollout, sur = self._compiled
        t0 = time.perf_counter()
        env, obs, traj, last_value = rollout(self.net, self._cenv, self._cobs, self._host_key(), sur.params)
        self._jax.block_until_ready(last_value)
        t1 = time.perf_counter()
        self.net, self._opt, stats = self._updates["compiled"](self.net, self._opt, traj, last_value, self._host_perms())
        self._jax.block_until_ready(stats)
        self._cenv, self._cobs = env, obs
        self.num_timesteps += self.cfg.rollout_size
        return t1 - t0, time.perf_counter() - t1

    def _compile_for(self, menv: Any) -> bool:
        """Whether the rollout runs compiled in ``menv`` (built, and compiled ahead of time, for
        its current model); a surrogate ``jax_step`` does not cover steps in Python, warned once."""
        from sdrl_bench.surrogate.jax_step import unsupported  # noqa: PLC0415

        held = self._compiled
        exe = None
        if held is not None and held[0] is menv.model and held[1] is menv.spec:
            exe, sur = held[2], held[3]
        else:
            try:
                missing = unsupported(menv)
                sur = jax_ppo.surrogate(menv) if not missing else None
            except NotImplementedError as exc:
                missing = [str(exc)]
            if missing:
                warnings.warn(f"agent=ppo_jax: the surrogate of env '{menv.spec.name}' steps in Python, not compiled: "
                              f"{'; '.join(missing)}", stacklevel=3)
                return False
            if held is not None and held[1] is menv.spec and held[3].key == sur.key:
                exe = held[2]  # a refit: new numbers (sur.params), the same program
                self.rollout_swaps += 1
        if self._cenv is None:  # fresh episodes (first learn, or one that resets): one program, not op by op
            cfg = self.cfg
            init = self._jax.jit(lambda key, params: jax_ppo.init_env(sur, key, cfg.n_envs, cfg, params))
            key = self._split()
            self._cenv, self._cobs = self._timed_compile(init, key, sur.params)(key, sur.params)
        if exe is None:
            roll, wrap = jax_ppo.make_rollout(sur, self.cfg), self._jax.random.wrap_key_data
            rollout = self._jax.jit(lambda net, env, obs, key_data, params: roll(net, env, obs, wrap(key_data), params))
            exe = self._timed_compile(rollout, self.net, self._cenv, self._cobs, self._host_key(), sur.params)
            self.rollout_compiles += 1
        self._compiled = (menv.model, menv.spec, exe, sur)
        return True

    def _rollout_compiled(self, callback: Any) -> tuple | None:
        callback.on_rollout_start()
        _, _, exe, sur = self._compiled
        env, obs, traj, last_value = exe(self.net, self._cenv, self._cobs, self._host_key(), sur.params)
        self._jax.block_until_ready(last_value)
        self._cenv, self._cobs = env, obs
        self.num_timesteps += self.cfg.rollout_size
        self.diverged_episodes += int(np.asarray(traj.diverged).sum())
        # one callback step for the whole rollout: its episode ends and task rewards, (n_steps, n_envs),
        # under SB3's names (an episode-counting callback counts right; a per-step one sees a rollout)
        callback.update_locals({"dones": np.asarray(traj.done), "rewards": np.asarray(traj.task_reward)})
        if not callback.on_step():
            return None
        callback.on_rollout_end()
        done = np.asarray(traj.done)
        return traj, last_value, np.asarray(traj.episode_return)[done].tolist()

    def _rollout_python(self, callback: Any) -> tuple | None:
        """One rollout stepped in the vector env, as SB3's ``collect_rollouts``."""
        env, cfg, gamma = self.env, self.cfg, self.cfg.gamma
        low, high = self._bounds
        n = cfg.n_envs
        if self._last_obs is None:
            self._last_obs = env.reset()
        explore = self._explore(self.net, self._split())
        obs_b, act_b, logp_b, val_b, rew_b, done_b, episodes = [], [], [], [], [], [], []
        callback.on_rollout_start()
        for _ in range(cfg.n_steps):
            obs = np.asarray(self._last_obs, np.float32).reshape(n, -1)
            actions, logp, v = (np.asarray(x) for x in self._act(self.net, obs, self._split(), explore))
            clipped_actions = actions if self.discrete else np.clip(actions, low, high)
            new_obs, rewards, dones, infos = env.step(clipped_actions)
            self.num_timesteps += n
            callback.update_locals(locals())  # SB3's names: actions, clipped_actions, new_obs, rewards, dones, infos
            if not callback.on_step():
                return None
            rewards = np.asarray(rewards, np.float32).copy()
            for i, done in enumerate(dones):
                info = infos[i]
                if "episode" in info:
                    episodes.append(float(info["episode"]["r"]))
                if done and info.get("terminal_observation") is not None and info.get("TimeLimit.truncated", False):
                    term_obs = np.asarray(info["terminal_observation"], np.float32).reshape(1, -1)
                    rewards[i] += gamma * float(np.asarray(self._value(self.net, term_obs))[0])
            obs_b.append(obs), act_b.append(actions), logp_b.append(logp), val_b.append(v)
            rew_b.append(rewards), done_b.append(np.asarray(dones, bool))
            self._last_obs = new_obs
        last_value = self._value(self.net, np.asarray(self._last_obs, np.float32).reshape(n, -1))
        callback.on_rollout_end()
        stack = np.stack
        traj = jax_ppo.Transition(stack(obs_b), stack(act_b), stack(logp_b), stack(val_b), stack(rew_b), stack(done_b),
                                  *([None] * 8))
        return traj, last_value, episodes

    def predict(self, observation: Any, state: Any = None, episode_start: Any = None,
                deterministic: bool = False) -> tuple[np.ndarray, None]:
        """The action for one observation or a batch: the mean clipped to the action space or
        the most probable index (``deterministic``), or a sample, clipped: plain Gaussian noise,
        a categorical draw, or gSDE's held matrices (``reset_noise``)."""
        obs = np.asarray(observation, np.float32)
        single = obs.ndim == 1
        batch = obs.reshape(1 if single else obs.shape[0], -1)
        if deterministic:  # on the host: an evaluation asks once per real step (jax_nets.HostPolicy)
            if self._host is None or self._host[0] is not self.net:
                self._host = (self.net, jax_nets.HostPolicy(self.net, *self._bounds))
            out = self._host[1](batch)
        else:  # from the predict stream, never the training's (CompiledAgent.reset_noise)
            explore = self._sde_matrices(len(batch))
            noise = None
            if explore is None:
                draw = self._predict_rng.gumbel if self.discrete else self._predict_rng.standard_normal
                noise = draw(size=(len(batch), self._n_act)).astype(np.float32)
            action, _, _ = jax_nets.sample_action(self.net, batch, None, explore, noise)
            out = np.asarray(action) if self.discrete else np.clip(np.asarray(action), *self._bounds)
        return (out[0] if single else out), None

    # ------------------------------------------------------------------ files
    def save(self, path: str | Path) -> None:
        """A zip (``write_agent``): ``config.json`` (the PPO config, sizes, action bounds, steps),
        the networks' arrays and Adam's state."""
        leaves = self._jax.tree_util.tree_leaves(self.net)
        low, high = self._bounds
        meta = {"format": FORMAT, "config": asdict(self.cfg), "n_obs": self._n_obs, "n_act": self._n_act,
                "action_low": None if low is None else low.tolist(), "action_high": None if high is None else high.tolist(),
                "num_timesteps": int(self.num_timesteps), "seed": self.seed, "compiled_rollout": self.compiled_rollout}
        write_agent(path, meta, leaves, self._jax.tree_util.tree_leaves(self._opt))

    @classmethod
    def load(cls, path: str | Path, env: Any = None, device: Any = None, **_: Any) -> JaxPPO:
        """An agent ``save`` wrote (``env``: to train on; its copy count must be the saved one)."""
        meta, leaves, opt = read_agent(path, FORMAT, "JaxPPO")
        agent = cls(seed=meta["seed"], compiled_rollout=bool(meta.get("compiled_rollout", True)))
        cfg = PPOConfig(**meta["config"])
        bounds = [None if meta[k] is None else np.asarray(meta[k], np.float32) for k in ("action_low", "action_high")]
        agent._init(cfg, meta["n_obs"], meta["n_act"], *bounds)
        agent.net = restore_leaves(agent._jax, agent.net, leaves)
        agent._opt = restore_leaves(agent._jax, jax_ppo.optimizer(cfg).init(agent.net), opt)
        agent.num_timesteps = int(meta["num_timesteps"])
        if env is not None:
            check_loaded_env("JaxPPO", path, env, cfg.n_envs, agent._n_obs, agent._n_act, agent._bounds,
                              cfg.normalize_reward)
            agent.env = env
        return agent


def __getattr__(name: str) -> Any:
    """``JaxSAC`` under its older path, ``sdrl_bench.rl.jax_agent.JaxSAC``: ``agent=sac_jax``'s
    ``_target_`` names it there, because a run's config keys (a sweep's resume, the real arm's
    reuse) hash the resolved config, and stored runs and users' packs name that path. Imported on
    first use: ``rl.jax_sac_agent`` imports this module."""
    if name == "JaxSAC":
        from sdrl_bench.rl.jax_sac_agent import JaxSAC  # noqa: PLC0415

        return JaxSAC
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
