"""sdrl-bench: sparse-dynamics (SINDy) surrogate environments for reinforcement learning."""

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

__version__ = "0.1.0"


class ConfigError(ValueError):
    """Bad user input (a config key, a file): reported as one line, before expensive work."""


def nearest_existing(folder: "str | os.PathLike[str]") -> Path:
    """``folder`` if it exists, else its nearest existing ancestor (where ``mkdir(parents=True)``
    would start)."""
    there = Path(folder)
    while not there.exists() and there != there.parent:
        there = there.parent
    return there


def file_in_the_way(folder: "str | os.PathLike[str]") -> "Path | None":
    """The file (not a folder) at ``folder`` or at its nearest existing ancestor, which would stop
    ``mkdir(parents=True)`` there; None when that is a folder. Bad input is named by it."""
    there = nearest_existing(folder)
    return None if there.is_dir() else there


def redact(url: str) -> str:
    """``url`` with its password hidden (``user:***@host``), for messages, tags, params, logged
    configs and reports: a tracking server's or a database's credentials are the user's to keep.
    Text that is no ``scheme://`` URL (a path, ``journal:...``, any other value) and a SQLite URL
    come back as they are. Another database URL (an Optuna storage) is read and written by
    SQLAlchemy, which takes a password with ``/`` or ``?`` in it as the database does, as earlier
    versions did (a study's parent run is found again by its redacted storage, tag
    ``sdrl.storage``); an HTTP(S) URL by ``urllib.parse``, which reads it as MLflow does."""
    import re
    import urllib.parse

    if "://" not in url or url.lower().startswith("sqlite:"):  # a SQLite URL holds a path, never a login
        return url
    if not url.lower().startswith(("http://", "https://")):
        try:
            from sqlalchemy.engine import make_url

            return make_url(url).render_as_string(hide_password=True)
        except Exception:  # not a URL SQLAlchemy reads (or no SQLAlchemy): hide what looks like a login
            return re.sub(r"//([^:/@]*):[^@]*@", r"//\1:***@", url)
    try:
        parts = urllib.parse.urlsplit(url)
        if parts.password is None:
            return url
    except ValueError:  # not a URL (an unbalanced bracket, a bad port): nothing to hide in it
        return url
    userinfo, _, host = parts.netloc.rpartition("@")
    return urllib.parse.urlunsplit(parts._replace(netloc=f"{userinfo.partition(':')[0]}:***@{host}"))


def redact_arg(arg: str) -> str:
    """A command-line argument, a URL or an override (``key=URL``, ``--flag=URL``, the URL
    quoted or not, as Hydra wants it when the password holds a comma), with any password in it
    hidden (``redact``)."""
    key, eq, value = arg.partition("=")
    if eq and "://" not in key:
        return f"{key}{eq}{_redact_quoted(value)}"
    return _redact_quoted(arg)


def _redact_quoted(text: str) -> str:
    quote = text[:1]
    if quote in ("'", '"') and len(text) > 1 and text.endswith(quote):
        return quote + redact(text[1:-1]) + quote
    return redact(text)


class Terminated(KeyboardInterrupt):
    """A stop signal (SIGTERM, SIGINT) raised as an exception in the main thread, so that open
    runs unwind and end KILLED (and Optuna fails the running trial, as it does on Ctrl-C)."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


_stop = {"signum": None, "pending": False, "held": 0}


def raise_on_stop_signals() -> None:
    """In the main thread: SIGTERM and SIGINT raise ``Terminated`` (at once, or at the end of a
    ``stop_signals_held`` block).

    A ``Terminated`` raised where Python cannot propagate it (a ``gc.callbacks`` function, a
    weakref callback, a ``__del__``) is printed and dropped ("Exception ignored in ..."), and the
    stop would be lost while the run goes on: jax registers a gc callback (the compiled agents
    load it), and torch, SQLAlchemy (under mlflow) and the standard library use
    weakref callbacks (a SIGTERM once landed in a ``WeakValueDictionary``'s). Such exceptions
    reach ``sys.unraisablehook``; ours delivers the signal again a moment later, outside the
    callback."""
    import signal
    import sys

    def handler(signum, frame):
        _stop["signum"] = signum
        run_stop_hooks()
        if _stop["held"]:
            _stop["pending"] = True
        else:
            raise Terminated(signum)

    previous = sys.unraisablehook
    if not getattr(previous, "_sdrl_redelivers", False):

        def hook(unraisable):
            if isinstance(unraisable.exc_value, Terminated):
                _redeliver(unraisable.exc_value.signum)
            else:
                previous(unraisable)

        hook._sdrl_redelivers = True  # type: ignore[attr-defined]
        sys.unraisablehook = hook
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, handler)


def _redeliver(signum: int, delay: float = 0.05) -> None:
    """Send ``signum`` to this process again after ``delay`` seconds (a daemon timer thread)."""
    import os
    import threading

    timer = threading.Timer(delay, os.kill, (os.getpid(), signum))
    timer.daemon = True
    timer.start()


_stop_hooks: list = []


def on_stop_signal(hook) -> None:
    """Call ``hook()`` when a stop signal arrives, before anything unwinds (``raise_on_stop_signals``'
    handler, the sweep driver's): a layer above this one prepares the cleanup a stop runs (the
    tracking client shortens its waits on a server, ``tracking.client``). A hook is cheap and does
    not raise; one registered twice runs once."""
    if hook not in _stop_hooks:
        _stop_hooks.append(hook)


def run_stop_hooks() -> None:
    """Run the ``on_stop_signal`` hooks (a stop signal's handler calls it first)."""
    for hook in _stop_hooks:
        with contextlib.suppress(Exception):
            hook()


def stop_signal_received() -> int | None:
    """The stop signal this process has received, if any (an exception raised after one is
    taken as that stop: a library's cleanup may have replaced our ``Terminated`` with its own)."""
    return _stop["signum"]


def raise_pending_stop() -> None:
    """Raise ``Terminated`` for a stop signal that arrived while signals were held."""
    if _stop["pending"]:
        _stop["pending"] = False
        raise Terminated(_stop["signum"])


@contextlib.contextmanager
def stop_signals_held(held: bool = True) -> Iterator[None]:
    """Hold stop signals in this block (``held=False``: let them through again, inside a held one).

    Why: an exception raised at an arbitrary bytecode can break a library's own bookkeeping.
    Optuna's ``_run_trial`` tolerates an interrupted objective but not one raised while it tells
    the storage (it then fails with UnboundLocalError and may leave the trial RUNNING). The study
    holds signals around ``optimize`` and lets them through only while a trial does its work; a
    signal held meanwhile is raised at the next allowed point.
    """
    saved = _stop["held"]
    _stop["held"] = 1 if held else 0
    try:
        if not held:
            raise_pending_stop()
        yield
    finally:
        _stop["held"] = saved
    if not saved:
        raise_pending_stop()


def _register_envs() -> None:
    """Register ``sdrl/Surrogate-v0`` with gymnasium (lazily imported: ``sdrl_bench.surrogate.env``)."""
    import gymnasium

    if "sdrl/Surrogate-v0" not in gymnasium.registry:
        # No max_episode_steps: the surrogate truncates at its spec's limit itself.
        gymnasium.register(id="sdrl/Surrogate-v0", entry_point="sdrl_bench.surrogate.env:SurrogateEnv")


_register_envs()
