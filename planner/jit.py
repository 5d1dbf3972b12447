"""Compiled kernels of the planner: numba's `njit` with the options every one of them uses.

Why compiled code: the planner's inner loops are sequential searches and dynamic programs (the
reachability passes of the time-optimal parametrisation, the greedy knot searches, the Viterbi pass over
knot values) whose steps depend on the previous one. In NumPy each step costs a few microseconds of
interpreter overhead whatever its size; compiled, the whole loop costs about what its arithmetic does
(planning a 7 s 6-axis path went from ~100 ms to a few ms, benchmarks/bench_planner.py).

- `cache=True`: the machine code is kept beside the module (`__pycache__`, or numba's cache directory
  where that is not writable), so only the first process on a machine compiles (once; about a minute on
  a busy 2-core machine, nearly all of it in the first plan, which reaches almost every kernel, so
  compiling only what the demo needs would not save much). `make test` compiles them first
  (`python -m planner.plan`, which reports each kernel as it is compiled: `compiling`), a service when it
  starts (planner.plan.warm_up). A machine's first `make demo` plans with the kernels interpreted
  (`NUMBA_DISABLE_JIT=1`: 2-4 s for the demo's job) and compiles them after it, so that motion shows
  within seconds of the install. The demo's child processes (bus/sim/process.py, bus/engine.py) import no
  kernel, so they never compile (tests/cli/test_first_run.py).
- `nogil=True`: a kernel releases the GIL, so planning on one thread does not stall the streaming
  thread's SYNC handling (DEVELOPERS.md: a busy Python thread in the same process raised its jitter
  from 0.6 to 6 ms).
- `error_model="numpy"`: a division by zero gives inf or nan as in NumPy, and no check per division.

`NUMBA_DISABLE_JIT=1` runs every kernel as plain Python (slow, but debuggable and covered by tracing).

The memory of a plan: a plan allocates and frees a few MB of arrays (every ms of every axis, a few times
per repair round). glibc returns the freed top of its heap to the system and maps it in again for the
next arrays, a page fault per 4 kB: a quarter of a 20-waypoint plan's time (15 -> 11 ms with the pages
kept, measured). `keep_heap` (called by planner.plan.warm_up, which a service or a benchmark calls
once) asks glibc to keep 64 MB of freed heap for reuse; elsewhere it does nothing.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar, cast

from numba import njit
from numba.core import event

F = TypeVar("F", bound=Callable[..., Any])

KERNELS: list[Any] = []  # every kernel of the planner, as its modules are imported (numba dispatchers)


def kernel(fn: F) -> F:
    """`fn` compiled (see the module docstring)."""
    compiled = njit(cache=True, nogil=True, error_model="numpy")(fn)
    KERNELS.append(compiled)
    return cast(F, compiled)


def kernel_name(dispatcher: Any) -> str:
    """`module.function` of a kernel, without the `planner.` prefix: "topp._solve"."""
    fn = dispatcher.py_func
    return f"{fn.__module__.removeprefix('planner.')}.{fn.__qualname__}"


class _CompileListener(event.Listener):
    def __init__(self, done: Callable[[str], None]) -> None:
        self._done = done

    def on_start(self, ev: Any) -> None:
        pass

    def on_end(self, ev: Any) -> None:
        dispatcher = ev.data["dispatcher"]
        if any(dispatcher is k for k in KERNELS):
            self._done(kernel_name(dispatcher))


@contextmanager
def compiling(done: Callable[[str], None]) -> Iterator[None]:
    """Calls `done(name)` each time one of the planner's kernels has been compiled (not when it was loaded from
    the cache) while in the block: numba's compile events, which fire in the compiling thread."""
    listener = _CompileListener(done)
    event.register("numba:compile", listener)  # type: ignore[no-untyped-call]
    try:
        yield
    finally:
        event.unregister("numba:compile", listener)  # type: ignore[no-untyped-call]


_M_TOP_PAD = -2  # glibc malloc.h
KEEP_HEAP_BYTES = 64 << 20


def keep_heap() -> bool:
    """Keep `KEEP_HEAP_BYTES` of freed heap in this process for the next plan (glibc's M_TOP_PAD; see the
    module docstring). False where the C library has no mallopt (not glibc)."""
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c"))
        return bool(libc.mallopt(_M_TOP_PAD, KEEP_HEAP_BYTES))
    except (OSError, AttributeError):
        return False

