"""Compiled kernels of the planner: numba's `njit` with the options every one of them uses.

Why compiled code: the planner's inner loops are sequential searches and dynamic programs (the
reachability passes of the time-optimal parametrisation, the greedy knot searches, the Viterbi pass over
knot values) whose steps depend on the previous one. In NumPy each step costs a few microseconds of
interpreter overhead whatever its size; compiled, the whole loop costs about what its arithmetic does
(planning a 7 s 6-axis path went from ~100 ms to a few ms, benchmarks/bench_planner.py).

- `cache=True`: the machine code is kept beside the module (`__pycache__`, or numba's cache directory
  where that is not writable), so only the first process on a machine compiles (once; about 2 minutes on
  a busy 2-core machine, nearly all of it in the first plan, which reaches almost every kernel, so
  compiling only what the demo needs would not save much; `make`'s install step runs
  `planner.plan.warm_up`, a service runs it when it starts). The demo's child processes (bus/sim/process.py,
  bus/engine.py) import no kernel, so they never compile (tests/cli/test_first_run.py).
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

from collections.abc import Callable
from typing import Any, TypeVar, cast

from numba import njit

F = TypeVar("F", bound=Callable[..., Any])


def kernel(fn: F) -> F:
    """`fn` compiled (see the module docstring)."""
    return cast(F, njit(cache=True, nogil=True, error_model="numpy")(fn))


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
