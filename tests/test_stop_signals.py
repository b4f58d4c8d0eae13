"""A stop signal that lands where Python cannot raise is not lost.

Python prints and drops an exception raised in a ``gc.callbacks`` function, a weakref callback
or a ``__del__`` ("Exception ignored in ..."), so a ``Terminated`` raised there by the
stop-signal handler would vanish and the run go on. jax registers a gc callback (pysindy imports
jax wherever jax is installed); torch, SQLAlchemy (under mlflow) and the standard library use
weakref callbacks (a SIGTERM landing in a ``WeakValueDictionary``'s once left a training run
going past the CI test's minute). The hook that receives such exceptions delivers the signal again a moment
later. A real SIGTERM, in a child process, landing inside each kind of callback."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

CHILD = textwrap.dedent("""
    import gc, os, signal, sys, time, weakref
    from sdrl_bench import Terminated, raise_on_stop_signals

    raise_on_stop_signals()
    sent = []

    def land():  # the signal arrives while a callback runs
        if not sent:
            sent.append(1)
            os.kill(os.getpid(), signal.SIGTERM)
            t = time.monotonic()
            while time.monotonic() - t < 0.3:
                pass

    class Thing:
        pass

    class Finalized:
        def __del__(self):
            land()

    where = sys.argv[1]
    try:
        if where == "gc":
            gc.callbacks.append(lambda phase, info: land())
            gc.collect()
        elif where == "weakref":
            thing = Thing()
            ref = weakref.ref(thing, lambda r: land())
            del thing
        elif where == "del":
            Finalized()
        t = time.monotonic()
        while time.monotonic() - t < 10:
            time.sleep(0.01)
        print("survived")
    except Terminated as exc:
        print("terminated", exc.signum, "inside the callback:", len(sent))
""")


@pytest.mark.parametrize("where", ["gc", "weakref", "del"])
def test_a_sigterm_inside_a_callback_python_cannot_raise_from_still_stops_the_process(where):
    out = subprocess.run([sys.executable, "-c", CHILD, where], capture_output=True, text=True, timeout=60)
    assert out.stdout.strip() == "terminated 15 inside the callback: 1", (out.stdout, out.stderr)
    assert "Exception ignored" not in out.stderr


def test_the_last_word_of_a_stop_says_whether_a_run_was_made(tmp_path, capsys):
    """A command stopped before its run existed (while it loaded or fitted) said "the run ended
    KILLED" of a run that never was; it now says so, and names the run when one was made (this
    process's own, ended KILLED if the signal caught it RUNNING)."""
    import signal

    from omegaconf import OmegaConf

    from sdrl_bench import tracking
    from sdrl_bench.cli.build import exit_after_stop_signal

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    cfg = OmegaConf.create({"tracking": {"uri": uri, "experiment": "stops"}})
    with pytest.raises(SystemExit) as exc:
        exit_after_stop_signal(cfg, signal.SIGTERM, "sdrl-bench", "the run ended KILLED")
    assert exc.value.code == 128 + signal.SIGTERM
    assert capsys.readouterr().err == "sdrl-bench: stopped by SIGTERM; before its run was made (nothing to resume)\n"
    exp = tracking.ensure_experiment(uri, "stops")
    run = tracking.mlflow_client(uri).create_run(exp, tags=tracking.process_tags())  # caught mid-creation: RUNNING
    with pytest.raises(SystemExit):
        exit_after_stop_signal(cfg, signal.SIGINT, "sdrl-bench", "the run ended KILLED")
    assert capsys.readouterr().err == "sdrl-bench: stopped by SIGINT; the run ended KILLED\n"
    assert tracking.mlflow_client(uri).get_run(run.info.run_id).info.status == "KILLED"
