"""``sdrl-bench-report``: tracking store -> reports/<name>/report.md and report.html.

    sdrl-bench-report --name reproduction [--uri URI] [--experiment E] [--parent-run ID]
                      [--tag k=v ...] [--out reports] [--ui-url http://127.0.0.1:5000]
                      [--provenance rebuild.json]
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path
from collections.abc import Sequence
from urllib.parse import urlsplit

from sdrl_bench import ConfigError, redact_arg, tracking
from sdrl_bench.report.folder import report_files

# The report's builder (report.build: mlflow, pandas, about 4 s of imports) is imported in main,
# after the arguments and a local store's integrity are checked, so that bad input is answered
# at once.


def _parse_tags(items: Sequence[str]) -> dict[str, str]:
    out = {}
    for item in items:
        k, sep, v = item.partition("=")
        if not sep or not k:
            raise ConfigError(f"--tag: expected key=value, got {item!r}")
        out[k] = v
    return out


def _check_name(name: str) -> None:
    """``--name`` is a folder under ``--out`` (``mine`` or ``thesis/ch3``): a report never writes
    outside ``--out``, so no absolute path and no ``..``."""
    parts = Path(name).parts
    if not name.strip() or Path(name).is_absolute() or ".." in parts or not parts:
        raise ConfigError(f"--name: a folder under --out is required (no absolute path, no '..'), got {name!r}")


def main(argv: Sequence[str] | None = None) -> int:
    """The ``sdrl-bench-report`` command; exit code 0, or 2 when the input named nothing to report."""
    ap = argparse.ArgumentParser(prog="sdrl-bench-report", description=__doc__.splitlines()[0])
    ap.add_argument("--uri", help="tracking URI (default: MLFLOW_TRACKING_URI, else sqlite:///mlruns/mlflow.db)")
    ap.add_argument("--experiment", default="sdrl-bench", help="MLflow experiment (default: sdrl-bench; the searches "
                                                               "log to sdrl-bench-search)")
    ap.add_argument("--parent-run", help="only this sweep/study run and its descendants")
    ap.add_argument("--tag", action="append", default=[], metavar="K=V", help="only runs with this tag (repeatable)")
    ap.add_argument("--name", default="report", help="report folder name under --out: new, or an earlier report's "
                                                     "(rebuilt in place); other files there are left alone, and a file "
                                                     "of yours under a name the report writes is refused")
    ap.add_argument("--out", default="reports", type=Path, help="output folder (default: reports/)")
    ap.add_argument("--ui-url", help="MLflow UI base URL: numbers link to their runs there (default: the tracking "
                                     "server's own URL when --uri is a server; none for a local store)")
    ap.add_argument("--no-log", action="store_true", help="do not log the report as an MLflow run")
    ap.add_argument("--provenance", type=Path, help="rebuild record (scripts/reproduce.py's rebuild.json): how it was made")
    args = ap.parse_args(argv)
    command = "sdrl-bench-report " + " ".join(shlex.quote(redact_arg(a)) for a in (argv if argv is not None else sys.argv[1:]))
    try:
        tags = _parse_tags(args.tag)
        _check_name(args.name)
        ui_parts = urlsplit(args.ui_url or "")
        if args.ui_url and (ui_parts.scheme not in ("http", "https") or not ui_parts.netloc):
            raise ConfigError(f"--ui-url: an http(s) URL of an MLflow UI is required (e.g. http://127.0.0.1:5000), "
                              f"got {redact_arg(args.ui_url)!r}")
        uri = tracking.resolve_uri(args.uri)
        tracking.check_store(uri, tracking.uri_key(args.uri, "--uri"), reach=True)
        report_files(args.out, args.name)  # a folder holding the user's files: refused before the builder loads
        from sdrl_bench.report.build import ReportInput, build_report  # noqa: PLC0415  (see the imports above)

        # a server serves its own UI; the links are written into the report, so no credentials in them
        ui = tracking.without_credentials(args.ui_url) if args.ui_url else tracking.ui_base(uri)
        inp = ReportInput(uri, args.experiment, args.parent_run, tags, ui)
        res = build_report(inp, args.name, args.out, command.strip(), log_run=not args.no_log,
                           provenance=args.provenance)
    except ConfigError as exc:
        print(f"sdrl-bench-report: error: {exc}", file=sys.stderr)
        return 2
    print(f"report: {res.folder / 'report.md'} and {res.folder / 'report.html'} "
          f"({res.n_runs} run{'' if res.n_runs == 1 else 's'}, {res.seconds:.1f} s)"
          + (f"; logged as run {res.report_run_id}" if res.report_run_id else "; not logged to MLflow"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
