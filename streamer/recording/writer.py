"""Building and writing recordings in a separate, low-priority process (for the job service).

Theory of operation. Between jobs the service's process still runs SYNC (and with `--sim` the simulated
drives); building a recording is a few hundred ms of pure Python that would hold the GIL and delay SYNC
(docs/recording.md measures it). So the service hands the job's raw material (`RecordingInputs`: compact
arrays, the plan's demand, the report) to one worker process, spawned (no fork of a threaded process) at
nice 10, which builds the `JobRecording` and writes the MCAP file while the executor waits without the
GIL. The worker starts with the service and is replaced if it died; `in_process=True` does the work on
the calling thread (for tools with no SYNC to protect). The worker ends with the service's process even
when that one is killed (`_watch_parent`): a pool worker holds both ends of its call queue, so it would
never see the queue close, and lived on idle after every killed service.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import multiprocessing
import os
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from streamer.recording.files import RecordingFiles, SavedRecording
from streamer.recording.model import JobRecording, build_recording

WRITE_TIMEOUT_S = 300.0
WORKER_NICE = 10


@dataclass(frozen=True)
class PlanView:
    """What `build_recording` needs of a `PvtTrajectory`, as plain picklable data."""

    axis_names: tuple[str, ...]
    node_ids: tuple[int, ...]
    counts_per_unit: tuple[float, ...]
    tolerance_counts: int
    duration_ms: int
    demand_per_ms: Any  # numpy int array (n_axes, duration_ms + 1): `PvtTrajectory.planned_demand()`

    @classmethod
    def of(cls, traj: Any) -> PlanView:
        return cls(tuple(str(n) for n in traj.axis_names), tuple(int(n) for n in traj.node_ids),
                   tuple(float(c) for c in traj.counts_per_unit), int(traj.tolerance_counts),
                   int(traj.duration_ms), traj.planned_demand())

    def planned_demand(self) -> Any:
        return self.demand_per_ms


@dataclass(frozen=True)
class RecordingInputs:
    """A finished job's raw material for its recording (built where it is written)."""

    plan: PlanView
    trace: Any  # streamer.runtime.trace.JobTrace (record=True)
    report: Mapping[str, Any]
    first_sync: int
    start_sync: int | None
    sync_period_ms: int
    cell: str = ""
    epoch_s: float | None = None
    underflow_watermark: int | None = None
    overflow_watermark: int | None = None
    drive: Any = None  # streamer.recording.drive.DriveRecording: the drives' own recorders (a `record` section)
    # per node, the TPDO2 samples at the SYNC the core attributed them to (`JobReport.feedback`); None: by arrival
    feedback: Mapping[int, Any] | None = None

    def build(self, job_id: str = "", cell: str | None = None) -> JobRecording:
        return build_recording(self.plan, self.trace, self.report, first_sync=self.first_sync,
                               start_sync=self.start_sync, sync_period_ms=self.sync_period_ms, job_id=job_id,
                               cell=self.cell if cell is None else cell, epoch_s=self.epoch_s,
                               underflow_watermark=self.underflow_watermark,
                               overflow_watermark=self.overflow_watermark, drive=self.drive,
                               feedback=self.feedback)


def as_recording(item: JobRecording | RecordingInputs, job_id: str, cell: str) -> JobRecording:
    if isinstance(item, RecordingInputs):
        return item.build(job_id, cell)
    return replace(item, job_id=job_id, cell=cell)


PARENT_POLL_S = 0.5  # how often the worker looks whether the process that started it still runs


def _start_worker(parent: int) -> None:
    with contextlib.suppress(OSError):  # not allowed here: the worker still has its own GIL
        os.nice(WORKER_NICE)
    threading.Thread(target=_watch_parent, args=(parent,), name="recording-writer-parent", daemon=True).start()


def _watch_parent(parent: int) -> None:
    """Exit the worker once its parent is gone (reparented: getppid changes). Polling, not PR_SET_PDEATHSIG:
    portable, and half a second is soon enough for an idle process."""
    while os.getppid() == parent:
        time.sleep(PARENT_POLL_S)
    os._exit(0)


def _warm_up() -> int:
    import numpy  # noqa: F401  (the plan's demand arrives as a numpy array)

    import streamer.recording.mcap_io  # noqa: F401

    return os.getpid()


def _write(path: str, item: JobRecording | RecordingInputs, job_id: str, cell: str) -> tuple[int, int]:
    """In the worker: build and write; (messages, the worker's pid)."""
    from streamer.recording.mcap_io import write_mcap

    messages = write_mcap(as_recording(item, job_id, cell), Path(path))
    return messages, os.getpid()


class RecordingWriter:
    """Writes each job's recording into `files`, in a worker process (see the module docstring)."""

    def __init__(self, files: RecordingFiles, *, in_process: bool = False):
        self.files = files
        self.in_process = in_process
        self.last_writer_pid: int | None = None
        self._pool: concurrent.futures.ProcessPoolExecutor | None = None

    def _executor(self) -> concurrent.futures.ProcessPoolExecutor:
        if self._pool is None:
            self._pool = concurrent.futures.ProcessPoolExecutor(
                max_workers=1, mp_context=multiprocessing.get_context("spawn"), initializer=_start_worker,
                initargs=(os.getpid(),))
        return self._pool

    def start(self) -> None:
        """Start the worker and let it import what it needs now (about a second of CPU), so that burst
        does not land between two jobs."""
        if not self.in_process:
            self._executor().submit(_warm_up).result(timeout=WRITE_TIMEOUT_S)

    def save(self, job_id: str, item: JobRecording | RecordingInputs, *, cell: str) -> SavedRecording:
        path = self.files.path(job_id)  # checks the job id before anything is sent
        path.parent.mkdir(parents=True, exist_ok=True)
        if self.in_process:
            messages, pid = _write(str(path), item, job_id, cell)
        else:
            try:
                messages, pid = self._executor().submit(_write, str(path), item, job_id, cell).result(
                    timeout=WRITE_TIMEOUT_S)
            except concurrent.futures.process.BrokenProcessPool:
                self._drop_pool()  # the worker died (killed, out of memory): a new one next time
                raise
        self.last_writer_pid = pid
        deleted = self.files.prune(keep=path)
        return SavedRecording(path, path.stat().st_size, messages, deleted)

    def _drop_pool(self) -> None:
        pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)

    def close(self) -> None:
        pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)

