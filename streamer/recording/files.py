"""The job service's recordings on disk: one MCAP file per job beside the journal, with retention.

Layout: `<journal dir>/<journal stem>.recordings/<job_id>.mcap`; job ids (1-64 of [A-Za-z0-9_.-], never
"." or "..") are safe file names. Retention (`RecordingRetention`): after each recording the oldest are
deleted down to `max_count` files and `max_bytes`, but the newest is always kept.
"""

from __future__ import annotations

import contextlib
import os
import re
from dataclasses import dataclass
from pathlib import Path

from streamer.recording.model import JobRecording, RecordingError

SUFFIX = ".mcap"
DEFAULT_MAX_COUNT = 200
DEFAULT_MAX_BYTES = 1 << 30  # 1 GiB
_JOB_ID = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")


@dataclass(frozen=True)
class RecordingRetention:
    """How many recordings the service keeps: at most `max_count` files and `max_bytes` in total.

    Defaults: 200 recordings, 1 GiB (the demo's 6-axis, 3.7 s job at a 10 ms SYNC takes 0.4 MB, most
    of it the CAN frames, so 200 jobs of a minute stay within the byte limit)."""

    max_count: int = DEFAULT_MAX_COUNT
    max_bytes: int = DEFAULT_MAX_BYTES

    def __post_init__(self) -> None:
        if isinstance(self.max_count, bool) or not isinstance(self.max_count, int) or self.max_count < 1:
            raise RecordingError("CONFIG", f"recordings max_count must be an integer >= 1, got {self.max_count!r}",
                                 "max_count")
        if isinstance(self.max_bytes, bool) or not isinstance(self.max_bytes, int) or self.max_bytes < 1:
            raise RecordingError("CONFIG", f"recordings max_bytes must be an integer >= 1, got {self.max_bytes!r}",
                                 "max_bytes")


def default_recordings_dir(journal: str | os.PathLike[str]) -> Path:
    """`<journal dir>/<journal stem>.recordings` (demo.jobs.sqlite -> demo.jobs.recordings)."""
    p = Path(journal)
    return p.with_name(f"{p.stem}.recordings")


def check_job_id(job_id: str) -> str:
    if not isinstance(job_id, str) or not _JOB_ID.match(job_id) or job_id in (".", ".."):
        raise RecordingError("BAD_JOB_ID", f"job id {job_id!r} is not 1-64 characters of [A-Za-z0-9_.-]", "job_id")
    return job_id


@dataclass(frozen=True)
class SavedRecording:
    path: Path
    bytes: int
    messages: int
    deleted: tuple[str, ...]  # job ids whose recordings retention removed

    def info(self) -> dict[str, object]:
        return {"file": self.path.name, "bytes": self.bytes, "messages": self.messages}


class RecordingFiles:
    """One folder of `<job_id>.mcap` files with retention. Only the service writes; readers just read."""

    def __init__(self, directory: str | os.PathLike[str], retention: RecordingRetention | None = None):
        self.directory = Path(directory)
        self.retention = retention or RecordingRetention()

    def path(self, job_id: str) -> Path:
        return self.directory / f"{check_job_id(job_id)}{SUFFIX}"

    def find(self, job_id: str) -> Path | None:
        p = self.path(job_id)
        return p if p.is_file() else None

    def save(self, job_id: str, rec: JobRecording) -> SavedRecording:
        """Write the recording of `job_id` (atomically), then apply retention."""
        from streamer.recording.mcap_io import write_mcap

        path = self.path(job_id)
        messages = write_mcap(rec, path)
        size = path.stat().st_size
        deleted = self.prune(keep=path)
        return SavedRecording(path, size, messages, deleted)

    def files(self) -> list[Path]:
        """The recordings, oldest first."""
        if not self.directory.is_dir():
            return []
        found = []
        for p in self.directory.iterdir():
            if p.suffix == SUFFIX and p.is_file() and not p.name.startswith("."):
                try:
                    found.append((p.stat().st_mtime_ns, p.name, p))
                except FileNotFoundError:  # removed meanwhile
                    continue
        return [p for _, _, p in sorted(found)]

    def prune(self, keep: Path | None = None) -> tuple[str, ...]:
        files = self.files()
        sizes = {}
        for p in files:
            try:
                sizes[p] = p.stat().st_size
            except FileNotFoundError:
                sizes[p] = 0
        total = sum(sizes.values())
        count = len(files)
        deleted: list[str] = []
        for p in files:
            if count <= self.retention.max_count and total <= self.retention.max_bytes:
                break
            if keep is not None and p == keep:
                continue
            with contextlib.suppress(FileNotFoundError):
                p.unlink()
            count -= 1
            total -= sizes[p]
            deleted.append(p.stem)
        return tuple(deleted)
