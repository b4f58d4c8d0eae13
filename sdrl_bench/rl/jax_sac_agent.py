"""The compiled SAC behind stable-baselines3's interface (``agent=sac_jax``, ``JaxSAC``): SB3's
off-policy collection in Python, the gradient steps compiled (``rl.jax_sac``); what it shares with
the compiled PPO (compile counters, saving, callbacks) is ``rl.jax_agent.CompiledAgent``."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from sdrl_bench import ConfigError
from sdrl_bench.rl import jax_nets
from sdrl_bench.rl.jax_agent import CompiledAgent, check_loaded_env, read_agent, restore_leaves, write_agent
from sdrl_bench.rl.jax_compile import cpu_pool_threads

SAC_FORMAT = "sdrl-bench-jax-sac-v1"
NO_REWARD_SCALING = ("agent.normalize_reward: the compiled SAC (agent=sac_jax) trains on the env's own rewards; "
                     "set agent.normalize_reward=false")


class JaxSAC(CompiledAgent):
    """SAC with its update compiled by jax (``rl.jax_sac``), behind SB3's interface:
    ``agent=sac_jax``. ``JaxSAC(policy="MlpPolicy", env=..., seed=..., **sac_kwargs)`` takes SB3's
    SAC keyword arguments (``jax_sac.SACConfig.from_kwargs`` refuses the rest in one line).

    ``learn`` is SB3's off-policy loop: ``train_freq`` vector steps collected in Python (the
    actor's actions by numpy, ``jax_sac.HostActor``; callbacks' ``on_step`` after every vector
    step, ``on_rollout_start`` / ``on_rollout_end`` around each collection), then
    ``gradient_steps`` gradient steps in one compiled call on batches drawn on the host from the
    replay buffer (``jax_sac.Replay``). The same path serves the surrogate (its vector env, a Dyna
    refit included) and the real env (the control). The update is compiled once, ahead of time
    and timed (``compile_seconds``); ``rollout_compiles`` stays 0. ``predict`` is SB3's: tanh of
    the (clipped) mean, or a sample, scaled to the action space. Rewards are the env's: a
    ``VecNormalize`` around it (``agent.normalize_reward``) is refused, as is any space but Box.

    ``save`` keeps the networks, the targets, the entropy coefficient and the three Adam states,
    as SB3's does; not the replay buffer (SB3 keeps it apart, ``save_replay_buffer``, which this
    class does not have)."""

    LABEL = "the compiled SAC (agent=sac_jax, sdrl_bench.rl.jax_agent.JaxSAC)"
    """What a missing extra's message names."""

    def __init__(self, policy: str = "MlpPolicy", env: Any = None, seed: int | None = None, verbose: int = 0,
                 device: Any = None, **kwargs: Any):
        from sdrl_bench.rl import jax_sac  # noqa: PLC0415

        if policy != "MlpPolicy":
            raise ConfigError(f"agent.algo.policy: JaxSAC has MlpPolicy only, got {policy!r}")
        self._kwargs = dict(kwargs)
        self._sac = jax_sac
        self.env = env
        self.seed = int(seed or 0)
        self.verbose = verbose
        self._init_counters()
        self.gradient_steps_done = 0
        """Gradient steps taken over this agent's life (SB3's ``_n_updates``)."""
        self.rollout_backend = "python"
        self._jax, self._jnp, _ = jax_nets.modules()
        self._host_rng = np.random.default_rng(np.random.SeedSequence([self.seed, 53]))
        """Collection's draws (gSDE matrices, Gaussian noise, warm-up actions), replay samples and
        the update's keys: one stream, from the seed."""
        self.cfg = None
        self.state = None
        self._train_exe = None
        self._host: Any = None
        self._replay = None
        self._last_obs = None
        self._episodes = 0
        self._ep_returns: list[float] = []
        if env is not None:
            self._setup(env)
            env.seed(self.seed)

    @staticmethod
    def check_config(kwargs: dict[str, Any], n_envs: int, normalize_reward: bool = False) -> None:
        """Config-time validation (``rl.agents.AgentConfig.check``): the optional extra is
        installed, the keyword arguments are ones this SAC has and rewards are not scaled, each
        failure one line."""
        if normalize_reward:
            raise ConfigError(NO_REWARD_SCALING)
        try:
            jax_nets.modules(JaxSAC.LABEL)
        except ImportError as exc:
            raise ConfigError(f"agent.algo: {exc}") from None
        from sdrl_bench.rl.jax_sac import SACConfig  # noqa: PLC0415

        SACConfig.from_kwargs(dict(kwargs), n_envs, "agent.algo")

    def _setup(self, env: Any) -> None:
        from stable_baselines3.common.vec_env import VecNormalize  # noqa: PLC0415

        if isinstance(env, VecNormalize):
            raise ConfigError(NO_REWARD_SCALING)
        space = env.action_space
        if not hasattr(space, "low"):
            raise ConfigError(f"agent=sac_jax: SAC acts in Box spaces, not {type(space).__name__}")
        cfg = self._sac.SACConfig.from_kwargs(self._kwargs, env.num_envs, "agent.algo")
        self._init(cfg, int(np.prod(env.observation_space.shape)), int(np.prod(space.shape)),
                   np.asarray(space.low, np.float32), np.asarray(space.high, np.float32))

    def _init(self, cfg: Any, n_obs: int, n_act: int, low: np.ndarray, high: np.ndarray, nets: Any = None) -> None:
        """The networks (fresh from the seed, or ``nets``), Adam's states, the replay buffer and
        the update's jitted function (compiled on first use)."""
        sac = self._sac
        self.cfg, self._n_obs, self._n_act, self._bounds = cfg, n_obs, n_act, (low, high)
        self.state = sac.init_state(cfg, nets if nets is not None else sac.init_nets(self.seed, cfg, n_obs, n_act))
        self.pool_threads = cpu_pool_threads()
        self._replay = sac.Replay(cfg.rows, cfg.n_envs, n_obs, n_act)
        self._train_fn = self._jax.jit(sac.make_train(cfg, n_act))
        self._train_exe = None
        self._host = None

    def _exploration(self, rng: np.random.Generator, n: int) -> np.ndarray | None:
        return self._actor().exploration(rng, n)  # the draw collection makes (jax_sac.HostActor)

    def _actor(self) -> Any:
        """The host's copy of the actor, made again after each update."""
        if self._host is None:
            self._host = self._sac.HostActor(self.cfg, self.state.nets.actor, *self._bounds)
        return self._host

    def _host_key(self) -> np.ndarray:
        return self._host_rng.integers(0, 2**32, size=2, dtype=np.uint32)

    # ------------------------------------------------------------------ SB3's interface
    def learn(self, total_timesteps: int, callback: Any = None, log_interval: int = 4, tb_log_name: str = "JaxSAC",
              reset_num_timesteps: bool = True, progress_bar: bool = False) -> JaxSAC:
        """Train for at least ``total_timesteps`` more env steps (whole collections of
        ``train_freq`` vector steps), as SB3's off-policy ``learn``: a callback returning False
        from ``on_step`` ends it."""
        if self.env is None:
            raise ValueError("JaxSAC.learn: no env (load(path, env=...) to train on)")
        if reset_num_timesteps:  # as SB3's _setup_learn: the episode count and the returns' window too
            self.num_timesteps, self._episodes, self._ep_returns = 0, 0, []
            self._last_obs = None
        callback = self._callback(callback, progress_bar)
        total_timesteps = target = self.num_timesteps + int(total_timesteps)  # SB3's locals: the target, not the increment
        callback.on_training_start(locals(), globals())
        cfg = self.cfg
        while self.num_timesteps < target:
            if not self._collect(callback, log_interval):
                break
            if self.num_timesteps > cfg.learning_starts and cfg.gradient_steps > 0:
                self._train()
        self._dump()  # the last losses, also where no episode ended (SB3 logs at episode ends only)
        self._noise = None  # stochastic predict's next gSDE draw uses the trained log_std
        callback.on_training_end()
        return self

    def _collect(self, callback: Any, log_interval: int) -> bool:
        """``train_freq`` vector steps into the replay buffer, as SB3's ``collect_rollouts``;
        False when a callback stops training."""
        env, cfg, n = self.env, self.cfg, self.env.num_envs
        if self._last_obs is None:
            self._last_obs = env.reset()
        actor, rng = self._actor(), self._host_rng
        explore = actor.exploration(rng, n)
        callback.on_rollout_start()
        for _ in range(cfg.train_freq):
            obs = np.asarray(self._last_obs, np.float32).reshape(n, -1)
            if self.num_timesteps < cfg.learning_starts and not (cfg.use_sde and cfg.use_sde_at_warmup):
                buffer_actions = rng.uniform(-1.0, 1.0, (n, self._n_act)).astype(np.float32)
            else:
                buffer_actions = actor.sample(obs, rng, explore).astype(np.float32)
            actions = actor.unscale(buffer_actions)
            new_obs, rewards, dones, infos = env.step(actions)
            self.num_timesteps += n
            callback.update_locals(locals())  # SB3's names: actions, buffer_actions, new_obs, rewards, dones, infos
            if not callback.on_step():
                return False
            next_obs = np.array(new_obs, np.float32).reshape(n, -1)
            stored_dones = np.asarray(dones, np.float32).copy()
            for i, done in enumerate(dones):
                info = infos[i]
                if not done:
                    continue
                if info.get("terminal_observation") is not None:
                    next_obs[i] = np.asarray(info["terminal_observation"], np.float32).reshape(-1)
                if info.get("TimeLimit.truncated", False):
                    stored_dones[i] = 0.0
                if "episode" in info:
                    self._ep_returns = [*self._ep_returns[-99:], float(info["episode"]["r"])]
                self._episodes += 1
                if log_interval and self._episodes % log_interval == 0:
                    self._dump()
            self._replay.add(obs, next_obs, buffer_actions, np.asarray(rewards, np.float32), stored_dones)
            self._last_obs = new_obs
        callback.on_rollout_end()
        return True

    def _train(self) -> None:
        """``gradient_steps`` gradient steps in one compiled call (compiled ahead of time on the
        first, and timed)."""
        cfg = self.cfg
        batches = self._replay.sample(self._host_rng, cfg.gradient_steps, cfg.batch_size)
        args = (self.state, batches, self._host_key())
        if self._train_exe is None:
            self._train_exe = self._timed_compile(self._train_fn, *args)
        self.state, stats = self._train_exe(*args)
        self._host = None
        self.gradient_steps_done += cfg.gradient_steps
        log = self._logger()
        log.record("train/n_updates", self.gradient_steps_done, exclude="tensorboard")
        for k, v in stats.items():
            log.record(f"train/{k}", float(v))

    def _dump(self) -> None:
        log = self._logger()
        if self._ep_returns:
            log.record("rollout/ep_rew_mean", float(np.mean(self._ep_returns)))
        log.record("time/episodes", self._episodes, exclude="tensorboard")
        log.dump(step=self.num_timesteps)

    def predict(self, observation: Any, state: Any = None, episode_start: Any = None,
                deterministic: bool = False) -> tuple[np.ndarray, None]:
        """The action for one observation or a batch, in the action space's bounds: tanh of the
        (clipped) mean when ``deterministic``, else a sample (gSDE: the held matrices, ``reset_noise``)."""
        obs = np.asarray(observation, np.float32)
        single = obs.ndim == 1
        batch = obs.reshape(1 if single else obs.shape[0], -1)
        actor = self._actor()
        scaled = (actor.deterministic(batch) if deterministic  # else the predict stream (reset_noise)
                  else actor.sample(batch, self._predict_rng, self._sde_matrices(len(batch))))
        out = actor.unscale(scaled).astype(np.float32)
        return (out[0] if single else out), None

    # ------------------------------------------------------------------ files
    def save(self, path: str | Path) -> None:
        """A zip (``write_agent``): ``config.json`` (the SAC config, sizes, action bounds, steps),
        the networks, targets and log-alpha, and the three Adam states."""
        leaves = self._jax.tree_util.tree_leaves(self.state.nets)
        low, high = self._bounds
        meta = {"format": SAC_FORMAT, "config": asdict(self.cfg), "n_obs": self._n_obs, "n_act": self._n_act,
                "action_low": low.tolist(), "action_high": high.tolist(), "num_timesteps": int(self.num_timesteps),
                "gradient_steps_done": int(self.gradient_steps_done), "seed": self.seed}
        write_agent(path, meta, leaves, self._jax.tree_util.tree_leaves(self.state[1:]))

    @classmethod
    def load(cls, path: str | Path, env: Any = None, device: Any = None, **_: Any) -> JaxSAC:
        """An agent ``save`` wrote (``env``: to train on; its copy count must be the saved one)."""
        from sdrl_bench.rl import jax_sac  # noqa: PLC0415

        meta, leaves, opt = read_agent(path, SAC_FORMAT, "JaxSAC")
        config = dict(meta["config"])
        for k in ("net_arch", "qf_arch"):
            config[k] = tuple(config[k])
        cfg = jax_sac.SACConfig(**config)
        agent = cls(seed=meta["seed"])
        low, high = (np.asarray(meta[k], np.float32) for k in ("action_low", "action_high"))
        nets = restore_leaves(agent._jax, jax_sac.init_nets(agent.seed, cfg, meta["n_obs"], meta["n_act"]), leaves)
        agent._init(cfg, meta["n_obs"], meta["n_act"], low, high, nets)
        agent.state = jax_sac.State(agent.state.nets, *restore_leaves(agent._jax, tuple(agent.state[1:]), opt))
        agent.num_timesteps = int(meta["num_timesteps"])
        agent.gradient_steps_done = int(meta.get("gradient_steps_done", 0))
        if env is not None:
            check_loaded_env("JaxSAC", path, env, cfg.n_envs, agent._n_obs, agent._n_act, agent._bounds, False)
            agent.env = env
        return agent
