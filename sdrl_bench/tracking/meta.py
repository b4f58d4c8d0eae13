"""What MLflow's UI shows beside the numbers: standard tags (Version, User, Source), the lean
params a run used (the full config goes in as ``config.yaml``), run and experiment
descriptions, system metrics, and the UI's own URLs for runs and comparisons."""

from __future__ import annotations

import contextlib
import functools
import getpass
import json
import subprocess
import sys
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any
from urllib.parse import quote, urlsplit, urlunsplit

from sdrl_bench import redact
from sdrl_bench.tracking.client import Run, flatten, git_commit, mlflow_client

NOTE_TAG = "mlflow.note.content"  # the run's (or the experiment's) Description in the UI
EXPERIMENT_NOTE = (
    "sdrl-bench: sparse-dynamics (SINDy) surrogates of Gymnasium environments and RL agents trained in them.\n\n"
    "Runs by `sdrl.kind`: `fit` (collect -> fit -> one-step and k-step fidelity on a fixed held-out test set; "
    "the run's description holds the discovered equations, its Models tab the surrogate as a pyfunc, its "
    "Datasets the training transitions and the test set), `transfer` (an agent trained inside the surrogate and "
    "one in the real env, both judged in the real env; arms under `surrogate/` and `real/`, the fit under the "
    "same names as fit runs), `sweep` (a multirun's parent: its overrides as params, the best child's metric), "
    "`study` (an Optuna search), `report`."
)


@functools.cache
def package_commit() -> str:
    """The git commit of the sdrl_bench source that runs, read once per process (the code that
    runs is the code imported): "unknown" for an installed wheel, also one whose venv sits inside
    another git repository (the folder above the package must be that repository's top)."""
    root = Path(__file__).resolve().parents[2]
    try:
        top = subprocess.run(["git", "rev-parse", "--show-toplevel"], capture_output=True, text=True, cwd=root,
                             timeout=5)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    if top.returncode != 0 or Path(top.stdout.strip()).resolve() != root:
        return "unknown"
    return git_commit(root)


@functools.cache
def package_version() -> str:
    """The installed distribution's version (a wheel's, or an editable install's), read once per
    process (every run's standard tags carry it)."""
    from importlib import metadata

    try:
        return metadata.version("sdrl-bench")
    except metadata.PackageNotFoundError:  # imported from a source tree that is not installed
        from sdrl_bench import __version__

        return __version__


def source_commit() -> str:
    """The commit of the working directory's repository (the user's experiment code), else of
    the sdrl_bench checkout that runs (an editable install used from another folder), else
    "unknown"."""
    commit = git_commit()
    return commit if commit != "unknown" else package_commit()


def standard_tags(source: str | None = None) -> dict[str, str]:
    """MLflow's own tags, which fill the UI's Version, User and Source columns; plus the
    project's ``git_commit`` tag (same value), ``sdrl.package_version`` and, from a checkout,
    ``sdrl.package_commit`` (the harness's own)."""
    commit = source_commit()
    try:
        user = getpass.getuser()
    except Exception:  # no login name (some containers)
        user = "unknown"
    name = source or (Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "sdrl-bench")
    if name in ("__main__.py", "-m", "-c", ""):
        name = "sdrl-bench"
    tags = {"mlflow.user": user, "mlflow.source.name": name, "mlflow.source.type": "LOCAL", "git_commit": commit,
            "sdrl.package_version": package_version()}
    if commit != "unknown":
        tags["mlflow.source.git.commit"] = commit
    harness = package_commit()
    if harness != "unknown":
        tags["sdrl.package_commit"] = harness
    return tags


# ---------------------------------------------------------------------- params
_DROP = ("_target_", "_partial_")


def _group(cfg: Mapping[str, Any], key: str, *, skip: Sequence[str] = ()) -> dict[str, str]:
    sub = cfg.get(key)
    if not isinstance(sub, Mapping):
        return {}
    flat = flatten(sub, f"{key}.")
    return {k: v for k, v in flat.items() if k.rsplit(".", 1)[-1] not in _DROP and not any(k.startswith(s) for s in skip)}


def used_params(config: Mapping[str, Any], uri: str, task: str = "fit") -> dict[str, str]:
    """The parameters a run used, from the resolved config (a plain dict): seed and data,
    collector, model (SINDy: library and optimizer; else the surrogate's hyperparameters), and
    for ``task="train"`` the agent and the RL budgets (``task="dyna"``: the agent and ``rl.dyna``). Values that are None are left out;
    ``tracking.uri`` is the store the run went to (its password hidden). The whole config goes in as
    ``config.yaml``."""
    arms = config.get("rl", {}).get("arms", []) if task == "train" else ["surrogate"]
    p: dict[str, str] = {"seed": str(config.get("seed")), "tracking.uri": redact(uri)}
    if "surrogate" in arms:
        p["n_transitions"] = str(config.get("n_transitions"))
        p.update(_group(config, "dataset"))
        collector = config.get("collector", {})
        p["collector.name"] = str(collector.get("name"))
        p["collector.epsilon"] = str(collector.get("epsilon"))
        p["collector.max_steps_per_episode"] = str(collector.get("max_steps_per_episode"))
        policy = collector.get("policy") or {}
        if isinstance(policy, Mapping) and "budget" in policy:  # an expert collector
            p["collector.policy.budget"] = str(policy["budget"])
            p["collector.policy.agent.name"] = str((policy.get("agent") or {}).get("name"))
        surrogate = config.get("surrogate", {}) or {}
        p["surrogate.kind"] = str(surrogate.get("kind"))
        p.update({f"surrogate.{k}": v for k, v in _group(surrogate, "model").items()})
        if surrogate.get("kind", "sindy") == "sindy":
            p.update(_group(config, "library"))
            p.update(_group(config, "optimizer"))
    if task in ("train", "dyna"):
        agent = config.get("agent", {}) or {}
        p["agent.name"] = str(agent.get("name"))
        p["agent.n_envs"] = str(agent.get("n_envs"))
        if agent.get("normalize_reward"):
            p["agent.normalize_reward"] = "True"
        p.update({f"agent.{k}": v for k, v in _group(agent, "algo", skip=("algo.device",)).items()})
        if task == "train":
            p.update(_group(config, "rl", skip=("rl.reuse_real_arm", "rl.dyna")))
        else:
            p.update({f"rl.{k}": v for k, v in _group(config.get("rl", {}) or {}, "dyna").items()})
    return {k: v for k, v in p.items() if v not in ("None", "null")}


def log_config(run: Run, config: Mapping[str, Any], uri: str, task: str = "fit") -> None:
    """Lean params (``used_params``) and the full resolved config as ``config.yaml``, every URL's
    password in it hidden (``redact``: ``tracking.uri``, ``study.storage``)."""
    import yaml

    run.log_params(used_params(config, uri, task))
    plain = json.loads(json.dumps(dict(config), default=str))
    run.log_text(yaml.safe_dump(_redacted(plain), sort_keys=False), "config.yaml")


def _redacted(node: Any) -> Any:
    if isinstance(node, dict):
        return {k: _redacted(v) for k, v in node.items()}
    if isinstance(node, list):
        return [_redacted(v) for v in node]
    return redact(node) if isinstance(node, str) else node


# ---------------------------------------------------------------------- descriptions
def set_description(run: Run, text: str) -> None:
    """The run's Description (Markdown) in the UI."""
    run.set_tags({NOTE_TAG: text})


def describe_experiment(uri: str, experiment_id: str) -> None:
    """Give the experiment a description once (a user's own is kept)."""
    client = mlflow_client(uri)
    exp = client.get_experiment(experiment_id)
    if NOTE_TAG not in (exp.tags or {}):
        client.set_experiment_tag(experiment_id, NOTE_TAG, EXPERIMENT_NOTE)


def experiment_id_of(run: Run) -> str:
    return mlflow_client(run.uri).get_run(run.run_id).info.experiment_id


@contextlib.contextmanager
def system_metrics(run: Run, interval: float = 5.0) -> Iterator[None]:
    """MLflow's system metrics (CPU, memory, disk, network; ``system/*``) sampled into ``run``
    every ``interval`` seconds while the body runs (psutil; GPUs when pynvml finds one)."""
    try:
        from mlflow.system_metrics.system_metrics_monitor import SystemMetricsMonitor

        monitor = SystemMetricsMonitor(run.run_id, sampling_interval=interval, tracking_uri=run.uri)
        monitor.start()
    except Exception:  # psutil missing or the monitor cannot start: train without it
        monitor = None
    try:
        yield
    finally:
        if monitor is not None:
            monitor.finish()


# ---------------------------------------------------------------------- UI links
def ui_base(uri: str) -> str | None:
    """The MLflow UI's address for a tracking URI: an http(s) server serves its own UI; a local
    store has none until ``mlflow ui`` runs (None). No credentials: the links are printed and
    written into reports (a browser asks for them)."""
    return without_credentials(uri).rstrip("/") if uri.startswith(("http://", "https://")) else None


def without_credentials(url: str) -> str:
    """``url`` without its ``user:password@`` part."""
    try:
        parts = urlsplit(url)
    except ValueError:
        return url
    if "@" not in parts.netloc:
        return url
    return urlunsplit(parts._replace(netloc=parts.netloc.rpartition("@")[2]))


def run_url(base: str, experiment_id: str, run_id: str) -> str:
    """A run's page (MLflow 3 routes; ``workflowType=machine_learning`` keeps the UI in its
    model-training mode instead of GenAI)."""
    return f"{base.rstrip('/')}/#/experiments/{experiment_id}/runs/{run_id}?workflowType=machine_learning"


def runs_url(base: str, experiment_id: str) -> str:
    return f"{base.rstrip('/')}/#/experiments/{experiment_id}/runs?workflowType=machine_learning"


def compare_url(base: str, run_ids: Sequence[str], experiment_ids: Sequence[str]) -> str:
    """The UI's compare view of exactly these runs (a table cell that is a mean over seeds)."""
    runs = quote(json.dumps(list(run_ids), separators=(",", ":")), safe="")
    exps = quote(json.dumps(sorted(set(experiment_ids)), separators=(",", ":")), safe="")
    return f"{base.rstrip('/')}/#/compare-runs?runs={runs}&experiments={exps}&workflowType=machine_learning"


def browse_hint(uri: str, experiment_id: str, run_id: str, display: str) -> str:
    """What to open to see a run: its URL on a server; for a local store the ``mlflow ui``
    command and the URL the run will have there."""
    base = ui_base(uri)
    if base is not None:
        return f"open {run_url(base, experiment_id, run_id)}"
    return (f"browse: mlflow ui --backend-store-uri {display}, then open "
            f"{run_url('http://127.0.0.1:5000', experiment_id, run_id)}")
