"""Config -> typed jobs: the one place that turns a composed DictConfig into library objects.

``build_fit_job`` and ``build_transfer_job`` validate keys and instantiate targets
(``_convert_="all"``), so the library below only sees typed arguments. ``compose`` gives the
same config the command line would (Hydra's compose API over ``pkg://sdrl_bench.conf`` and any
``--config-dir``/``hydra.searchpath`` the running app was given), for tests, benchmarks and
notebooks.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import math
import re
from pathlib import Path
from typing import TYPE_CHECKING, Any
from collections.abc import Sequence

from hydra import compose as hydra_compose
from hydra import initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import InterpolationResolutionError

from sdrl_bench import ConfigError
from sdrl_bench.cli import CONFIG_MODULE, NOT_OF_THE_RESULT
from sdrl_bench.envs.functional import one_line
from sdrl_bench.models.libraries import LibraryPart
from sdrl_bench.pipeline import FitJob

if TYPE_CHECKING:
    from sdrl_bench.rl.dyna import DynaJob
    from sdrl_bench.rl.transfer import TransferJob


def compose(overrides: Sequence[str] = (), config_name: str = "config", return_hydra_config: bool = False) -> DictConfig:
    """The composed config as the command line would build it (no run dir, no callbacks).

    Inside a running Hydra app the app's search path (with the user's ``--config-dir``) is
    used; elsewhere the package's own configs.
    """
    if GlobalHydra.instance().is_initialized():
        return hydra_compose(config_name=config_name, overrides=list(overrides), return_hydra_config=return_hydra_config)
    with initialize_config_module(config_module=CONFIG_MODULE, version_base="1.3"):
        return hydra_compose(config_name=config_name, overrides=list(overrides), return_hydra_config=return_hydra_config)


_PLAIN_KEY = re.compile(r"^\$\{([A-Za-z_][\w.\[\]]*)\}$")
"""An interpolation of one config key (``${env.poly_degree}``), not a resolver's call."""


def _origin(source: Any) -> str:
    """`` (from env.poly_degree)`` when the value came through an interpolation of a key, else ''."""
    found = _PLAIN_KEY.match(source) if isinstance(source, str) else None
    return f" (from {found.group(1)})" if found else ""


def _admits(annotation: Any, value: Any) -> bool:
    """Whether a parameter's annotation (a string under ``from __future__ import annotations``)
    names the value's type or ``Any`` (``bool | str`` admits a string): then the default's type
    does not bind. No annotation admits nothing: the default's type decides."""
    if annotation is inspect.Parameter.empty:
        return False
    text = annotation if isinstance(annotation, str) else getattr(annotation, "__name__", None) or str(annotation)
    words = set(re.findall(r"[A-Za-z_]+", text))
    return bool(words & {"Any", type(value).__name__})


def _numbers(seq: Any, nulls: bool = False) -> bool:
    """Whether ``seq`` is a non-empty tuple or list of numbers (bools are not); with ``nulls``,
    None entries too (a spec's bounds read null as unbounded)."""
    return (isinstance(seq, (tuple, list)) and len(seq) > 0
            and all((isinstance(v, (int, float)) and not isinstance(v, bool)) or (nulls and v is None) for v in seq))


def check_value_types(node: Any, key: str, source: Any = None) -> None:
    """Each value under a ``_target_`` whose parameter defaults to a bool must be a bool, and one
    whose parameter defaults to a number must not be a string or a bool: the targets themselves
    read ``maybe`` as true (pysindy's ``normalize_columns``, an env spec's ``terrain``) or fail
    deep inside with ``'<' not supported between 'str' and 'int'``; a list where the parameter
    defaults to a list of numbers must hold numbers or nulls (``TrigLibrary``'s frequencies, a
    spec's bounds). One line naming the key, and the key it was interpolated from (a list: that
    key alone). Left to the target: parameters without a default, or defaulting to None or a
    string; values the annotation admits (``progress_bar: bool | str``); null and Hydra's
    ``???``. ``source`` is the node before interpolation."""
    if isinstance(node, list):
        for i, value in enumerate(node):
            check_value_types(value, f"{key}[{i}]", source[i] if isinstance(source, list) and i < len(source) else None)
        return
    if not isinstance(node, dict):
        return
    params: Any = {}
    if isinstance(node.get("_target_"), str):
        try:
            from hydra.utils import get_object

            params = inspect.signature(get_object(node["_target_"])).parameters
        except Exception:  # noqa: BLE001 - an import error or a builtin without a signature: instantiate's to report
            params = {}
    for name, value in node.items():
        if not isinstance(name, str) or name.startswith("_"):
            continue
        src = source.get(name) if isinstance(source, dict) else None
        where = f"{key}.{name}"
        param = params.get(name)
        found = _PLAIN_KEY.match(src) if isinstance(src, str) else None  # set elsewhere: named by that key
        if isinstance(value, list) and param is not None and _numbers(param.default) and not _numbers(value, nulls=True):
            raise ConfigError(f"{found.group(1) if found else where}: a list of numbers is required, got {value!r}")
        if isinstance(value, (dict, list)):  # a subtree from elsewhere: its own keys
            check_value_types(value, found.group(1) if found else where, None if found else src)
            continue
        default = None if param is None else param.default
        if default is None or default is inspect.Parameter.empty or value is None or value == "???":
            continue
        if _admits(param.annotation, value):
            continue
        if isinstance(default, bool) and not isinstance(value, bool):
            raise ConfigError(f"{where}{_origin(src)}: true or false is required, got {value!r}")
        if isinstance(default, (int, float)) and not isinstance(default, bool) and isinstance(value, (str, bool)):
            raise ConfigError(f"{where}{_origin(src)}: a number is required, got {value!r}")


def instantiate_typed(node: Any, key: str, source: Any = None) -> Any:
    """``instantiate_key`` with the values' types checked against the targets' defaults
    (``check_value_types``; ``source``: the node before interpolation, when ``node`` is a plain
    container), after the target's own checks, whose messages are more precise. For the fit's
    parts (env spec, collector, library, optimizer, surrogate model); an agent's settings have
    checks of their own, with their domains (``rl.agents``)."""
    try:
        if isinstance(node, DictConfig):
            resolved, source = OmegaConf.to_container(node, resolve=True), OmegaConf.to_container(node, resolve=False)
        else:
            resolved = node
            if isinstance(source, DictConfig):
                source = OmegaConf.to_container(source, resolve=False)
    except Exception:  # noqa: BLE001 - an interpolation that does not resolve: instantiate says which
        resolved = None
    try:
        built = instantiate_key(node, key)
    except ConfigError as exc:  # the target's own check stands; another failure may be a type's
        if not getattr(exc, "targets_own", False) and resolved is not None:
            check_value_types(resolved, key, source)
        raise
    if resolved is not None:  # built, but would read "maybe" as true, or fail on "two" when fitted
        check_value_types(resolved, key, source)
    return built


_FULL_KEY = re.compile(r"^[a-z_]+(\.[A-Za-z_][\w\[\]]*)+( \([^)]*\))?: ")
"""A message that starts with a dotted config key (``env.expert.budget: ...``)."""


def instantiate_key(node: Any, key: str) -> Any:
    """``instantiate(node)``; any failure is one line naming ``key`` and the root cause (a user
    module's own import error with its file and line, not Hydra's wrapper)."""
    try:
        return instantiate(node, _convert_="all")
    except Exception as exc:
        root = exc  # the first ConfigError of the chain (already one line), else the innermost cause
        while root.__cause__ is not None and root.__cause__ is not root and not isinstance(root, ConfigError):
            root = root.__cause__
        if isinstance(root, ConfigError):
            text = " ".join(str(root).split())
            named = text.startswith(key) or _FULL_KEY.match(text)  # it names the key the user sets
            own = ConfigError(text if named else f"{key}: {text}")
            own.targets_own = True  # the target's own validation (instantiate_typed keeps it)
            raise own from None
        target = node.get("_target_") if isinstance(node, (dict, DictConfig)) else None
        if target and (isinstance(exc.__cause__, ImportError) or isinstance(root, (ImportError, SyntaxError))):
            raise ConfigError(f"{key}: cannot import {target!r}: {one_line(root)}") from None
        message = " ".join(str(root).split())  # a library's own validation message, as it says it
        raise ConfigError(f"{key}: {message}" if message else f"{key}: {one_line(root)}") from None


def _check_resolvable(cfg: DictConfig, group: str) -> None:
    """Every interpolation in ``group`` resolves (``collector=expert`` reads ``env.expert.*``,
    which only envs with an expert define)."""
    try:
        OmegaConf.to_container(cfg[group], resolve=True)
    except InterpolationResolutionError as exc:
        missing = str(getattr(exc, "msg", exc)).splitlines()[0]
        if group == "collector" and "env.expert" in missing:
            raise ConfigError(f"collector=expert: env '{cfg.env.spec.get('name', '?')}' names no expert ({missing}); add "
                              "'defaults: [/agent@expert.agent: sac, _self_]' and 'expert: {budget: N}' to its YAML, "
                              "or use collector=random / heuristic") from None
        raise ConfigError(f"{group}: {missing}") from None


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


def int_key(cfg: DictConfig, key: str, minimum: int | None = None, maximum: int | None = None) -> int:
    """The integer at ``key`` (``1.5``, ``abc`` and ``true`` are refused, not truncated)."""
    value = OmegaConf.select(cfg, key)
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"{key}: an integer is required, got {value!r}")
    if minimum is not None and value < minimum:
        raise ConfigError(f"{key} must be >= {minimum}, got {value}")
    if maximum is not None and value > maximum:
        raise ConfigError(f"{key} must be <= {maximum}, got {value}")
    return value


SEED_MAX = 2**32 - 1
"""The largest run seed: numpy's legacy seeding and SB3's take 32-bit seeds."""


def seed_key(cfg: DictConfig) -> int:
    return int_key(cfg, "seed", minimum=0, maximum=SEED_MAX)


def bool_key(cfg: DictConfig, key: str) -> bool:
    """The true or false at ``key`` (``abc`` is refused, not read as true)."""
    value = OmegaConf.select(cfg, key)
    if not isinstance(value, bool):
        raise ConfigError(f"{key}: true or false is required, got {value!r}")
    return value


def float_key(cfg: DictConfig, key: str, low: float | None = None, high: float | None = None) -> float:
    """The finite number at ``key`` within [low, high] (nan, inf and strings are refused)."""
    value = OmegaConf.select(cfg, key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{key}: a finite number is required, got {value!r}")
    if (low is not None and value < low) or (high is not None and value > high):
        raise ConfigError(f"{key} must be within [{low}, {high}], got {value}")
    return float(value)


def _check_finite(node: Any, key: str) -> None:
    """Every number in a config subtree is finite (a nan threshold fits an all-zero model)."""
    if isinstance(node, dict):
        for k, v in node.items():
            _check_finite(v, f"{key}.{k}")
    elif isinstance(node, list):
        for i, v in enumerate(node):
            _check_finite(v, f"{key}[{i}]")
    elif isinstance(node, float) and not math.isfinite(node):
        raise ConfigError(f"{key}: a finite number is required, got {node!r}")


def build_fit_job(cfg: DictConfig) -> FitJob:
    """Turn a composed config into a typed ``FitJob`` (no env steps, no fit)."""
    for group in ("env", "collector", "library", "optimizer", "surrogate"):
        if group not in cfg or cfg[group] is None:
            raise ConfigError(f"{group}: missing config group")
    spec = instantiate_typed(cfg.env.spec, "env.spec")
    spec.check_registered()  # the real env (a user module that registers it): collection and test set use it
    _check_resolvable(cfg, "collector")
    policy = instantiate_typed(cfg.collector.policy, "collector.policy")
    parts = tuple(
        LibraryPart(instantiate_typed(p.library, f"library.parts[{i}].library"), _inputs(p.get("inputs", "all")))
        for i, p in enumerate(cfg.library.parts)
    )
    seed = seed_key(cfg)
    n_transitions = int_key(cfg, "n_transitions", minimum=1)
    epsilon = float_key(cfg, "collector.epsilon", 0.0, 1.0)
    opt_cfg = OmegaConf.to_container(cfg.optimizer, resolve=True)
    opt_cfg.pop("name", None)
    _check_finite(opt_cfg, "optimizer")
    if "n_models" in opt_cfg:  # pysindy 2.1's EnsembleOptimizer refuses 0 naming n_candidates_to_drop
        int_key(cfg, "optimizer.n_models", minimum=1)
    optimizer = instantiate_typed(opt_cfg, "optimizer", source=cfg.optimizer)
    model_factory = instantiate_typed(cfg.surrogate.model, "surrogate.model")
    return FitJob(
        spec=spec,
        library_parts=parts,
        optimizer=optimizer,
        n_transitions=n_transitions,
        policy=policy,
        epsilon=epsilon,
        max_steps_per_episode=_episode_cut(cfg.collector.get("max_steps_per_episode")),
        seed=seed,
        dataset_path=cfg.dataset.path,
        exclude_bound_transitions=bool_key(cfg, "dataset.exclude_bound_transitions"),
        surrogate=str(cfg.surrogate.kind),
        model_factory=model_factory,
        tuning_real_steps=int_key(cfg, "surrogate.tuning_real_steps", minimum=0) if "tuning_real_steps" in cfg.surrogate else 0,
        names={
            "env": spec.name,
            "collector": cfg.collector.name,
            "library": cfg.library.name,
            "optimizer": cfg.optimizer.name,
            "surrogate": cfg.surrogate.kind,
        },
    )


def build_transfer_job(cfg: DictConfig, fit_job) -> TransferJob:
    from sdrl_bench.rl.transfer import TransferJob  # noqa: PLC0415  (torch and SB3: not for a fit's command)

    agent = instantiate_key(cfg.agent, "agent")
    rl = cfg.rl
    if isinstance(rl.arms, str) or rl.arms is None:
        raise ConfigError(f"rl.arms: a list is required (e.g. rl.arms=[surrogate] or rl.arms=[surrogate,real]), got {rl.arms!r}")
    arms = tuple(str(a) for a in rl.arms)
    steps = {k: int_key(cfg, f"rl.{k}") for k in ("surrogate_steps", "real_steps", "eval_every", "eval_episodes",
                                                   "final_episodes")}
    stop = rl.get("stop_when_solved", False)
    if not isinstance(stop, bool):
        raise ConfigError(f"rl.stop_when_solved: true or false, got {stop!r}")
    confirm = int_key(cfg, "rl.confirm_episodes", minimum=0) if "confirm_episodes" in rl else 0
    return TransferJob(fit=fit_job, agent=agent, arms=arms, seed=seed_key(cfg),
                       progress_bar=bool(cfg.progress_bar), stop_when_solved=stop, confirm_episodes=confirm, **steps)


def build_dyna_job(cfg: DictConfig, fit_job: FitJob) -> DynaJob:
    """The typed Dyna job (``rl.dyna.*``: unknown keys and bad values are one-line errors naming the key)."""
    import dataclasses

    from sdrl_bench.rl.dyna import DynaConfig, DynaJob  # noqa: PLC0415  (torch and SB3: not for a fit's command)

    node = cfg.rl.get("dyna")
    if node is None:
        raise ConfigError("rl.dyna: missing (task=dyna needs the rl.dyna block of config.yaml)")
    values = OmegaConf.to_container(node, resolve=True)
    known = {f.name for f in dataclasses.fields(DynaConfig)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ConfigError(f"rl.dyna.{unknown[0]}: unknown key; known: {', '.join(sorted(known))}")
    dyna = DynaConfig(**values)
    dyna.check()
    agent = instantiate_key(cfg.agent, "agent")
    return DynaJob(fit=fit_job, agent=agent, dyna=dyna, seed=seed_key(cfg))


TASKS = ("fit", "train", "dyna", "fidelity")


def check_task(cfg: DictConfig) -> None:
    """The task is one ``sdrl-bench`` has; the switches of any task are true or false."""
    if cfg.task not in TASKS:
        raise ConfigError(f"task: {cfg.task!r} is not one of {', '.join(repr(t) for t in TASKS)}")
    for key in ("resume", "progress_bar"):
        if key in cfg:
            bool_key(cfg, key)


def check_run_keys(cfg: DictConfig) -> tuple[int, int]:
    """The process settings of an RL task (train, dyna, fidelity), whatever its agent:
    ``(torch_threads, jax_threads)``; ``rl.reuse_real_arm`` a boolean; ``jax_cache_dir`` not a file."""
    threads = int_key(cfg, "torch_threads", minimum=1), int_key(cfg, "jax_threads", minimum=0)
    if "reuse_real_arm" in cfg.get("rl", {}):
        bool_key(cfg, "rl.reuse_real_arm")
    cache = cfg.get("jax_cache_dir")
    if cache and Path(cache).exists() and not Path(cache).is_dir():
        raise ConfigError(f"jax_cache_dir: {cache} is a file, not a folder")
    return threads


def check_job(cfg: DictConfig, overrides: Sequence[str] = ()) -> None:
    """What a job checks before its run exists (its typed job built, then the job's own
    ``check``), without collecting, fitting or training; ``overrides``: the command line's that
    composed ``cfg``. A ``-m`` sweep's driver runs it on each job's config (``cli.precheck``), so
    that a bad value stops the sweep in one line before its parent run, its output folder or its
    workers exist; each job checks again when it runs."""
    from sdrl_bench.pipeline import check  # noqa: PLC0415

    check_task(cfg)
    fit_job = build_fit_job(cfg)
    if cfg.task == "fit":
        check(fit_job)
        return
    check_run_keys(cfg)
    if cfg.task == "train":
        build_transfer_job(cfg, fit_job).check()
    elif cfg.task == "dyna":
        build_dyna_job(cfg, fit_job).check()
    else:
        from sdrl_bench.cli.fidelity_task import build_cluster  # noqa: PLC0415  (it builds on this module)

        build_cluster(cfg, list(overrides))[0].check()


def real_arm_key(cfg: DictConfig) -> str:
    """What the real arm depends on: env, agent, budgets of the real arm, seed."""
    parts = {
        "agent": OmegaConf.to_container(cfg.agent, resolve=True),
        "env": OmegaConf.to_container(cfg.env.spec, resolve=True),
        "rl": {k: cfg.rl[k] for k in ("real_steps", "eval_every", "eval_episodes", "final_episodes")},
        "seed": cfg.seed,
    }
    if cfg.rl.get("stop_when_solved", False):  # only when set: keys of earlier runs stay as they were
        parts["rl"]["stop_when_solved"] = True
    if cfg.rl.get("confirm_episodes", 0):  # likewise
        parts["rl"]["confirm_episodes"] = cfg.rl.confirm_episodes
    parts["env"].pop("own_data", None)  # shapes only the surrogate: a Dyna variant shares its base's real arm
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


JOB_TAG = "sdrl.job"
"""A sweep job's own overrides (what tells it from its siblings)."""


def run_label(name: str, tags: dict | None) -> str:
    """A run's name: inside a sweep its own overrides come first (``seed=3 library=trig ·
    fit-...``), so that the UI's runs table, which cuts names short, tells siblings apart."""
    job = (tags or {}).get(JOB_TAG)
    return f"{job} · {name}" if job else name


def config_key(cfg: DictConfig) -> str:
    """What a job computes: its resolved config, less what does not change the result
    (progress bars, the resume switch, Hydra's own settings)."""
    body = OmegaConf.to_container(cfg, resolve=True)
    for key in ("hydra", *NOT_OF_THE_RESULT):
        body.pop(key, None)
    if isinstance(body.get("rl"), dict) and body["rl"].get("confirm_episodes") == 0:
        body["rl"].pop("confirm_episodes")  # the default (added later): earlier runs' keys stay as they were
    return hashlib.sha256(json.dumps(body, sort_keys=True, default=str).encode()).hexdigest()[:16]


def exit_after_stop_signal(cfg: DictConfig, signum: int, prog: str, what: str,
                          before_runs: str = "before its run was made (nothing to resume)") -> None:
    """The last word of a command stopped by SIGTERM/SIGINT (``Terminated``, or whatever a
    library's cleanup raised instead after the signal): end the runs this process owns that the
    signal caught mid-creation, say so in one line (``what``; ``before_runs`` when this process
    made no run in the store: stopped while it loaded or fitted), exit 128 + signal."""
    import signal
    import sys

    from sdrl_bench import redact, tracking

    # the stop's handler has capped MLflow's waits on a server (``sdrl_bench.on_stop_signal``)
    made, said, uri = True, what, str(cfg.tracking.uri)
    try:
        uri = tracking.resolve_uri(cfg.tracking.uri)
        tracking.end_runs_of_this_process(uri, cfg.tracking.experiment)
        made = bool(tracking.runs_of_this_process(uri, cfg.tracking.experiment))
    except Exception:  # the store went away mid-run: its runs could not be ended, and the line says so
        said = (f"the tracking store at {redact(uri)} did not answer, so this command's runs may still show RUNNING "
                "(the next command on this experiment ends them)")
    close_progress_bars()  # an open bar would draw its last line below this one at exit
    print(f"{prog}: stopped by {signal.Signals(signum).name}; {said if made else before_runs}", file=sys.stderr)
    sys.exit(128 + signum)


def close_progress_bars() -> None:
    """Close the progress bars a stop left open (SB3's, tqdm over rich), so that their last line is
    drawn now, not after the stop's message when the interpreter exits. Hand-written: tqdm has no
    public list of its open bars; its class keeps them in ``_instances``."""
    import sys

    tqdm = getattr(sys.modules.get("tqdm"), "tqdm", None)
    for bar in list(getattr(tqdm, "_instances", None) or ()):
        try:
            bar.close()
        except Exception:  # a bar half torn down by the stop: it has nothing left to draw
            pass
