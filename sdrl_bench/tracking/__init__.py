"""The one door to MLflow: the only package that imports mlflow.

``from sdrl_bench import tracking`` and call ``tracking.<function>``. The submodules:
``client`` (where the store is, creating it safely, one run's writes), ``lifecycle`` (the run
lifecycle every tracked job shares), ``fit`` (a fit's
metrics, dataset, model and figures), ``transfer`` (an RL run's arms, curves, agents and the
reuse of a finished real arm), ``sb3`` (SB3's logger into a run), ``meta`` (standard tags, lean params, descriptions, system
metrics, UI links), ``model`` (datasets and the pyfunc model), ``sweep`` (a sweep parent's summary) and ``read`` (runs as plain
dicts for the report and the search).
"""

from sdrl_bench.tracking.client import (
    DEFAULT_DB,
    PARENT_TAG,
    RUN_NAME_TAG,
    Run,
    check_integrity,
    check_store,
    uri_key,
    check_writable,
    cpu_tags,
    create_parent_run,
    delete_run,
    display_uri,
    end_run,
    ensure_experiment,
    flatten,
    git_commit,
    machine_label,
    log_report,
    mlflow_client,
    process_tags,
    resolve_uri,
    sqlite_path,
    start_run,
    store_lock,
    use_wal,
)
from sdrl_bench.tracking.fit import fit_metrics, log_fit, uncertainty_table
from sdrl_bench.tracking.lifecycle import end_runs_of_dead_processes, tracked_run
from sdrl_bench.tracking.read import (
    child_statuses,
    download_artifact,
    end_runs_of_this_process,
    runs_of_this_process,
    end_stale_runs,
    find_runs,
    list_artifacts,
    list_experiments,
    owner_alive,
    run_exists,
    running_below,
)
from sdrl_bench.tracking.meta import (
    browse_hint,
    compare_url,
    describe_experiment,
    log_config,
    run_url,
    runs_url,
    set_description,
    standard_tags,
    system_metrics,
    ui_base,
    without_credentials,
    used_params,
)
from sdrl_bench.tracking.sb3 import sb3_logger
from sdrl_bench.tracking.sweep import ADOPTED_BY_TAG, ADOPTED_FROM_TAG, note_adoptions, summarize_sweep
from sdrl_bench.tracking.transfer import find_real_arm, log_arm, log_curve_point, reuse_real_arm

__all__ = [
    "DEFAULT_DB", "PARENT_TAG", "RUN_NAME_TAG", "Run", "check_integrity", "check_store", "uri_key", "check_writable", "child_statuses", "create_parent_run",
    "cpu_tags", "delete_run", "display_uri", "download_artifact", "end_run", "end_runs_of_dead_processes", "end_runs_of_this_process", "runs_of_this_process", "end_stale_runs", "owner_alive", "process_tags", "ensure_experiment", "find_real_arm", "find_runs",
    "fit_metrics", "flatten", "git_commit", "list_artifacts", "list_experiments", "log_arm", "log_curve_point",
    "log_fit", "log_report", "machine_label", "mlflow_client", "resolve_uri", "reuse_real_arm", "run_exists", "running_below", "sb3_logger", "sqlite_path",
    "start_run", "store_lock", "tracked_run", "uncertainty_table", "use_wal",
    "browse_hint", "compare_url", "describe_experiment", "log_config", "run_url", "runs_url", "set_description",
    "standard_tags", "summarize_sweep", "note_adoptions", "ADOPTED_BY_TAG", "ADOPTED_FROM_TAG", "system_metrics", "ui_base", "used_params", "without_credentials",
]
