"""Spill: where an endless job's per-SYNC columns keep their old samples (streamer/core/spool.py).

`temp_store(typecode)` is a `BlockStore` on an anonymous temporary file (tempfile.TemporaryFile: no name
on disk, removed when it is closed or collected with its column): blocks are appended at its end and read
back by sample index. The runtimes give it to the core (`Coordinator(store=...)`, used only for an
open-ended plan) and to the `JobTrace` of an open-ended job, so that an hour of motion holds one block per
column in memory and the report and recording still read every sample. Pickled (the service hands a job's
trace to its recording process), a store carries its samples and unpickles into a temporary file there.
"""

from __future__ import annotations

import tempfile
from array import array
from typing import IO


class TempFileStore:
    """A column's spilled samples in a temporary file (see the module docstring)."""

    def __init__(self, typecode: str) -> None:
        self.typecode = typecode
        self.itemsize = array(typecode).itemsize
        self._file: IO[bytes] = tempfile.TemporaryFile(prefix="pvt-spill-")  # noqa: SIM115 (lives with the column)
        self._size = 0  # samples written

    def write(self, block: array[int] | array[float]) -> None:
        if block.typecode != self.typecode:
            raise TypeError(f"a {block.typecode!r} block for a {self.typecode!r} store")
        self._file.seek(self._size * self.itemsize)
        block.tofile(self._file)
        self._size += len(block)

    def read(self, start: int, count: int) -> array[int] | array[float]:
        if start < 0 or count < 0 or start + count > self._size:
            raise IndexError(f"samples {start}..{start + count - 1} of a store of {self._size}")
        out: array[int] | array[float] = array(self.typecode)
        self._file.seek(start * self.itemsize)
        out.frombytes(self._file.read(count * self.itemsize))
        return out

    def close(self) -> None:
        self._file.close()

    # a finished job's trace and feedback logs are pickled to the process that writes its recording
    # (streamer/recording/writer.py): the samples travel, and land in a temporary file of that process
    def __getstate__(self) -> dict[str, object]:
        self._file.seek(0)
        return {"typecode": self.typecode, "data": self._file.read(self._size * self.itemsize)}

    def __setstate__(self, state: dict[str, object]) -> None:
        typecode, data = state["typecode"], state["data"]
        assert isinstance(typecode, str) and isinstance(data, bytes)
        self.__init__(typecode)  # type: ignore[misc]
        self._file.write(data)
        self._size = len(data) // self.itemsize


def temp_store(typecode: str) -> TempFileStore:
    """An empty `TempFileStore` (a `streamer.core.spool.StoreFactory`)."""
    return TempFileStore(typecode)
