"""The repository scripts' command lines (``benchmarks/``, ``studies/``, ``scripts/reproduce.py``).

Checks, each on an argparse parser's values: a bad value is one line naming its flag
(``ap.error``: exit 2) before any fit, training or store write starts. argparse's ``type=``
checks one value; these check what argparse cannot (a value against the machine, a seed list's
ranges, a store).

Children: a script that runs ``sdrl-bench`` commands (``run_child``, ``wait_children``) passes a
stop on to them, so that stopping the script stops the runs it started (``script_main``).

No hydra here: the scripts call ``sdrl-bench`` as a command or compose through ``cli.build``."""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any


def at_least(ap: argparse.ArgumentParser, args: argparse.Namespace, minimum: int | float, *flags: str) -> None:
    """``ap.error`` for the first of ``flags`` (as typed: ``"--repeats"``) whose value is under
    ``minimum``; a flag left at None (not given, no default) passes. For ``nargs`` flags, each value."""
    for flag in flags:
        value = getattr(args, flag.lstrip("-").replace("-", "_"))
        for v in value if isinstance(value, list) else [value]:
            if v is not None and v < minimum:
                kind = "an integer" if isinstance(minimum, int) else "a number"
                ap.error(f"{flag}: {kind} >= {minimum} is required, got {v}")


def n_jobs_problem(value: object) -> str | None:
    """What is wrong with a sweep's parallel jobs (``hydra.launcher.n_jobs``, joblib's ``n_jobs``:
    a whole number other than 0; -1 is every core, -2 all but one), None when nothing is."""
    if isinstance(value, bool) or not isinstance(value, int) or value == 0:
        return f"a whole number of parallel jobs other than 0 is required (1, 2, ...; -1 for every core), got {value!r}"
    return None


def jobs(ap: argparse.ArgumentParser, value: int, flag: str = "--jobs") -> None:
    """A script's ``--jobs``, handed to a sweep as ``hydra.launcher.n_jobs`` (``n_jobs_problem``)."""
    problem = n_jobs_problem(value)
    if problem:
        ap.error(f"{flag}: {problem}")


def pin_cores(ap: argparse.ArgumentParser, cores: int | None, flag: str = "--cores") -> None:
    """Pin this process to its first ``cores`` allowed cores (None: leave it); more than it may
    use, or under 1, is refused (a per-core benchmark would silently run on fewer, or none)."""
    if cores is None:
        return
    have = sorted(os.sched_getaffinity(0))
    if not 1 <= cores <= len(have):
        ap.error(f"{flag}: an integer from 1 to {len(have)} (the cores this process may use) is required, got {cores}")
    os.sched_setaffinity(0, have[:cores])


def seed_list(ap: argparse.ArgumentParser, text: str, flag: str = "--seeds") -> list[int]:
    """``0-4``, ``0,2`` or both (``0-4,20-24``): the seeds, in order; anything else (an empty
    part, a range that runs backwards, a non-number) is ``ap.error`` naming ``flag``."""
    out: list[int] = []
    for part in text.split(","):
        lo, dash, hi = part.strip().partition("-")
        if not (lo.isdigit() and (hi.isdigit() or not dash)) or int(hi or lo) < int(lo):
            ap.error(f"{flag}: seeds as 0-4, 0,2 or 0-4,20-24 are required, got {text!r}")
        out += range(int(lo), int(hi or lo) + 1)
    return out


def folder(ap: argparse.ArgumentParser, path: str | Path, flag: str) -> Path:
    """``path`` resolved, refused when it exists and is not a folder (the script would create
    it, or files in it)."""
    p = Path(path).expanduser().resolve()
    if p.exists() and not p.is_dir():
        ap.error(f"{flag}: {path} is a file, not a folder")
    return p


def out_file(ap: argparse.ArgumentParser, path: str | Path | None, flag: str = "--out") -> Path | None:
    """``path`` (a file the script writes at its end) resolved, refused when it is a folder or its
    folder does not exist (found before the work, not after it); None passes."""
    if path is None or str(path) == "":
        return None
    p = Path(path).expanduser().resolve()
    if p.is_dir() or not p.parent.is_dir():
        ap.error(f"{flag}: {path} is a folder, or in a folder that does not exist")
    return p


def store(ap: argparse.ArgumentParser, uri: str, flag: str = "--uri") -> None:
    """The tracking store at ``uri`` checked as ``sdrl-bench`` checks ``tracking.uri``
    (``tracking.check_store``: a folder, a damaged or an Optuna file, an unknown scheme)."""
    from sdrl_bench import ConfigError, tracking

    try:
        tracking.check_store(tracking.resolve_uri(uri), key=flag)
    except ConfigError as exc:
        ap.error(str(exc))


def script_main(main: Callable[[], Any], prog: str) -> None:
    """Run a script's ``main`` with SIGTERM and SIGINT raised as ``sdrl_bench.Terminated`` (as
    ``sdrl-bench`` takes them), so that its ``finally`` blocks run and ``wait_children`` stops
    its children; a stop ends in one line and exit 128 + the signal (SIGTERM's default killed the
    script alone and left its ``sdrl-bench`` children running)."""
    from sdrl_bench import Terminated, raise_on_stop_signals

    raise_on_stop_signals()
    try:
        code = main()
    except Terminated as exc:
        print(f"{prog}: stopped by {signal.Signals(exc.signum).name}; its commands were stopped", file=sys.stderr)
        sys.exit(128 + exc.signum)
    sys.exit(code if isinstance(code, int) else 0)


STOP_GRACE_S = 60.0
"""How long a stopped child may take to end its runs (``sdrl-bench`` ends them KILLED; a sweep
driver stops its workers within about 5 s) before it is killed."""


def wait_children(procs: Sequence[subprocess.Popen], grace: float = STOP_GRACE_S) -> list[int]:
    """The children's exit codes, once all have ended. When this process is stopped meanwhile
    (``Terminated``, Ctrl-C) or fails, each child still running gets SIGTERM and SIGKILL after
    ``grace`` seconds, and then the exception goes on. A Ctrl-C at a terminal reaches the children
    too (one process group): they get 10 s to end by themselves first, so their cleanup is not
    interrupted by a second signal."""
    from sdrl_bench import Terminated

    try:
        return [p.wait() for p in procs]
    except BaseException as exc:
        if not (isinstance(exc, Terminated) and exc.signum == signal.SIGTERM):  # SIGINT: likely the tty's
            _wait_until(procs, 10.0 if isinstance(exc, KeyboardInterrupt) else 0.0)
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        _wait_until(procs, grace)
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
        raise


def _wait_until(procs: Sequence[subprocess.Popen], seconds: float) -> None:
    deadline = time.monotonic() + seconds
    for p in procs:
        try:
            p.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            pass


def run_child(cmd: Sequence[str], check: bool = True, **popen: Any) -> int:
    """``subprocess.run(cmd, check=check, **popen)``'s exit code, the child stopped with this
    process (``wait_children``; ``subprocess.run`` SIGKILLs it, leaving its runs RUNNING)."""
    code = wait_children([subprocess.Popen(list(cmd), **popen)])[0]
    if check and code:
        raise subprocess.CalledProcessError(code, list(cmd))
    return code
