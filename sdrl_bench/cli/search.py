"""``sdrl-bench-search``: a thin Hydra entry point around ``search.run_study`` and ``refine``.

    sdrl-bench-search                                   # TPE study, MountainCar (sdrl_bench/conf/search_app.yaml)
    sdrl-bench-search search=grid                       # the paper's threshold x alpha grid
    sdrl-bench-search search=pareto                     # error vs active terms (Pareto front)
    sdrl-bench-search search=refine                     # residual-guided library refinement
    sdrl-bench-search -m study.worker=0,1,2,3 hydra.launcher.n_jobs=4   # 4 workers, one study

A trial's parameters become overrides of the ``sdrl-bench`` config (``search.space.PARAM_KEYS``),
so every trial is a fit that ``sdrl-bench`` could run, and the best one is exported as such.
"""

from __future__ import annotations

import copy
import functools
import json
import math
import signal
import sys
from pathlib import Path
from typing import Any
from collections.abc import Mapping, Sequence

import hydra
import yaml
from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, ListConfig, OmegaConf, open_dict

from sdrl_bench import ConfigError, Terminated, raise_on_stop_signals, redact, stop_signal_received, tracking
from sdrl_bench.cli import CONFIG_PATH
from sdrl_bench.cli.build import bool_key, build_fit_job, compose, exit_after_stop_signal, float_key, int_key, seed_key
from sdrl_bench.pipeline import FitJob
from sdrl_bench.search.refine import run_refinement
from sdrl_bench.search.study import BuildJob, StudySettings, check_study, run_study
from sdrl_bench.search.summary import check_export, comparison_table, load_summaries, summarize
from sdrl_bench.search.space import GROUP_PARAMS, PARAM_KEYS, Conditions, SearchSpace, check_model_kind, conditions, parse_space
from sdrl_bench.search.location import resolve_storage
from sdrl_bench.search.storage import check_study_name, open_storage

GROUPS = ("env", "collector", "library", "optimizer", "surrogate")
_NOT_CONTEXT = ("search", "study", "tracking", "hydra", "seed", "n_transitions")


@functools.lru_cache(maxsize=64)
def _group_option(group: str, name: str) -> DictConfig:
    return compose([f"{group}={name}"])[group]


def load_group(group: str, name: str, key: str | None = None) -> DictConfig:
    """One option of a config group, composed by Hydra from the app's search path (the
    package's configs and any ``--config-dir``), unresolved (cached: a DictConfig assigned
    into another config is copied, so the cached node never changes). An unknown option is a
    ``ConfigError`` naming ``key``, the config key that chose it (default: the search space's)."""
    from hydra.errors import MissingConfigException

    try:
        return _group_option(group, name)
    except MissingConfigException as exc:
        known = sorted(o for o in (exc.options or []))
        raise ConfigError(f"{key or f'search.space.{group}'}: unknown choice '{name}' (the {group} group has {known})") from None


def _config_name(cfg: DictConfig, key: str) -> str:
    """The config-group option named at ``key`` (a string; a list, a mapping or null is refused)."""
    value = OmegaConf.select(cfg, key)
    if isinstance(value, bool) or not isinstance(value, (str, int)) or str(value) == "":
        raise ConfigError(f"{key}: a config name is required, got {value!r}")
    return str(value)


def make_build_job(cfg: DictConfig) -> BuildJob:
    """params -> the ``FitJob`` that ``sdrl-bench`` with those overrides would run."""
    base = _fit_config(cfg)

    def build(params: Mapping[str, Any]) -> FitJob:
        c = copy.deepcopy(base)
        with open_dict(c):
            for key, value in params.items():
                if key in GROUP_PARAMS:
                    c[key] = load_group(key, str(value))
                else:
                    OmegaConf.update(c, PARAM_KEYS[key], value, merge=False)
        return build_fit_job(c)

    return build


def runtime_choices(cfg: DictConfig) -> dict[str, str]:
    """The config-group choices of this run (env, collector, library, ...)."""
    if "hydra" in cfg:
        choices = cfg.hydra.runtime.choices
    elif HydraConfig.initialized():
        choices = HydraConfig.get().runtime.choices
    else:
        raise ConfigError("search: group choices unknown (compose with return_hydra_config=True)")
    return {g: str(choices[g]) for g in GROUPS if g in choices}


def _override_values(cfg: DictConfig, searched: set[str]) -> dict[str, Any]:
    """Values set by command-line overrides that change the fit (so the export repeats them)."""
    if "hydra" in cfg:
        task = list(cfg.hydra.overrides.task)
    else:
        task = list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []
    out = {}
    for item in task:
        key = item.split("=", 1)[0].lstrip("+~")
        root = key.split("/")[0].split(".")[0]
        if "=" not in item or key in GROUPS or root in _NOT_CONTEXT or key in searched:
            continue
        value = OmegaConf.select(cfg, key)
        out[key] = OmegaConf.to_container(value, resolve=True) if isinstance(value, (DictConfig, ListConfig)) else value
    return out


def study_settings(cfg: DictConfig, choices: Mapping[str, str]) -> StudySettings:
    """Typed settings from the composed config; the space and its choices validated. Every
    number is checked here, before any data are collected (``1.5``, ``abc`` and ``true`` for an
    integer are one-line errors naming the key, never truncated)."""
    sc, st = cfg.search, cfg.study
    seed = seed_key(cfg)
    fixed = {"seed": seed, "n_transitions": int_key(cfg, "n_transitions", minimum=1),
              "collector.epsilon": float_key(cfg, "collector.epsilon", 0.0, 1.0)}
    k_folds = int_key(cfg, "search.k_folds", minimum=2)
    n_trials = None if sc.get("n_trials") is None else int_key(cfg, "search.n_trials", minimum=0)
    study_seed, worker = int_key(cfg, "study.seed", minimum=0), int_key(cfg, "study.worker", minimum=0)
    heartbeat_interval = int_key(cfg, "study.heartbeat_interval", minimum=1)
    heartbeat_grace = int_key(cfg, "study.heartbeat_grace", minimum=1)
    if heartbeat_grace < heartbeat_interval and not str(st.storage).startswith("journal:"):  # no heartbeats there
        raise ConfigError(f"study.heartbeat_grace: {heartbeat_grace} s is shorter than study.heartbeat_interval "
                          f"({heartbeat_interval} s), so other workers would fail live trials as stale; set it to a few "
                          "intervals (Optuna's default is twice the interval)")
    space = parse_space(OmegaConf.to_container(sc.space, resolve=True))
    kind = str(cfg.surrogate.get("kind", "sindy"))
    check_model_kind(space, kind)
    if kind != "sindy" and "n_terms" in list(sc.objectives):
        raise ConfigError(f"search.objectives: n_terms counts SINDy's active terms; surrogate={kind} has none: use [error]")
    for p in space:
        if p.name in GROUP_PARAMS:
            for choice in p.choices or ():
                load_group(p.name, str(choice))
    when = space_conditions(cfg, space, choices) if kind == "sindy" else {}
    if str(sc.sampler) == "nsga2":  # NSGA-II evolves only the params every trial has: a value sampled
        when = {}                   # under some choices would be drawn at random in every trial
    searched = {p.name for p in space}
    searched_keys = {PARAM_KEYS[n] for n in searched}
    context = {
        # an NN's fit reads no library or optimizer (SINDy's groups): its export names neither
        "choices": {g: v for g, v in choices.items() if g not in searched
                    and not (kind != "sindy" and g in GROUP_PARAMS)},
        "values": {**fixed, **_override_values(cfg, searched_keys)},
    }
    if n_trials is None:
        from sdrl_bench.search.space import grid_values

        n_trials = 1
        for values in grid_values(space).values():
            n_trials *= len(values)
    objective = str(sc.get("objective", "one_step"))
    name = st.name or f"{choices.get('env', 'env')}-{sc.name}-s{seed}" + ("" if objective == "one_step" else f"-{objective}")
    check_export(st.get("export_dir"), check_study_name(str(name)))
    return StudySettings(
        name=str(name), space=space, storage=st.storage, objectives=tuple(sc.objectives), objective=objective,
        policy=_policy_probe(cfg, objective, seed),
        sampler=str(sc.sampler), n_trials=n_trials, k_folds=k_folds, pruner=str(sc.pruner),
        seed=study_seed, worker=worker, heartbeat_interval=heartbeat_interval,
        heartbeat_grace=heartbeat_grace, tracking_uri=cfg.tracking.uri,
        experiment=str(cfg.tracking.experiment), context=context, when=when,
    )


def space_conditions(cfg: DictConfig, space: SearchSpace, choices: Mapping[str, str]) -> Conditions:
    """``search.space.conditions`` over the fit's groups: a searched group's choices as
    ``load_group`` gives them, a fixed one as this run composed it (a command-line
    ``optimizer.alpha=...`` replaces the interpolation, and a searched alpha then changes nothing)."""
    searched = {p.name: p for p in space}
    groups = {}
    for group in GROUP_PARAMS:
        if group in searched:
            groups[group] = {str(c): OmegaConf.to_container(load_group(group, str(c)), resolve=False)
                             for c in searched[group].choices or ()}
        else:
            name = choices.get(group) or cfg[group].get("name") or group  # a sweep's precheck has no choices
            groups[group] = {str(name): OmegaConf.to_container(cfg[group], resolve=False)}
    return conditions(space, groups)


def _policy_probe(cfg: DictConfig, objective: str, seed: int):
    """``search.objective=onpolicy_one_step | reference_gap``: the agent (``agent=...``) and the real
    episodes (``search.policy.*``) it scores each trial with; None for a data objective."""
    from sdrl_bench.fidelity import POLICY_METRICS

    if objective not in POLICY_METRICS:
        return None
    from sdrl_bench.rl.fidelity_study import PolicyProbe
    node = cfg.search.get("policy")
    if node is None:
        raise ConfigError(f"search.objective={objective}: needs search.policy (train_steps, episodes, reference)")
    from sdrl_bench.cli.build import instantiate_key

    ref = str(node.get("reference", "random"))
    reference = None if ref == "random" else instantiate_key(
        load_group("collector", ref, "search.policy.reference").policy, "search.policy.reference")
    agent = instantiate_key(cfg.agent, "agent")
    agent.check(instantiate_key(cfg.env.spec, "env.spec"))  # it can act in the env: before any data or trial
    return PolicyProbe(objective, agent, int_key(cfg, "search.policy.train_steps", 1),
                       int_key(cfg, "search.policy.episodes", 1), reference, seed, ref)


def run_search(cfg: DictConfig, choices: Mapping[str, str] | None = None, quiet: bool = False):
    """Run one worker of the configured study, then summarize it (best, test score, export)."""
    choices = choices or runtime_choices(cfg)
    settings = study_settings(cfg, choices)
    final_score = bool_key(cfg, "study.final_score")
    build = make_build_job(cfg)

    def progress(t) -> None:
        if not quiet:
            value = f"{t.values[0]:.3e}" if t.values else ""
            if t.state.name != "COMPLETE":  # a pruned trial's value is its running error when it was stopped
                folds = len(t.intermediate_values)
                value = f"{t.state.name.lower()}" + (f" (running error {value} after {folds} folds)" if value else "")
            print(f"[{settings.name} w{settings.worker}] trial {t.number}: {value} {t.params}", flush=True)

    result = run_study(settings, build, progress)
    def waiting() -> None:
        print(f"[{settings.name} w{settings.worker}] waiting for another worker's summary of the study", flush=True)

    summary = summarize(result, build, final_score, cfg.study.export_dir, None if quiet else waiting)
    if not quiet:
        _print_summary(summary, result, cfg.study.export_dir)
    return result, summary


def _print_summary(summary, result, export_dir: str | None) -> None:
    print(f"study '{summary.name}' in {redact(result.storage)}: {summary.n_trials} trials "
          f"({summary.n_complete} complete, {summary.n_pruned} pruned, {summary.n_failed} failed), "
          f"{summary.fits_total} fits; this worker ran {len(result.trials)}")
    if summary.best_number is None:
        return
    terms = "" if summary.best_n_terms is None else f"{summary.best_n_terms} terms, "
    print(f"best trial {summary.best_number}: held-out error {summary.best_error:.4g}, "
          f"{terms}after {summary.fits_to_best} fits; params {summary.best_params}")
    if summary.test_error is not None:
        print(f"fixed test set '{summary.test_name}': mse_norm/mean {summary.test_error:.4g}")
    print(summary.best_equations.rstrip())
    print("plain fit with the best config:\n  sdrl-bench " + " ".join(summary.overrides))
    if export_dir is not None:
        folder = Path(export_dir).resolve()
        print(f"or: sdrl-bench 'hydra.searchpath=[file://{folder}]' experiment={summary.name}")


def run_refine(cfg: DictConfig, choices: Mapping[str, str] | None = None, quiet: bool = False):
    """Residual-guided refinement from ``search.base_library`` with ``search.families``."""
    choices = choices or runtime_choices(cfg)
    sc = cfg.search
    seed = seed_key(cfg)
    name = check_study_name(str(cfg.study.name)) if cfg.study.name is not None else f"{choices.get('env', 'env')}-refine-s{seed}"
    k_folds = int_key(cfg, "search.k_folds", minimum=2)
    margin = float_key(cfg, "search.margin")
    if not 0.0 <= margin < 1.0:
        raise ConfigError(f"search.margin must be in [0, 1), got {margin}")
    thresholds = _thresholds(sc.get("thresholds"))
    label = _config_name(cfg, "search.base_library")
    base_library = load_group("library", label, "search.base_library")
    build = make_build_job(cfg)
    base_job = build({"library": label})
    families_node = sc.get("families")
    if not isinstance(families_node, DictConfig):
        raise ConfigError(f"search.families: a mapping of family name -> library parts is required, got {families_node!r}")
    family_cfgs = {str(k): OmegaConf.create({"name": str(k), "parts": v}) for k, v in families_node.items()}
    families = {k: _parts(cfg, v, f"search.families.{k}") for k, v in family_cfgs.items()}
    optimizers = [(f"threshold={t:g}", build({"threshold": t}).optimizer) for t in thresholds]
    out, fit = run_refinement(
        base_job, families, optimizers, margin=margin, seed=seed, k_folds=k_folds,
        uri=tracking.resolve_uri(cfg.tracking.uri), experiment=str(cfg.tracking.experiment), name=name,
        library_label=label,
        export_library=lambda chosen: _library_yaml(base_library, family_cfgs, chosen, name),
    )
    if not quiet:
        final = out.final
        for i, stage in enumerate(out.stages):
            for c in stage:
                score = "" if c.residual_score is None else f", residual score {c.residual_score:.3f}"
                print(f"stage {i}: base+{'+'.join(c.families) or '-'}: error {c.error:.3e}, {c.n_terms} terms "
                      f"({c.optimizer}{score}) {'accepted' if c.accepted else 'rejected'}")
        print(f"final: base+{'+'.join(final.families) or '-'} ({final.optimizer}); fixed test set "
              f"'{fit.test_name}' mse_norm/mean {fit.fidelity.metrics['mse_norm/mean']:.4g}; {out.n_fits} fits")
    return out, fit


def _fit_config(cfg: DictConfig) -> DictConfig:
    """The config without the search's own nodes: what ``build_fit_job`` reads."""
    c = copy.deepcopy(cfg)
    with open_dict(c):
        for key in ("search", "study", "hydra"):
            c.pop(key, None)
    return c


def _thresholds(value: Any) -> list[float]:
    """``search.thresholds``: a non-empty list of finite numbers >= 0 (the STLSQ thresholds)."""
    items = list(value) if isinstance(value, ListConfig) else None
    if not items or any(isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t) or t < 0
                        for t in items):
        raise ConfigError(f"search.thresholds: a non-empty list of finite numbers >= 0 is required, got "
                          f"{OmegaConf.to_container(value) if isinstance(value, ListConfig) else value!r}")
    return [float(t) for t in items]


def _parts(cfg: DictConfig, library_cfg: DictConfig, key: str) -> tuple:
    """The library parts of a refinement family (an error names ``key``, not ``library``)."""
    parts = library_cfg.get("parts")
    if not isinstance(parts, ListConfig) or not parts:
        raise ConfigError(f"{key}: a non-empty list of library parts is required, got {parts!r}")
    c = _fit_config(cfg)
    with open_dict(c):
        c.library = library_cfg
    try:
        return build_fit_job(c).library_parts
    except ConfigError as exc:
        message = str(exc)
        if message.startswith("library.parts["):  # the family's own parts: named by the search's key
            message = key + message[len("library.parts"):]
        raise ConfigError(message) from None


def _library_yaml(base: DictConfig, families: Mapping[str, DictConfig], chosen, name: str) -> str:
    parts = list(OmegaConf.to_container(base.parts)) + [p for f in chosen for p in OmegaConf.to_container(families[f].parts)]
    body = {"name": name, "parts": parts}
    return f"# Library found by residual-guided refinement '{name}' (copy into a library/ folder of your --config-dir).\n" + yaml.safe_dump(body, sort_keys=False)


def study_names(cfg: DictConfig) -> list[str]:
    """``search=compare``'s ``search.studies``: a non-empty list of study names."""
    value = cfg.search.get("studies")
    items = list(value) if isinstance(value, ListConfig) else None
    if not items or any(isinstance(v, bool) or not isinstance(v, (str, int)) or str(v) == "" for v in items):
        shown = OmegaConf.to_container(value) if isinstance(value, ListConfig) else value
        raise ConfigError(f"search.studies: a non-empty list of study names is required "
                          f"(search.studies=[name1,name2]), got {shown!r}")
    return [str(v) for v in items]


def search_mode(cfg: DictConfig) -> str:
    mode = str(cfg.search.get("mode", "study"))
    if mode not in ("study", "refine", "compare"):
        raise ConfigError(f"search.mode: 'study', 'refine' or 'compare', got {mode!r}")
    return mode


def check_job(cfg: DictConfig, overrides: Sequence[str] = ()) -> None:
    """What a study's worker checks before its data and stores (``run_search``'s settings, the
    run's own fit and the search space, as ``run_study`` checks them). A ``-m`` sweep's driver runs
    it on each worker's config (``cli.precheck``) before ``SearchStorageCallback`` makes the
    stores, so a bad value stops the sweep in one line with nothing made. Refinements and
    comparisons check themselves when they run."""
    if search_mode(cfg) != "study":
        return
    settings = study_settings(cfg, {})
    bool_key(cfg, "study.final_score")
    check_study(settings, make_build_job(cfg))


class SearchStorageCallback(Callback):
    """In a ``-m`` sweep, create the Optuna storage and the MLflow store in the driver, before
    workers start (processes racing to create SQLite tables crash)."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        open_storage(resolve_storage(config.study.storage))
        tracking.ensure_experiment(tracking.resolve_uri(config.tracking.uri), config.tracking.experiment)


def main() -> None:
    """``python -m sdrl_bench.cli.search``: the command line checked first, then the Hydra app
    (``cli.precheck.search_main``, the ``sdrl-bench-search`` entry point)."""
    from sdrl_bench.cli.precheck import search_main

    search_main()


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="search_app")
def app(cfg: DictConfig) -> float | None:
    """Entry point of ``sdrl-bench-search``: returns the best held-out error (for sweepers)."""
    # SIGTERM and SIGINT unwind: the running trial fails in Optuna, its run and the study's
    # parent run end KILLED (a rerun resumes the study)
    if signal.getsignal(signal.SIGTERM) in (signal.SIG_DFL, None):
        raise_on_stop_signals()
    try:
        mode = search_mode(cfg)
        if mode == "refine":
            out, _ = run_refine(cfg)
            return float(out.final.error)
        if mode == "compare":
            print(comparison_table(load_summaries(cfg.study.storage, study_names(cfg))))
            return None
        result, summary = run_search(cfg)
        if HydraConfig.get().mode.name == "MULTIRUN":
            out_dir = Path(HydraConfig.get().runtime.output_dir)
            (out_dir / "worker.json").write_text(json.dumps({"study": summary.name, "worker": result.settings.worker,
                                                             "trials": result.trials}))
        return summary.best_error
    except ConfigError as exc:
        print(f"sdrl-bench-search: error: {exc}", file=sys.stderr)
        sys.exit(2)
    except (Terminated, Exception) as exc:
        signum = exc.signum if isinstance(exc, Terminated) else stop_signal_received()
        if signum is None:
            raise
        exit_after_stop_signal(cfg, signum, "sdrl-bench-search",
                               "the trial and study runs ended KILLED; rerun the same command to resume the study")


if __name__ == "__main__":  # python -m: run the package's copy, so joblib workers can unpickle it
    from sdrl_bench.cli.search import main as package_main

    package_main()
