"""The ``task=fidelity`` half of ``sdrl-bench``: one cluster of the fidelity-vs-transfer study
(``rl.fidelity_study``), a cluster MLflow run with one child run per surrogate.

The cluster's data follow from its seed, a full factorial over ``fidelity.axes``: with axes of
sizes (a, b, c), seed s takes ``n_transitions[s % a]``, ``collector[(s // a) % b]`` and
``data_noise[(s // ab) % c]``, so seeds 0..abc-1 cover every combination once, each with its own
real data (no two clusters share a reset seed). ``fidelity.models`` names the surrogates fitted on
every cluster (label -> Hydra overrides, composed on top of the job's own). A study is then an
ordinary sweep over seeds (``-m experiment=fidelity_<env>``); a rerun adopts its finished
clusters, and inside a cluster its finished surrogates (same config key), so a stopped study
continues where it stopped.
"""

from __future__ import annotations

import sys

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from sdrl_bench import ConfigError, tracking
from sdrl_bench.cli.callbacks import CONFIG_KEY_TAG
from sdrl_bench.cli.build import build_fit_job, compose, config_key, instantiate_key, int_key, run_label, seed_key
from sdrl_bench.rl.fidelity_study import ClusterJob, Variant, collect_cluster, score_variant

POINT_TAG = "sdrl.fidelity_point"
"""A surrogate run's config key: a rerun of its cluster adopts it instead of refitting."""


def cluster_axes(cfg: DictConfig) -> dict[str, object]:
    """The cluster's data settings, chosen by its seed from ``fidelity.axes`` (a full factorial)."""
    axes = cfg.fidelity.axes
    seed = seed_key(cfg)
    out, div = {}, 1
    for key in ("n_transitions", "collector", "data_noise"):
        values = list(OmegaConf.to_container(axes[key], resolve=True)) if key in axes else []
        if not values:
            raise ConfigError(f"fidelity.axes.{key}: a non-empty list is required")
        for v in values:  # named here: a cluster's composed config would name only n_transitions or data_noise
            if key == "n_transitions" and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
                raise ConfigError(f"fidelity.axes.n_transitions: integers >= 1 are required, got {v!r}")
            if key == "data_noise" and (isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v < float("inf")):
                raise ConfigError(f"fidelity.axes.data_noise: finite numbers >= 0 are required, got {v!r}")
        out[key] = values[(seed // div) % len(values)]
        div *= len(values)
    out["n_clusters"] = div
    return out


def base_overrides(cfg: DictConfig, given: list[str] | None) -> list[str]:
    """The job's own overrides (the command line's, or ``given``), less the keys the cluster sets."""
    if given is None:
        given = list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []
    drop = ("n_transitions=", "collector=", "task=", "surrogate=", "library=", "optimizer=")
    return [o for o in given if not o.lstrip("+~").startswith(drop)]


def build_cluster(cfg: DictConfig, given: list[str] | None = None) -> tuple[ClusterJob, dict, list[DictConfig]]:
    """The typed cluster job, its data settings and each surrogate's composed config."""
    f = cfg.fidelity
    axes = cluster_axes(cfg)
    base = base_overrides(cfg, given) + [f"n_transitions={axes['n_transitions']}", f"collector={axes['collector']}"]
    data_cfg = _compose(base, "fidelity.axes")
    data_job = build_fit_job(data_cfg)
    models = f.models if f.models is None or not OmegaConf.is_config(f.models) else OmegaConf.to_container(f.models, resolve=True)
    models = {"default": []} if models is None else models
    if not isinstance(models, dict) or not models:
        raise ConfigError("fidelity.models: a mapping label -> list of overrides is required")
    variants, cfgs = [], []
    for label, overrides in models.items():
        if not isinstance(overrides, list):
            raise ConfigError(f"fidelity.models.{label}: a list of overrides is required, got {overrides!r}")
        vcfg = _compose(base + [str(o) for o in overrides], f"fidelity.models.{label}")
        job = build_fit_job(vcfg)
        variants.append(Variant(str(label), str(vcfg.surrogate.kind), job))
        cfgs.append(vcfg)
    if f.get("study") is not None and (isinstance(f.study, bool) or not isinstance(f.study, (str, int))
                                       or not str(f.study).strip()):  # 2024 arrives as an int
        raise ConfigError(f"fidelity.study: a name is required (or null for fidelity-<env>), got {f.study!r}")
    ref = str(f.reference)
    reference = None if ref == "random" else instantiate_key(
        _compose(base[:-1] + [f"collector={ref}"], "fidelity.reference").collector.policy, "fidelity.reference")
    agent = instantiate_key(cfg.agent, "agent")
    job = ClusterJob(
        data_job=data_job, variants=tuple(variants), agent=agent, train_steps=int_key(cfg, "fidelity.train_steps", 1),
        agent_seeds=int_key(cfg, "fidelity.agent_seeds", 1), final_episodes=int_key(cfg, "fidelity.final_episodes", 1),
        onpolicy_episodes=int_key(cfg, "fidelity.onpolicy_episodes", 0), reference=reference, reference_name=ref,
        reference_episodes=int_key(cfg, "fidelity.reference_episodes", 1),
        data_noise=float(axes["data_noise"]), seed=seed_key(cfg),
    )
    return job, axes, cfgs


def _compose(overrides: list[str], key: str) -> DictConfig:
    """``compose``; an override Hydra refuses (an unknown group option, a bad key) is one line naming ``key``."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    try:
        return compose(overrides)
    except (HydraException, OmegaConfBaseException) as exc:
        text = " ".join(str(exc).split()).split(" Config search path:")[0]
        raise ConfigError(f"{key}: {text[:300]}") from None


def run_fidelity_task(cfg: DictConfig, parent: str | None, extra_tags: dict[str, str] | None = None,
                      given: list[str] | None = None) -> dict[str, float]:
    """Validate, then run one cluster inside an MLflow run; returns {label: real return}."""
    from sdrl_bench.cli.train import prepare

    job, axes, cfgs = build_cluster(cfg, given)
    job, checked, uri = prepare(cfg, job)  # checked: each variant's (library, data), built once
    spec = job.data_job.spec
    study = str(cfg.fidelity.study) if cfg.fidelity.study is not None else f"fidelity-{spec.name}"
    tags = {"env": spec.name, "sdrl.study": study, "seed": job.seed, "collector": axes["collector"],
            "n_transitions": axes["n_transitions"], "data_noise": axes["data_noise"], "agent": job.agent.name,
            "reference": job.reference_name, **(extra_tags or {})}
    name = run_label(f"fidelity-{spec.name}-s{job.seed}", extra_tags)
    print(f"sdrl-bench: {name}: study {study}, cluster seed {job.seed} (cell {job.seed % axes['n_clusters']} of "
          f"{axes['n_clusters']}): {axes['n_transitions']} "
          f"transitions, collector {axes['collector']}, data noise {axes['data_noise']}; {len(job.variants)} surrogates x "
          f"{job.agent_seeds} agents of {job.train_steps:,} steps", flush=True)
    out: dict[str, float] = {}
    with tracking.tracked_run(uri, cfg.tracking.experiment, name, "fidelity-cluster", tags, parent, task="fidelity",
                              config=OmegaConf.to_container(cfg, resolve=True), system=True) as run:
        cluster = collect_cluster(job)
        run.log_metrics({"reference_real_return": float(cluster.reference_real.mean()),
                         "real_steps/model_data": float(cluster.counts["collect"]),
                         "real_steps/reference": float(cluster.counts["reference"]), "n_surrogates": float(len(job.variants))})
        for variant, vcfg, (library, _) in zip(job.variants, cfgs, checked, strict=True):
            out[variant.label] = _surrogate_run(cfg, uri, run.run_id, job, variant, vcfg, library, cluster, tags, extra_tags)
        run.log_metrics({"real_return_mean": sum(out.values()) / len(out)})
    return out


def _surrogate_run(cfg, uri, cluster_run, job, variant, vcfg, library, cluster, tags, extra_tags) -> float:
    own = OmegaConf.to_container(vcfg, resolve=True)
    own["fidelity"].pop("models")  # a surrogate's key: its own config, not its siblings' (adding a model keeps the others)
    key = config_key(OmegaConf.create(own)) + f"-{variant.label}"
    done = tracking.find_runs(uri, cfg.tracking.experiment,
                              f"tags.`{POINT_TAG}` = '{key}' and attributes.status = 'FINISHED'") if cfg.get("resume", True) else []
    if done:
        prev = done[-1]
        tracking.Run(uri, prev["run_id"]).set_tags({tracking.PARENT_TAG: cluster_run})
        print(f"  {variant.label}: finished in run {prev['run_id']}: adopted", file=sys.stderr, flush=True)
        return float(prev["metrics"]["real_return"])
    from sdrl_bench.rl.accounting import expert_of, headline

    spec = job.data_job.spec
    # its own config key: the cluster's (a sweep job's tag) would make the report keep one surrogate per cluster
    vtags = {**tags, "model": variant.label, "family": variant.family, "surrogate": variant.family,
             "library": variant.fit.names.get("library", ""), POINT_TAG: key, CONFIG_KEY_TAG: key}
    name = run_label(f"fidelity-{spec.name}-s{job.seed}-{variant.label}", extra_tags)
    with tracking.tracked_run(uri, cfg.tracking.experiment, name, "fidelity-surrogate", vtags, cluster_run,
                              task="fidelity") as run:
        score = score_variant(job, variant, cluster, library,
                              on_fit=lambda fit: tracking.log_fit(run, fit, config=OmegaConf.to_container(vcfg, resolve=True),
                                                                  task="fidelity", model=False))
        c = score.counts
        counts = {"model_data": len(cluster.data), "judge": c["judge"] + len(cluster.test)}
        m = headline(counts, score.fit.spec.declared_priors, [expert_of(variant.fit.policy, spec.name)],
                     tuning=job.agent.tuning_real_steps + variant.fit.tuning_real_steps)
        m.update({"real_steps/onpolicy": float(c["onpolicy"]), "real_steps/reference": float(cluster.counts["reference"]),
                  "real_resets/reset_pool": float(c["resets/reset_pool"])})
        m.update({f"candidate/{k}": float(v) for k, v in score.candidates.items()})
        m["real_return"] = score.real_return
        m["episodes_per_agent"] = float(job.final_episodes)  # the judge's episodes of each agent (the report says)
        m["reference_real_return"] = float(cluster.reference_real.mean())
        for k, (rets, in_surrogate) in enumerate(zip(score.returns, score.surrogate_returns, strict=True)):
            m[f"agent{k}/real_return"] = float(sum(rets) / len(rets))
            m[f"agent{k}/surrogate_return"] = in_surrogate
        m.update({f"{k}_seconds": v for k, v in score.seconds.items()})
        run.log_metrics(m)
    line = ", ".join(f"{k} {score.candidates[k]:.3g}" for k in ("one_step", "rollout50", "onpolicy_one_step")
                     if k in score.candidates)
    print(f"  {variant.label}: real return {score.real_return:.1f} ({line})", flush=True)
    return score.real_return
