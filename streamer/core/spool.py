"""Column: an append-only column of per-SYNC numbers that an endless job keeps whole without holding it.

A `Column` keeps its newest block in memory and hands every full block to its `BlockStore` (given by the
runtime: streamer/runtime/trace.py `TempFileStore`), so memory stays flat however long the job runs while
reads see every sample. Without a store (every finite job) it is a plain in-memory array. int64 or float64.
"""

from __future__ import annotations

from array import array
from collections.abc import Callable, Iterator
from typing import Protocol, overload

BLOCK = 4096  # samples per block handed to the store (32 KiB)


class BlockStore(Protocol):
    """Where a column's old samples go: appended in blocks, read back by index or in order."""

    def write(self, block: array[int] | array[float]) -> None: ...

    def read(self, start: int, count: int) -> array[int] | array[float]: ...


StoreFactory = Callable[[str], BlockStore]  # typecode -> an empty store for one column


class Column:
    """Samples [0, len) of one per-SYNC quantity (see the module docstring)."""

    __slots__ = ("_block", "_store", "_stored", "_tail", "_typecode")

    def __init__(self, typecode: str = "q", store: StoreFactory | None = None, block: int = BLOCK) -> None:
        self._typecode = typecode
        self._tail: array[int] | array[float] = array(typecode)
        self._store = store(typecode) if store is not None else None
        self._stored = 0
        self._block = block

    @property
    def held(self) -> int:
        """Samples held in memory."""
        return len(self._tail)

    def append(self, value: int | float) -> None:
        self._tail.append(value)  # type: ignore[arg-type]
        if self._store is not None and len(self._tail) >= self._block:
            self._store.write(self._tail)
            self._stored += len(self._tail)
            self._tail = array(self._typecode)

    def __len__(self) -> int:
        return self._stored + len(self._tail)

    def __bool__(self) -> bool:
        return len(self) > 0

    @overload
    def __getitem__(self, i: int) -> int | float: ...

    @overload
    def __getitem__(self, i: slice) -> list[int | float]: ...

    def __getitem__(self, i: int | slice) -> int | float | list[int | float]:
        if isinstance(i, slice):  # a list, as slicing the list a finite job's trace keeps gives
            start, stop, step = i.indices(len(self))
            if step != 1:
                return [self[j] for j in range(start, stop, step)]
            if stop <= start:
                return []
            out: list[int | float] = []
            if start < self._stored:
                assert self._store is not None
                out.extend(self._store.read(start, min(stop, self._stored) - start))
            lo = max(start, self._stored) - self._stored
            out.extend(self._tail[lo:max(lo, stop - self._stored)])
            return out
        n = len(self)
        j = i + n if i < 0 else i
        if not 0 <= j < n:
            raise IndexError(f"sample {i} of a column of {n}")
        if j >= self._stored:
            return self._tail[j - self._stored]
        assert self._store is not None
        return self._store.read(j, 1)[0]

    def __iter__(self) -> Iterator[int | float]:
        if self._store is not None:
            for start in range(0, self._stored, self._block * 16):
                yield from self._store.read(start, min(self._block * 16, self._stored - start))
        yield from self._tail

    def array(self) -> array[int] | array[float]:
        """Every sample, in one in-memory array (for a reader that wants them all at once)."""
        if self._store is None:
            return array(self._typecode, self._tail)
        out: array[int] | array[float] = array(self._typecode)
        if self._stored:
            out.extend(self._store.read(0, self._stored))  # type: ignore[arg-type]
        out.extend(self._tail)  # type: ignore[arg-type]
        return out
