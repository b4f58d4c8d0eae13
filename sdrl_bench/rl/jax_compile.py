"""JAX's compiles for the compiled agents (``rl.jax_agent.JaxPPO``, ``rl.jax_sac_agent.JaxSAC``)
and the programs the benchmarks and studies compile: JAX's persistent compilation cache and the
count of programs loaded from it (``use_compilation_cache``, ``cache_hits``), the lowering cache
beside it (``compile_program``, ``lowering_key``), and the threads of XLA's CPU pool
(``cpu_pool_threads``, ``size_cpu_pool``). Process-wide settings: the CLI calls them once, before
anything creates JAX's backend (``cli.train``)."""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from sdrl_bench.rl import jax_nets

OFF_CPU_PARITY = ("CI tests the compiled step and agents on the CPU only; on an H200 (jax 0.11.2) the jitted "
                  "SINDy steps of 5 built-in envs matched ModelEnv's (at most 1.5e-12), the NN steps to their CPU "
                  "tolerances, and the agents' updates SB3's (the swing-up not run there); no agent was trained "
                  "there beyond the tests' budgets (docs/compiled.md, 'On a GPU')")
"""What was measured off the CPU (the tests marked ``jax``, run on an H200 on 2026-11-30), quoted by
``backend_note`` where a run is about to train there."""


def backend_note(backend: str) -> str | None:
    """None where JAX's default backend is the CPU, where the compiled agents' step is tested;
    else one line for the run's log: they train on ``backend``, what that changes, and how to stay
    on the CPU. Hand-written: jax says where it runs, not what our tests covered."""
    if backend == "cpu":
        return None
    return (f"JAX's default backend is {backend}: the compiled agents train there; {OFF_CPU_PARITY}. "
            "JAX_PLATFORMS=cpu keeps them on the CPU")


def use_compilation_cache(path: str | Path) -> None:
    """JAX's persistent compilation cache in ``path`` (config ``jax_cache_dir``), for every
    compiled program however short its compile: a program compiled before (the update of the same
    recipe; a rollout over the same model, e.g. a rerun) loads from disk instead of compiling.
    Measured on MountainCar's fast pack: 3.3 s cold, 0.4 s cached. ``compile_wall_seconds`` is
    what a run spent, cached or not.

    The XLA caches that JAX would otherwise keep under ``path`` as well (GPU kernels and
    autotuning: ``jax_persistent_cache_enable_xla_caches``) are off, because their paths enter
    every program's cache key: a cache copied or moved with its store then missed every program.
    Measured: LunarLander's terrain programs loaded from the same folder in 0.82 s, and compiled
    cold (7.0 s) from a copy of it elsewhere. These programs run on the CPU, where those caches
    do nothing. The lowering cache (``compile_program``) lives in its ``lowered`` folder."""
    jax, _, _ = jax_nets.modules()
    Path(path).mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(Path(path).resolve()))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    jax.config.update("jax_persistent_cache_enable_xla_caches", "none")


_CACHE_HIT = "/jax/compilation_cache/cache_hits"
_cache = {"hits": 0, "listening": False}
"""Programs this process loaded from JAX's persistent compilation cache, and whether the listener
that counts them is registered (``cache_hits``)."""


def _count_cache_hit(event: str, **_: Any) -> None:
    if event == _CACHE_HIT:
        _cache["hits"] += 1


def cache_hits() -> int:
    """Programs this process has loaded from the persistent compilation cache so far (JAX's
    ``/jax/compilation_cache/cache_hits`` monitoring event; its listener is registered on the
    first call)."""
    if not _cache["listening"]:
        import jax.monitoring  # noqa: PLC0415

        jax.monitoring.register_event_listener(_count_cache_hit)
        _cache["listening"] = True
    return int(_cache["hits"])


LOWERED = "lowered"
"""The folder, inside JAX's persistent compilation cache, of the lowering cache
(``compile_program``): one serialized ``jax.export.Exported`` per program."""
_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")
_lowering = {"off": False}
"""Whether this process found jax.export's serialization missing and turned the lowering cache
off, with one warning (``compile_program``)."""


def _constants(jaxpr: Any, out: list) -> list:
    """Every constant a (closed) jaxpr holds, its nested ones included, in a fixed order: a
    constant captured inside a nested ``jit``, ``scan`` or ``cond`` stays in that inner closed
    jaxpr, and the printed jaxpr names it without its value."""
    if hasattr(jaxpr, "consts") and hasattr(jaxpr, "jaxpr"):
        out.extend(jaxpr.consts)
        jaxpr = jaxpr.jaxpr
    for eqn in jaxpr.eqns:
        for value in eqn.params.values():
            for x in value if isinstance(value, (tuple, list)) else (value,):
                if hasattr(x, "eqns") or (hasattr(x, "consts") and hasattr(x, "jaxpr")):
                    _constants(x, out)
    return out


def lowering_key(traced: Any, options: dict[str, Any]) -> str:
    """The lowering cache's key of a traced program (``jax.jit(f).trace(*args)``): a SHA-256 of
    what its lowering depends on: the program's jaxpr as text (every equation with its shapes,
    dtypes, parameters and literals; memory addresses in callables' names taken out: they differ
    from process to process and lowering does not read those callables), the values of its
    captured constants (those of nested jaxprs too, ``_constants``), the layout of its arguments, jax's and jaxlib's versions, the backend,
    every jax configuration value (some change a lowering without showing in the jaxpr, e.g. the
    PRNG's implementation) but the cache folder's path, and the compiler options."""
    import jax  # noqa: PLC0415
    import jaxlib  # noqa: PLC0415

    h = hashlib.sha256(_ADDRESS.sub("", str(traced.jaxpr)).encode())
    for c in _constants(traced.jaxpr, []):
        dtype = getattr(c, "dtype", None)
        a = np.asarray(jax.random.key_data(c) if dtype is not None and jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key) else c)
        h.update(repr((a.dtype.str, a.shape)).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    config = sorted((k, repr(v)) for k, v in jax.config.values.items() if k != "jax_compilation_cache_dir")
    h.update(repr((str(traced.in_tree), jax.__version__, jaxlib.__version__, jax.default_backend(), config,
                   sorted(options.items()))).encode())
    return h.hexdigest()


def compile_program(fn: Any, args: tuple, options: dict[str, Any]) -> tuple[Any, bool]:
    """``fn`` (a ``jax.jit`` function) compiled for ``args`` with XLA ``options``: (a callable
    taking and returning what ``fn`` does, whether its lowering came from the lowering cache).

    With JAX's persistent compilation cache on (``use_compilation_cache``), a program's lowering
    is kept beside it: the program is traced, and its lowering is loaded from
    ``<cache>/lowered/<lowering_key>`` when there, else exported (``jax.export``) and saved
    there; the exported program is then compiled, from JAX's cache when compiled before. Without
    the persistent cache, ``fn`` is lowered and compiled as usual.

    Hand-written, and why: JAX's persistent cache keys a program on its lowered module, so a
    fresh process traces and lowers every program before it can load the compiled code; JAX keeps
    its lowerings within a process only. ``jax.export`` serializes a lowering; what this adds is
    the key, made from the traced program (``lowering_key``). Measured on LunarLander's terrain
    pack in a fresh process, this 2-core machine (2026-11-27): the three programs (the episodes'
    start, the rollout, the update) took 0.69 s to trace, lower and load from JAX's cache, and
    0.50 s with their lowerings from this cache (of it, tracing 0.21 s and JAX's cache 0.21 s).
    A program ``jax.export`` cannot hold (a host callback) is lowered and compiled as usual, and
    so is every program, with one warning, where jax.export's serialization is missing
    (``flatbuffers``, which the ``jax`` extra installs)."""
    import jax  # noqa: PLC0415
    from jax import export  # noqa: PLC0415

    traced = fn.trace(*args)

    def direct() -> tuple[Any, bool]:
        return traced.lower().compile(compiler_options=options), False

    folder = jax.config.jax_compilation_cache_dir
    if not folder or _lowering["off"]:  # no persistent cache, or no serialization (warned once)
        return direct()
    leaves, in_tree = jax.tree_util.tree_flatten(args)
    out_tree = jax.tree_util.tree_structure(traced.out_info)
    path = Path(folder) / LOWERED / lowering_key(traced, options)
    exported = None
    if path.is_file():
        try:
            exported = export.deserialize(bytearray(path.read_bytes()))
        except Exception:  # noqa: BLE001 - unreadable (cut short, another jax): lowered again and replaced
            exported = None
    hit = exported is not None
    if exported is None:
        def flat(*xs: Any) -> list:
            return jax.tree_util.tree_leaves(fn(*jax.tree_util.tree_unflatten(in_tree, xs)))

        try:
            exported = export.export(jax.jit(flat))(*leaves)
            blob = exported.serialize()
        except ImportError as exc:  # jax.export's serialization needs flatbuffers (the jax extra has it)
            warnings.warn(f"the lowering cache is off: {exc}", stacklevel=3)
            _lowering["off"] = True  # the later programs go straight to the direct path
            return direct()
        except Exception:  # noqa: BLE001 - a program export cannot hold: compiled as it is
            return direct()
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_bytes(blob)
            os.replace(tmp, path)  # whole or absent, for a concurrent reader
        except OSError as exc:  # a full or read-only cache: this run compiles all the same
            warnings.warn(f"the lowering cache could not keep {path.name[:12]}...: {exc}", stacklevel=3)
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
    exe = jax.jit(exported.call).lower(*leaves).compile(compiler_options=options)

    def run(*a: Any) -> Any:
        return jax.tree_util.tree_unflatten(out_tree, exe(*jax.tree_util.tree_leaves(a)))

    return run, hit


POOL_THREAD_NAME = "tf_XLAEigen"
"""The name XLA's CPU client gives the threads of its pool (Linux's ``/proc/self/task/*/comm``)."""


def cpu_pool_threads() -> int | None:
    """Threads in XLA's CPU pool now: 0 before JAX's CPU backend exists, None where they cannot be
    read (no ``/proc``)."""
    try:
        tasks = os.listdir("/proc/self/task")
    except OSError:
        return None
    n = 0
    for tid in tasks:
        try:
            with open(f"/proc/self/task/{tid}/comm") as f:
                n += f.read().strip() == POOL_THREAD_NAME
        except OSError:  # a thread that ended meanwhile
            continue
    return n


def size_cpu_pool(threads: int, who: str = "sdrl_bench.rl.jax_compile") -> int | None:
    """Create JAX's CPU backend with ``threads`` threads in XLA's CPU pool (config ``jax_threads``;
    0: XLA's default, one per CPU the process may run on), as ``torch_threads`` sets torch's.
    Returns the pool's size (``cpu_pool_threads``); ``who`` names the caller in the install hint
    when jax is missing (an agent's ``LABEL``).

    Hand-written, and why: jax (0.10) has no setting for the pool (``make_cpu_client`` takes no
    thread count); XLA sizes it to the CPUs the creating thread may run on. So the creating
    thread's CPU affinity is narrowed to ``threads`` CPUs while the backend is created, then every
    thread of the process gets back the affinity it had, and the pool's new threads the process's:
    the pool has ``threads`` threads, none of them pinned. Measured on this 2-core machine, terrain
    LunarLander's fast pack (64 envs x 128 steps, minibatches of 256): one compiled iteration,
    rollout and update, took 53-56 ms with XLA's two threads and 41-43 ms with one. The programs'
    products and fusions are small; handing them between two threads costs more than the second
    core gives. Only on Linux (``os.sched_setaffinity``); elsewhere, or once the backend exists
    (a sweep's later jobs), the pool stays as it is, with a warning if it differs. Where JAX's
    default backend is not the CPU (a GPU build of jax), a warning says so (``backend_note``)."""
    jax, _, _ = jax_nets.modules(who)
    size = _size_pool(jax, threads)
    note = backend_note(jax.default_backend())  # the backends exist: jax.devices('cpu') made them all
    if note:
        warnings.warn(note, stacklevel=2)
    return size


def _size_pool(jax: Any, threads: int) -> int | None:
    """``size_cpu_pool``'s work: the CPU backend created with ``threads`` pool threads."""
    have = cpu_pool_threads()
    if threads == 0 or have is None or not hasattr(os, "sched_setaffinity"):
        jax.devices("cpu")
        return cpu_pool_threads()
    if have:  # the backend exists: its pool is fixed for the process's life
        if have != threads:
            warnings.warn(f"jax_threads={threads}: JAX's CPU backend already exists in this process with "
                          f"{have} pool threads; they stay", stacklevel=3)
        return have
    full = os.sched_getaffinity(0)
    before = {int(t): os.sched_getaffinity(int(t)) for t in os.listdir("/proc/self/task")}
    try:
        os.sched_setaffinity(0, set(sorted(full)[:threads]))
        jax.devices("cpu")
    finally:
        for tid in os.listdir("/proc/self/task"):
            try:
                os.sched_setaffinity(int(tid), before.get(int(tid), full))
            except OSError:  # a thread that ended meanwhile
                continue
    return cpu_pool_threads()
