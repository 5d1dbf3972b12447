"""The job service keeps one recording per job beside its journal, with retention by count and size;
`pvt jobs show/export ID` find it from the journal. The real backend records a real job (slow test)."""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

from bus.cob import RPDO2_BASE
from planner.config import CellConfig
from planner.encoding.record import unpack
from streamer.api.backend import CancelToken, Emit, Planned
from streamer.api.client import MotionClient
from streamer.api.service import JobService, ServiceOptions
from streamer.api.store import JobStore
from streamer.api.zenoh_config import build_config
from streamer.cli import main as pvt
from streamer.recording.files import RecordingFiles, RecordingRetention, default_recordings_dir
from streamer.recording.mcap_io import read_mcap
from streamer.recording.model import AxisInfo, AxisSamples, Frames, JobRecording, RecordedEvent, RecordingError
from tests.api.conftest import free_port
from tests.api.fakes import FakeBackend, timed_job


def synthetic(n_samples: int = 50, frames: int = 0) -> JobRecording:
    s = AxisSamples()
    for k in range(n_samples):
        s.append(k, k * 0.01, {"planned": k, "actual": k, "demand": k, "following_error": 0, "fifo_fill": 8})
    return JobRecording(
        job_id="", cell="", result="done", sync_period_ms=10, first_sync=0, start_sync=2, epoch_s=1.7e9,
        axes=(AxisInfo("j1", 1, 100.0),), samples={"j1": s}, events=(RecordedEvent(0.02, 2, "start"),),
        frames=Frames([k * 1e-3 for k in range(frames)], [0x80] * frames, [0] * frames, [b""] * frames),
        report={"result": "done"},
    )


class RecordingFake(FakeBackend):
    """The fake backend plus a recording per executed job (or an error when `broken`)."""

    broken = False

    def execute(self, planned: Planned, emit: Emit, cancel: CancelToken) -> Any:
        report = super().execute(planned, emit, cancel)
        self._rec = synthetic()
        return report

    def take_recording(self) -> JobRecording | None:
        if self.broken:
            raise OSError("disk full")
        rec, self._rec = getattr(self, "_rec", None), None
        return rec


def test_retention_by_count_and_size(tmp_path: Path) -> None:
    files = RecordingFiles(tmp_path / "rec", RecordingRetention(max_count=3, max_bytes=10**9))
    for k in range(5):
        saved = files.save(f"job-{k}", synthetic())
        os.utime(saved.path, ns=(k * 10**9, k * 10**9))  # creation order, whatever the clock's resolution
        files.prune(keep=saved.path)
    assert [p.stem for p in files.files()] == ["job-2", "job-3", "job-4"]
    one = files.path("job-4").stat().st_size
    by_size = RecordingFiles(tmp_path / "rec", RecordingRetention(max_count=100, max_bytes=2 * one + one // 2))
    assert by_size.prune() == ("job-2",)
    big = by_size.save("big", synthetic(frames=20_000))  # alone larger than the byte limit: still kept
    assert big.bytes > by_size.retention.max_bytes
    assert [p.stem for p in by_size.files()] == ["big"] and set(big.deleted) == {"job-3", "job-4"}
    with pytest.raises(RecordingError) as err:
        files.path("../escape")
    assert err.value.code == "BAD_JOB_ID"
    with pytest.raises(RecordingError, match="max_count"):
        RecordingRetention(max_count=0)
    with pytest.raises(RecordingError, match="max_bytes"):
        RecordingRetention(max_bytes=True)
    assert default_recordings_dir("/x/demo.jobs.sqlite") == Path("/x/demo.jobs.recordings")


def test_writer_builds_from_the_inputs_and_checks_the_job_id(tmp_path: Path) -> None:
    from streamer import demo
    from streamer.recording.writer import PlanView, RecordingInputs, RecordingWriter
    from tests.recording.recording_kit import record_virtual

    cell, _job, traj = demo.prepare(axes=2)
    result, report, direct = record_virtual(cell, traj)
    inputs = RecordingInputs(PlanView.of(traj), result.trace, report, result.first_sync,
                             result.coordinator.start_sync, cell.sync_period_ms, cell=cell.name,
                             epoch_s=direct.epoch_s, underflow_watermark=cell.drive.underflow_warning,
                             overflow_watermark=cell.drive.overflow_warning)
    writer = RecordingWriter(RecordingFiles(tmp_path / "rec"), in_process=True)
    saved = writer.save("w-1", inputs, cell="c1")
    back = read_mcap(saved.path)
    assert back == dataclasses.replace(direct, job_id="w-1", cell="c1")  # the same recording, built elsewhere
    assert writer.last_writer_pid == os.getpid()
    with pytest.raises(RecordingError):
        writer.save("a/b", inputs, cell="c1")


@pytest.fixture
def service(tmp_path: Path, demo_cell: CellConfig) -> Iterator[Any]:
    opened: list[tuple[JobService, JobStore, zenoh.Session]] = []

    def start(backend: FakeBackend, options: ServiceOptions | None = None) -> tuple[JobService, str]:
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        session = zenoh.open(build_config(mode="peer", listen=[endpoint]))
        store = JobStore(tmp_path / "cell.jobs.sqlite", synchronous="NORMAL")
        svc = JobService(session, backend, store, options).start()
        opened.append((svc, store, session))
        return svc, endpoint

    yield start
    for svc, store, session in opened:
        svc.close()
        store.close()
        session.close()


def test_service_keeps_one_recording_per_job_with_retention(service: Any, demo_cell: CellConfig, tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    options = ServiceOptions(recordings=RecordingRetention(max_count=2))
    svc, endpoint = service(RecordingFake(demo_cell), options)
    folder = tmp_path / "cell.jobs.recordings"
    assert svc.service_status()["recordings"] == str(folder)
    with MotionClient(connect=endpoint, cell=demo_cell.name) as client:
        statuses = [client.submit(timed_job(0.02), job_id=f"rec-{k}").wait(timeout=10) for k in range(3)]
    assert [s.state.value for s in statuses] == ["done"] * 3
    for k, s in enumerate(statuses):
        assert s.report["recording"]["file"] == f"rec-{k}.mcap" and s.report["recording"]["bytes"] > 0
    assert sorted(p.name for p in folder.iterdir()) == ["rec-1.mcap", "rec-2.mcap"]  # max_count 2
    writer = svc._writer
    assert writer is not None and writer.last_writer_pid not in (None, os.getpid())  # written off-process
    rec = read_mcap(folder / "rec-2.mcap")
    assert rec.job_id == "rec-2" and rec.cell == demo_cell.name  # the service names the recording
    store = str(tmp_path / "cell.jobs.sqlite")
    capsys.readouterr()
    assert pvt(["jobs", "show", "rec-2", "--store", store, "--json"]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown["journal"]["state"] == "done" and shown["axes"][0]["samples"] == 50
    assert pvt(["jobs", "--store", store, "show", "rec-1"]) == 0  # the journal option before the action
    assert "rec-1" in capsys.readouterr().out
    assert pvt(["jobs", "export", "rec-2", "--store", store, "--csv", str(tmp_path / "r.csv")]) == 0
    assert (tmp_path / "r.csv").read_text().splitlines()[0] == "time_s,sync,j1.planned,j1.actual,j1.demand," \
                                                                "j1.following_error,j1.fifo_fill"
    capsys.readouterr()
    assert pvt(["jobs", "show", "rec-0", "--store", store]) == 1  # removed by retention
    assert "retention" in capsys.readouterr().err
    assert pvt(["jobs", "show", "nope", "--store", store]) == 1


def test_a_recording_that_cannot_be_written_does_not_fail_the_job(service: Any, demo_cell: CellConfig,
                                                                  tmp_path: Path) -> None:
    backend = RecordingFake(demo_cell)
    backend.broken = True
    _svc, endpoint = service(backend)
    with MotionClient(connect=endpoint, cell=demo_cell.name) as client:
        status = client.submit(timed_job(0.02), job_id="unlucky").wait(timeout=10)
    assert status.state.value == "done"
    assert status.report["recording"] == {"error": "OSError: disk full"}


def test_recording_can_be_switched_off(service: Any, demo_cell: CellConfig, tmp_path: Path) -> None:
    _svc, endpoint = service(RecordingFake(demo_cell), ServiceOptions(record_jobs=False))
    with MotionClient(connect=endpoint, cell=demo_cell.name) as client:
        status = client.submit(timed_job(0.02), job_id="quiet").wait(timeout=10)
    assert status.state.value == "done" and "recording" not in status.report
    assert not (tmp_path / "cell.jobs.recordings").exists()


@pytest.mark.slow
def test_the_real_backend_records_the_job_it_streamed(service: Any, demo_cell: CellConfig, tmp_path: Path) -> None:
    from streamer.runtime.bus_backend import RuntimeBackend

    cell = demo_cell.with_axes(2)
    backend = RuntimeBackend(cell, sim=True)
    try:
        _svc, endpoint = service(backend)
        job = {"kind": "move", "axes": ["j1", "j2"], "target": [0.2, -0.1], "mode": "absolute"}
        with MotionClient(connect=endpoint, cell=cell.name) as client:
            status = client.submit(job, job_id="real-1").wait(timeout=60)
        assert status.state.value == "done", status
        rec = read_mcap(tmp_path / "cell.jobs.recordings" / "real-1.mcap")
        assert rec.report["result"] == "done" and rec.start_sync is not None
        assert [e.state for e in rec.events if e.kind == "state"][-1] == "done"
        for a in rec.axes:
            s = rec.samples[a.name]
            assert len(s) > 20 and s.actual[-1] == s.planned[-1]
            records = [unpack(d) for c, d in zip(rec.frames.cob_id, rec.frames.data, strict=True)
                       if c == RPDO2_BASE + a.node_id]
            assert records and records[-1].time_ms == 0  # the end record went out and was recorded
        assert len(rec.frames) == rec.report["frames"]
        assert backend.take_recording() is None  # handed over once
    finally:
        backend.close()


@pytest.mark.wallclock
def test_the_writer_worker_ends_when_the_service_process_is_killed(tmp_path: Path) -> None:
    """A pool worker holds both ends of its call queue and never sees its parent go: after a killed service
    it lived on, idle (two were found after CI runs). It now watches its parent and exits."""
    import signal
    import subprocess
    import sys
    import time

    script = (
        "import os, sys\n"
        "from pathlib import Path\n"
        "from streamer.recording.files import RecordingFiles\n"
        "from streamer.recording.writer import RecordingWriter\n"
        f"w = RecordingWriter(RecordingFiles(Path({str(tmp_path)!r})))\n"
        "w.start()\n"
        "print(next(iter(w._pool._processes)), flush=True)\n"
        "sys.stdin.read()\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", script], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            cwd=str(Path(__file__).resolve().parents[2]))
    try:
        assert proc.stdout is not None
        worker = int(proc.stdout.readline())
        os.kill(worker, 0)  # running
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            try:
                os.kill(worker, 0)
            except ProcessLookupError:
                break
            with open(f"/proc/{worker}/stat") as f:  # a zombie waits for its reaper: it has ended
                if f.read().split(") ")[1].startswith("Z"):
                    break
            time.sleep(0.1)
        else:
            os.kill(worker, signal.SIGKILL)
            raise AssertionError(f"the writer's worker {worker} outlived its killed parent by 10 s")
    finally:
        if proc.poll() is None:
            proc.kill()
