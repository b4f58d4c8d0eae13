"""A stop signal that lands inside a garbage-collector callback is not lost.

Python prints and drops an exception raised in a ``gc.callbacks`` function ("Exception ignored
in ..."), so a ``Terminated`` raised there by the stop-signal handler would vanish and the run
go on. jax registers such a callback, and pysindy imports jax wherever jax is installed. The
handler sees the callback's frame and delivers the signal again a moment later. A real SIGTERM,
in a child process."""

from __future__ import annotations

import subprocess
import sys
import textwrap

CHILD = textwrap.dedent("""
    import gc, os, signal, time
    from sdrl_bench import Terminated, raise_on_stop_signals

    raise_on_stop_signals()
    sent = []

    def callback(phase, info):  # the signal arrives while this runs
        if not sent:
            sent.append(1)
            os.kill(os.getpid(), signal.SIGTERM)
            t = time.monotonic()
            while time.monotonic() - t < 0.3:
                pass

    gc.callbacks.append(callback)
    try:
        gc.collect()
        t = time.monotonic()
        while time.monotonic() - t < 10:
            time.sleep(0.01)
        print("survived")
    except Terminated as exc:
        print("terminated", exc.signum, "inside the callback:", len(sent))
""")


def test_a_sigterm_inside_a_gc_callback_still_stops_the_process():
    out = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, timeout=60)
    assert out.stdout.strip() == "terminated 15 inside the callback: 1", (out.stdout, out.stderr)
    assert "Exception ignored" not in out.stderr
