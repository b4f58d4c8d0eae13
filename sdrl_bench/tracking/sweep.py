"""A sweep parent's summary: the sweep's overrides as params, its children counted, the best
child's objective as metrics and tag, and a Markdown description listing the children; after a
rerun that adopted finished jobs, the earlier runs of the sweep say where their jobs went."""

from __future__ import annotations

import math
import sys
from collections import Counter
from collections.abc import Sequence

from sdrl_bench.tracking.client import PARENT_TAG, RUN_NAME_TAG, Run, mlflow_client
from sdrl_bench.tracking.meta import NOTE_TAG, standard_tags

#: A job's run adopted by a rerun of its sweep: the rerun's parent, and the parent it had before.
ADOPTED_BY_TAG, ADOPTED_FROM_TAG = "sdrl.adopted_by", "sdrl.adopted_from"
#: What a child run is judged by, per kind: (metric, "min" or "max").
OBJECTIVES = {"fit": ("mse_norm/mean", "min"), "transfer": ("surrogate/final_return_mean", "max")}


def _overrides(text: str) -> dict[str, str]:
    out = {}
    for item in text.split():
        key, sep, value = item.partition("=")
        if sep:
            out[key.lstrip("+~")[:250]] = value
    return out


def summarize_sweep(uri: str, parent_run_id: str, stamp: bool = True) -> dict[str, float]:
    """Write the summary onto the parent run (its ``sdrl.overrides`` tag names the sweep);
    returns the metrics logged. The best child is the one with the lowest normalized one-step
    MSE (fits) or the highest surrogate-arm real return (transfer runs). ``stamp``: add this
    process's standard tags the parent lacks (not for another process's earlier run)."""
    client = mlflow_client(uri)
    parent = client.get_run(parent_run_id)
    children = client.search_runs([parent.info.experiment_id], filter_string=f"tags.{PARENT_TAG} = '{parent_run_id}'",
                                  max_results=10_000)
    run = Run(uri, parent_run_id)
    overrides = _overrides(parent.data.tags.get("sdrl.overrides", ""))
    if overrides:
        run.log_params(overrides)
    statuses = [c.info.status for c in children]
    metrics: dict[str, float] = {"n_children": len(children), "n_finished": statuses.count("FINISHED"),
                                 "n_failed": sum(s in ("FAILED", "KILLED") for s in statuses)}
    kinds = {c.data.tags.get("sdrl.kind") for c in children}
    kind = next((k for k in OBJECTIVES if k in kinds), None)
    best = None
    if kind is not None:
        key, direction = OBJECTIVES[kind]
        scored = [c for c in children if c.info.status == "FINISHED" and not math.isnan(c.data.metrics.get(key, math.nan))]
        if scored:
            best = (min if direction == "min" else max)(scored, key=lambda c: c.data.metrics[key])
            metrics[f"best/{key}"] = best.data.metrics[key]
    run.log_metrics(metrics)
    tags = {k: v for k, v in standard_tags().items() if not parent.data.tags.get(k)} if stamp else {}
    lines = [f"**Sweep** over `{parent.data.tags.get('sdrl.overrides', '')}`: {len(children)} runs, "
             f"{metrics['n_finished']:.0f} finished, {metrics['n_failed']:.0f} failed."]
    if best is not None:
        key, direction = OBJECTIVES[kind]
        tags["best_run_id"] = best.info.run_id
        lines.append(f"\nBest ({direction} `{key}`): **{best.data.tags.get(RUN_NAME_TAG, best.info.run_id)}** "
                     f"(`{best.info.run_id}`), {best.data.metrics[key]:.4g}.")
        lines.append(f"\n| run | status | {key} |\n|---|---|---|")
        for c in sorted(children, key=lambda c: c.data.tags.get(RUN_NAME_TAG, "")):
            v = c.data.metrics.get(key)
            lines.append(f"| {c.data.tags.get(RUN_NAME_TAG, c.info.run_id)} | {c.info.status} | "
                         f"{'-' if v is None else f'{v:.4g}'} |")
    tags[NOTE_TAG] = "\n".join(lines)
    run.set_tags(tags)
    return metrics


def note_adoptions(uri: str, parent_run_id: str, earlier: Sequence[str]) -> list[str]:
    """The earlier runs of a sweep (``earlier``: their ids, same sweep key) after the rerun
    ``parent_run_id`` adopted finished jobs: each that is not RUNNING and whose children are no
    longer those its summary counts (``n_children``; none when it was stopped before its summary)
    is summarized again (the jobs it kept, often none), tagged ``sdrl.resumed_by``, its description
    opening with where its jobs went. A run this cannot update (deleted meanwhile) is left as it
    is. Returns the ids noted."""
    client = mlflow_client(uri)
    parent = client.get_run(parent_run_id)
    name = parent.data.tags.get(RUN_NAME_TAG, parent_run_id)
    adopted = client.search_runs(
        [parent.info.experiment_id], max_results=10_000,
        filter_string=f"tags.{PARENT_TAG} = '{parent_run_id}' and tags.`{ADOPTED_BY_TAG}` = '{parent_run_id}'")
    moved = Counter(c.data.tags.get(ADOPTED_FROM_TAG) for c in adopted)
    noted = []
    for old in earlier:
        try:
            run = client.get_run(old)
            if old == parent_run_id or run.info.lifecycle_stage != "active" or run.info.status == "RUNNING":
                continue
            kept = client.search_runs([run.info.experiment_id], filter_string=f"tags.{PARENT_TAG} = '{old}'",
                                      max_results=10_000)
            if run.data.metrics.get("n_children") == len(kept):
                continue  # nothing of it moved since its summary
            summarize_sweep(uri, old, stamp=False)
            note = client.get_run(old).data.tags.get(NOTE_TAG, "")
            here = (f"which adopted {moved[old]} of this run's finished jobs" if moved[old] else
                    "which holds the finished jobs this run had, adopted through a later rerun")
            Run(uri, old).set_tags({"sdrl.resumed_by": parent_run_id, NOTE_TAG: (
                f"**Resumed** by the sweep run **{name}** (`{parent_run_id}`), {here}: they are listed there; "
                f"this run keeps {len(kept)} run{'' if len(kept) == 1 else 's'}.\n\n{note}")})
            noted.append(old)
        except Exception as exc:  # one earlier run that cannot be updated does not stop the others
            print(f"sdrl-bench: could not note the rerun on earlier sweep run {old}: {(str(exc).splitlines() or [type(exc).__name__])[0]}",
                  file=sys.stderr)
    return noted
