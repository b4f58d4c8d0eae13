"""Expert collectors: the paper's pre-trained agents, trained here on first use and cached.

Hub downloads are impossible here, so an expert is trained with its zoo settings the first time
it is asked for, with a progress bar and a log line, and cached as an SB3 zip under
``cache_dir`` keyed by (env, algorithm, seed, budget). A missing expert is trained, never
replaced by a random policy.
"""

from __future__ import annotations

import functools
import logging
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from sdrl_bench import ConfigError, file_in_the_way, seeds
from sdrl_bench.envs.base import EnvSpec, Policy
from sdrl_bench.rl.agents import AgentConfig, real_vec_env, train

log = logging.getLogger(__name__)


@dataclass
class ExpertPolicy:
    """A policy factory for ``data.collect``: ``ExpertPolicy(...)(spec, env) -> policy``.

    ``agent`` is the algorithm with its zoo hyperparameters; ``budget`` its training steps.
    """

    agent: AgentConfig
    budget: int
    seed: int = 0
    cache_dir: str = "mlruns/experts"
    progress_bar: bool | str = True
    """A progress bar while the expert trains; a string names it (``rl.agents.train``)."""
    _model: Any = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        if isinstance(self.budget, bool) or not isinstance(self.budget, int) or self.budget <= 0:
            raise ConfigError(f"env.expert.budget (collector.policy.budget): a positive integer is required, got {self.budget!r}")

    def validate(self, spec: EnvSpec) -> None:
        """Config-time check (no training): the expert's algorithm can act in the env, and its
        cache folder can be one (a file there failed only after the expert's training)."""
        self.agent.check(spec, "env.expert.agent")
        blocker = file_in_the_way(self.cache_dir)
        if blocker is not None:
            raise ConfigError(f"collector.policy.cache_dir: {blocker} is a file, not a folder (the expert would be "
                              f"cached in {self.path(spec)})")

    def path(self, spec: EnvSpec) -> Path:
        return Path(self.cache_dir) / f"{spec.name}-{self.agent.name}-s{self.seed}-n{int(self.budget)}.zip"

    def load_or_train(self, spec: EnvSpec, act_only: bool = False) -> tuple[Any, bool]:
        """(the SB3 model, whether it came from the cache). ``act_only``: a cached expert is
        loaded to act, not to train on (``act_only_load``)."""
        self.agent.check(spec)
        path = self.path(spec)
        algo_cls = self.agent.algo.func if hasattr(self.agent.algo, "func") else self.agent.algo
        if path.is_file():
            log.info("expert: using cached %s", path)
            try:
                return (act_only_load(algo_cls, path) if act_only else algo_cls.load(path, device="cpu")), True
            except Exception as exc:
                raise ConfigError(f"collector: cached expert {path} cannot be loaded ({exc}); delete it to retrain") from exc
        log.warning(
            "expert: no cached %s expert for %s (seed %d, %d steps): training it now with its zoo settings",
            self.agent.name, spec.name, self.seed, self.budget,
        )
        t0 = time.perf_counter()
        env_seed = seeds.reset_seed(self.seed, "expert")
        venv = real_vec_env(spec, self.agent.n_envs, env_seed, Counter(), "expert")
        result = train(self.agent, venv, self.budget, seeds.int_seed(self.seed, "agent"), progress_bar=self.progress_bar,
                       env_seed=env_seed)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.zip")
        result.model.save(tmp)
        tmp.replace(path)  # atomic: a concurrent run never reads half a file
        log.warning("expert: trained in %.0f s, cached at %s", time.perf_counter() - t0, path)
        return result.model, False

    def __call__(self, spec: EnvSpec, env: gym.Env) -> Policy:
        if self._model is None:
            self._model, _ = self.load_or_train(spec, act_only=True)
        return deterministic_policy(self._model, bool(spec.n_discrete_actions))


class _NoOptimizer:
    """Stands in for a policy's optimizer in a model loaded to act (``act_only_load``): it takes
    the optimizer's arguments and saved state and refuses a step."""

    def __init__(self, params: Any, lr: Any = None, **kwargs: Any):
        pass

    def load_state_dict(self, state: Any, strict: bool = True) -> None:  # SB3 passes strict to what is no Optimizer
        pass

    def state_dict(self) -> dict:
        return {}

    def zero_grad(self, set_to_none: bool = True) -> None:
        pass

    def step(self, closure: Any = None) -> None:
        raise RuntimeError("experts: this expert was loaded to act only (act_only_load); load it with SB3 to train it")


def act_only_load(algo_cls: Any, path: str | Path, device: str = "cpu") -> Any:
    """The SB3 model (of class ``algo_cls``) at ``path`` with its policy's optimizers left out
    (``_NoOptimizer``), for a collector that only asks it for actions. The weights and the actions
    are SB3's (tested). Why not SB3's ``load``:

    * it builds the optimizer, and the first torch optimizer a process builds imports torch's
      compiler stack, 0.99 s measured in a fresh process (``torch.optim.Adam`` alone); a one-seed
      surrogate run paid it inside its collection time;
    * it unpickles every saved state in the archive, the optimizers' too (Adam's two moments per
      weight: MountainCar's SAC expert keeps 124 kB of them beside 100 kB of weights), and the
      policy's settings had to be read from the archive before ``load`` read it again.

    So the archive is read once: its ``data`` for the policy's settings, and SB3's ``load`` gets
    an uncompressed copy in memory in which each policy optimizer's state (``*.optimizer.pth``,
    which ``_NoOptimizer`` ignores) is an empty dict. An algorithm's other optimizers (SAC's
    entropy coefficient: ``ent_coef_optimizer.pth``) keep their state and are built as SB3 builds
    them. Median of 15 loads on one core of this machine (2026-11-26): MountainCar's SAC
    expert 8.6 ms against 21.4 ms reading the archive twice; LunarLander's PPO expert 4.8 against 12.8."""
    import io  # noqa: PLC0415
    import json  # noqa: PLC0415
    import zipfile  # noqa: PLC0415

    from stable_baselines3.common.save_util import json_to_data  # noqa: PLC0415

    with zipfile.ZipFile(path) as archive:
        names = archive.namelist()
        data = archive.read("data").decode() if "data" in names else "{}"
        copy = io.BytesIO()
        with zipfile.ZipFile(copy, "w", zipfile.ZIP_STORED) as out:
            for name in names:
                out.writestr(name, _empty_state() if name.endswith(".optimizer.pth") else archive.read(name))
    saved_kwargs = json_to_data(data, custom_objects=dict.fromkeys(json.loads(data).keys() - {"policy_kwargs"}))
    policy_kwargs = {**(saved_kwargs.get("policy_kwargs") or {}), "optimizer_class": _NoOptimizer}
    copy.seek(0)
    return algo_cls.load(copy, device=device, custom_objects={"policy_kwargs": policy_kwargs})


@functools.cache
def _empty_state() -> bytes:
    """An empty dict as ``torch.save`` writes it: the state of an optimizer ``act_only_load`` leaves out."""
    import io  # noqa: PLC0415

    import torch as th  # noqa: PLC0415  (SB3's own dependency)

    buf = io.BytesIO()
    th.save({}, buf)
    return buf.getvalue()


def deterministic_policy(model: Any, discrete: bool) -> Policy:
    """``model``'s deterministic action for one observation, as SB3's ``predict(obs,
    deterministic=True)`` computes it (the same torch ops: the policy's ``_predict`` on the
    observation as a float32 batch of one, then SB3's unscaling or clipping of a Box action), less
    ``predict``'s per-call checks and conversions. Why not ``predict``: a collector calls it once
    per real step, and it cost 96 us against 53 us here (3,000 LunarLander steps, measured; the
    actions were the same). ``tests/rl/test_experts.py`` holds the two to equal actions.

    For an ``ActorCriticPolicy`` (PPO, A2C) with a categorical or diagonal Gaussian action, the
    torch ops of ``_predict`` are called directly: the actor's features, latent and action net,
    then for a categorical the mode as torch's ``Categorical`` and SB3's ``mode`` compute it
    (softmax of the logits less their logsumexp, argmax), with no distribution object; a Gaussian's
    mode is its mean, the action net's output. Why: building the distribution, with its argument
    checks, and looking the policy's device up were a third of the call (LunarLander's expert,
    2,000 steps on one core of a slower host than the figures above: 135 us per action through
    ``_predict``, 73-88 us here; the same actions)."""
    import torch as th  # noqa: PLC0415  (SB3's own dependency)

    policy = model.policy
    policy.set_training_mode(False)
    space = policy.action_space
    box = isinstance(space, gym.spaces.Box)
    if not isinstance(policy.observation_space, gym.spaces.Box):  # SB3 preprocesses others (one-hot, dicts)

        def predict(obs: np.ndarray):
            action, _ = model.predict(obs, deterministic=True)
            return action.item() if discrete else action

        return predict

    from stable_baselines3.common.distributions import CategoricalDistribution, DiagGaussianDistribution  # noqa: PLC0415
    from stable_baselines3.common.policies import ActorCriticPolicy, BaseModel  # noqa: PLC0415

    cls = type(policy)
    direct = (isinstance(policy, ActorCriticPolicy) and type(policy.action_dist) in (CategoricalDistribution, DiagGaussianDistribution)
              and all(getattr(cls, f) is getattr(ActorCriticPolicy, f) for f in ("_predict", "get_distribution", "_get_action_dist_from_latent")))
    categorical = direct and isinstance(policy.action_dist, CategoricalDistribution)
    device = policy.device

    def forward(x):
        if not direct:
            return policy._predict(x, deterministic=True)
        out = policy.action_net(policy.mlp_extractor.forward_actor(BaseModel.extract_features(policy, x, policy.pi_features_extractor)))
        return th.argmax(th.softmax(out - out.logsumexp(dim=-1, keepdim=True), dim=-1), dim=1) if categorical else out

    def act(obs: np.ndarray):
        with th.no_grad():
            action = forward(th.as_tensor(np.asarray(obs, dtype=np.float32)[None], device=device)).cpu().numpy().reshape((-1, *space.shape))[0]
        if box:
            action = policy.unscale_action(action) if policy.squash_output else np.clip(action, space.low, space.high)
        return action.item() if discrete else action

    return act
