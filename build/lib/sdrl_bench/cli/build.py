"""Config -> typed jobs: the one place that turns a composed DictConfig into library objects.

``build_fit_job`` and ``build_transfer_job`` validate keys and instantiate targets
(``_convert_="all"``), so the library below only sees typed arguments. ``compose`` gives the
same config the command line would (Hydra's compose API over ``pkg://sdrl_bench.conf`` and any
``--config-dir``/``hydra.searchpath`` the running app was given), for tests, benchmarks and
notebooks.
"""

from __future__ import annotations

import hashlib
import json
from typing import Any
from collections.abc import Sequence

from hydra import compose as hydra_compose
from hydra import initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from sdrl_bench import ConfigError
from sdrl_bench.models.libraries import LibraryPart
from sdrl_bench.pipeline import FitJob
from sdrl_bench.rl.transfer import TransferJob

CONFIG_MODULE = "sdrl_bench.conf"
CONFIG_PATH = "pkg://" + CONFIG_MODULE


def compose(overrides: Sequence[str] = (), config_name: str = "config", return_hydra_config: bool = False) -> DictConfig:
    """The composed config as the command line would build it (no run dir, no callbacks).

    Inside a running Hydra app the app's search path (with the user's ``--config-dir``) is
    used; elsewhere the package's own configs.
    """
    if GlobalHydra.instance().is_initialized():
        return hydra_compose(config_name=config_name, overrides=list(overrides), return_hydra_config=return_hydra_config)
    with initialize_config_module(config_module=CONFIG_MODULE, version_base="1.3"):
        return hydra_compose(config_name=config_name, overrides=list(overrides), return_hydra_config=return_hydra_config)


def instantiate_key(node: Any, key: str) -> Any:
    try:
        return instantiate(node, _convert_="all")
    except Exception as exc:
        cause = exc.__cause__ or exc
        raise ConfigError(f"{key}: {cause}".splitlines()[0]) from None


def _inputs(value: Any) -> str | tuple[str, ...]:
    if isinstance(value, str):
        return value
    return tuple(str(v) for v in OmegaConf.to_container(value, resolve=True))


def _episode_cut(value: Any) -> int | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"collector.max_steps_per_episode must be a positive integer or null, got {value!r}")
    return value


def build_fit_job(cfg: DictConfig) -> FitJob:
    """Turn a composed config into a typed ``FitJob`` (no env steps, no fit)."""
    for group in ("env", "collector", "library", "optimizer", "surrogate"):
        if group not in cfg or cfg[group] is None:
            raise ConfigError(f"{group}: missing config group")
    spec = instantiate_key(cfg.env.spec, "env.spec")
    policy = instantiate_key(cfg.collector.policy, "collector.policy")
    parts = tuple(
        LibraryPart(instantiate_key(p.library, f"library.parts[{i}].library"), _inputs(p.get("inputs", "all")))
        for i, p in enumerate(cfg.library.parts)
    )
    opt_cfg = OmegaConf.to_container(cfg.optimizer, resolve=True)
    opt_cfg.pop("name", None)
    optimizer = instantiate_key(opt_cfg, "optimizer")
    model_factory = instantiate_key(cfg.surrogate.model, "surrogate.model")
    return FitJob(
        spec=spec,
        library_parts=parts,
        optimizer=optimizer,
        n_transitions=int(cfg.n_transitions),
        policy=policy,
        epsilon=float(cfg.collector.epsilon),
        max_steps_per_episode=_episode_cut(cfg.collector.get("max_steps_per_episode")),
        seed=int(cfg.seed),
        dataset_path=cfg.dataset.path,
        exclude_bound_transitions=bool(cfg.dataset.exclude_bound_transitions),
        surrogate=str(cfg.surrogate.kind),
        model_factory=model_factory,
        names={
            "env": spec.name,
            "collector": cfg.collector.name,
            "library": cfg.library.name,
            "optimizer": cfg.optimizer.name,
            "surrogate": cfg.surrogate.kind,
        },
    )


def build_transfer_job(cfg: DictConfig, fit_job) -> TransferJob:
    agent = instantiate_key(cfg.agent, "agent")
    rl = cfg.rl
    arms = tuple(str(a) for a in rl.arms)
    return TransferJob(
        fit=fit_job, agent=agent, arms=arms, surrogate_steps=int(rl.surrogate_steps),
        real_steps=int(rl.real_steps), eval_every=int(rl.eval_every), eval_episodes=int(rl.eval_episodes),
        final_episodes=int(rl.final_episodes), seed=int(cfg.seed), progress_bar=bool(cfg.progress_bar),
    )


def real_arm_key(cfg: DictConfig) -> str:
    """What the real arm depends on: env, agent, budgets of the real arm, seed."""
    parts = {
        "agent": OmegaConf.to_container(cfg.agent, resolve=True),
        "env": OmegaConf.to_container(cfg.env.spec, resolve=True),
        "rl": {k: cfg.rl[k] for k in ("real_steps", "eval_every", "eval_episodes", "final_episodes")},
        "seed": cfg.seed,
    }
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]
