"""Compiled kernels of the planner: numba's `njit` with the options every one of them uses.

The planner's inner loops are sequential (each step depends on the last), where NumPy pays microseconds
of interpreter per step. `cache=True`: only a machine's first process compiles (a first `make demo` plans
interpreted and compiles after). `nogil=True`: planning does not stall the streaming thread.
`error_model="numpy"`: no check per division. `keep_heap` keeps freed heap for the next plan's arrays.
`NUMBA_DISABLE_JIT=1` runs everything as Python. docs/formats.md ("path") has the costs.
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

