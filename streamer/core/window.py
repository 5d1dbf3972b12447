"""Window: a list indexed from the start of a stream that holds only its newer part.

An endless job's records, frames and segment ends are addressed by their index from the stream's start
for the whole job. A `Window` keeps that addressing while its owner drops a prefix never read again:
`len()` is the whole length, `w[i]` and slices take stream indices (i >= `base`); reading a dropped index
raises `IndexError` naming index and base, never a wrong item. Append, truncate and drop are O(new items).
"""

from __future__ import annotations

from bisect import bisect_right as _bisect_right
from collections.abc import Iterable, Iterator, Sequence
from typing import Generic, TypeVar, overload

T = TypeVar("T")


class Window(Sequence[T], Generic[T]):
    """Items [base, len) of a stream; items [0, base) were dropped (see the module docstring)."""

    __slots__ = ("_base", "_items", "_last_dropped")

    def __init__(self, items: Iterable[T] = ()) -> None:
        self._base = 0
        self._items: list[T] = list(items)
        self._last_dropped: T | None = None  # item base - 1 (what `bisect_right` compares against)

    @property
    def base(self) -> int:
        """Stream index of the first item held (items before it were dropped)."""
        return self._base

    @property
    def held(self) -> int:
        """Items held in memory."""
        return len(self._items)

    def __len__(self) -> int:
        return self._base + len(self._items)

    def _index(self, i: int) -> int:
        n = len(self)
        j = i + n if i < 0 else i
        if j >= n or j < 0:
            raise IndexError(f"index {i} out of a stream of {n}")
        if j < self._base:
            raise IndexError(f"index {i} was dropped (the window holds {self._base}..{n - 1})")
        return j - self._base

    @overload
    def __getitem__(self, i: int) -> T: ...

    @overload
    def __getitem__(self, i: slice) -> list[T]: ...

    def __getitem__(self, i: int | slice) -> T | list[T]:
        if isinstance(i, slice):
            start, stop, step = i.indices(len(self))
            if step != 1:
                raise ValueError(f"a Window slice takes step 1, not {step}")
            if stop <= start:
                return []
            if start < self._base:
                raise IndexError(f"slice from {start} reaches dropped items (the window holds {self._base}..)")
            return self._items[start - self._base:stop - self._base]
        return self._items[self._index(i)]

    def __iter__(self) -> Iterator[T]:
        if self._base:
            raise IndexError(f"iterating a Window whose first {self._base} items were dropped")
        return iter(self._items)

    def append(self, item: T) -> None:
        self._items.append(item)

    def extend(self, items: Iterable[T]) -> None:
        self._items.extend(items)

    def truncate(self, k: int) -> None:
        """Keep stream items [0, k) (k >= base): what a splice after index k keeps."""
        if k < self._base:
            raise IndexError(f"truncate at {k} reaches dropped items (the window holds {self._base}..)")
        del self._items[k - self._base:]

    def spliced(self, k: int, items: Iterable[T]) -> Window[T]:
        """A new window: this one's items [0, k) (k >= base) followed by `items` (what a splice at k makes),
        for trying a splice without changing this one. O(items held)."""
        if k < self._base:
            raise IndexError(f"splice at {k} reaches dropped items (the window holds {self._base}..)")
        out: Window[T] = Window(self._items[:k - self._base])
        out._base, out._last_dropped = self._base, self._last_dropped
        out.extend(items)
        return out

    def drop_before(self, k: int) -> int:
        """Drop stream items before index k (no-op where they are gone already); how many were dropped."""
        k = min(k, len(self))
        n = k - self._base
        if n <= 0:
            return 0
        self._last_dropped = self._items[n - 1]
        del self._items[:n]
        self._base = k
        return n


def bisect_right(w: Sequence[int], x: int) -> int:
    """`bisect.bisect_right` over a sorted `Window` (or list) in stream indices. A value below the last
    dropped item cannot be placed exactly: IndexError (the caller asked about time already forgotten)."""
    if isinstance(w, Window):
        base = w.base
        i = _bisect_right(w._items, x) + base
        last = w._last_dropped
        if i == base and base > 0 and last is not None and x < last:
            raise IndexError(f"value {x} falls before the window's held part (from index {base})")
        return i
    return _bisect_right(w, x)
