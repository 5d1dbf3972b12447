"""A job's `record` section over the job API (issue 16 section 2): checked at admission, run by the real
backend around the motion, and stored with the job: the drives' recordings are channels of the job's MCAP
file (`/recorder/<node>`, metadata `pvt.recorder`) and a summary in its report."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from planner.config import CellConfig
from streamer.api.backend import CancelToken, Emit, Planned
from streamer.api.client import MotionClient
from streamer.api.errors import MotionError
from streamer.api.service import JobService, ServiceOptions
from streamer.api.store import JobStore
from streamer.api.zenoh_config import build_config
from streamer.cli import main as pvt
from streamer.recording.drive import DriveRecording, NodeRecording, RecordRequest, parse_variable
from streamer.recording.mcap_io import read_mcap, write_mcap
from tests.api.conftest import free_port
from tests.api.fakes import FakeBackend, timed_job
from tests.recording.test_service_recordings import synthetic


@pytest.fixture
def service(tmp_path: Path) -> Iterator[Any]:
    opened: list[tuple[JobService, JobStore, zenoh.Session]] = []

    def start(backend: Any, options: ServiceOptions | None = None) -> tuple[JobService, str]:
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


class SeeingFake(FakeBackend):
    """The fake backend, keeping the `record` of every job it executes."""

    def __init__(self, cell: CellConfig):
        super().__init__(cell)
        self.records: list[Any] = []

    def execute(self, planned: Planned, emit: Emit, cancel: CancelToken) -> Any:
        self.records.append(planned.record)
        return super().execute(planned, emit, cancel)


def test_the_record_section_is_checked_when_the_job_is_submitted(service: Any, demo_cell: CellConfig) -> None:
    backend = SeeingFake(demo_cell)
    _svc, endpoint = service(backend)
    with MotionClient(connect=endpoint, cell=demo_cell.name) as client:
        for record, path, words in (
            ({"variables": ["torque"], "period_ms": 1}, "record.variables[0]", "unknown variable 'torque'"),
            ({"variables": ["statusword"] * 5, "period_ms": 1}, "record.variables", "at most 4 variables, got 5"),
            ({"variables": ["statusword"], "total_ms": 9e6}, "record.total_ms", "needs a sampling period"),
            ({"variables": ["statusword"], "period_ms": 1, "axes": ["j2"]}, "record.axes[0]", "'j2' is not an axis"),
            ({"variables": ["statusword"], "period_ms": 1, "when": "now"}, "record.when", "unknown field 'when'"),
        ):
            with pytest.raises(MotionError) as e:
                client.submit({**timed_job(0.02), "record": record})
            assert (e.value.code, e.value.path) == ("BAD_RECORD", path), e.value
            assert words in e.value.message
        job = {**timed_job(0.02), "record": {"variables": ["position_demand", "0x6041:00"], "period_ms": 0.5,
                                             "trigger": "movement", "preceding_ms": 2}}
        assert client.submit(job, job_id="with-record").wait(timeout=10).state.value == "done"
    (request,) = backend.records
    assert isinstance(request, RecordRequest)
    assert [v.name for v in request.variables] == ["position_demand", "statusword"]
    assert (request.period_units, request.preceding_samples, request.trigger) == (5, 4, "movement")


def test_a_drive_recording_round_trips_through_the_job_mcap(tmp_path: Path) -> None:
    variables = (parse_variable("position_demand"), parse_variable("0x6061:00"))
    request = RecordRequest(variables, trigger="end", period_ms=2.0, preceding_ms=4.0)
    nodes = {n: NodeRecording(n, variables, tuple(round((k - 2) * 0.002, 9) for k in range(6)),
                              {"position_demand": tuple(range(-3 * n, 3 * n, n)), "0x6061_00": (7, 7, 7, 7, 7, -1)},
                              0.002, True, 2, 5, 6) for n in (1, 2)}
    drive = DriveRecording(request, nodes, names={1: "j1", 2: "j2"}, upload={1: "block", 2: "segmented"},
                           trigger_t={1: 0.25, 2: None})
    rec = dataclasses.replace(synthetic(), drive=drive)
    write_mcap(rec, tmp_path / "r.mcap")
    back = read_mcap(tmp_path / "r.mcap")
    assert back.drive == drive
    assert back == rec


@pytest.mark.slow
def test_the_real_backend_records_the_drives_around_the_job(service: Any, demo_cell: CellConfig,
                                                            tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from planner.job import job_from_dict
    from planner.plan import plan_job
    from streamer.runtime.bus_backend import RuntimeBackend

    cell = demo_cell.with_axes(2)
    backend = RuntimeBackend(cell, sim=True)
    try:
        _svc, endpoint = service(backend)
        body = {"kind": "move", "axes": ["j1", "j2"], "target": [0.3, -0.2], "mode": "absolute"}
        record = {"variables": ["position_demand", "velocity_actual"], "period_ms": 5, "trigger": "movement",
                  "preceding_ms": 20}
        with MotionClient(connect=endpoint, cell=cell.name) as client:
            status = client.submit({**body, "record": record}, job_id="rec-job").wait(timeout=60)
        assert status.state.value == "done", status
        summary = status.report["drive_recording"]
        assert set(summary["nodes"]) == {"1", "2"}
        assert all(n["triggered"] and n["upload"] == "block" for n in summary["nodes"].values())
        rec = read_mcap(tmp_path / "cell.jobs.recordings" / "rec-job.mcap")
        drive = rec.drive
        assert drive is not None and drive.names == {1: "j1", 2: "j2"}
        traj = plan_job(job_from_dict(body, cell), cell)
        plan = traj.planned_demand()
        start_t = rec.events[[e.kind for e in rec.events].index("start")].t
        for i, node in enumerate((1, 2)):
            nr = drive.nodes[node]
            assert drive.trigger_t[node] == pytest.approx(start_t, abs=1e-6)  # the start SYNC, on every node
            t_ms = np.array(nr.t) * 1000.0
            index = np.clip(np.ceil(t_ms - 1e-6), 0, traj.duration_ms).astype(int)
            assert np.abs(np.array(nr.series("position_demand")) - plan[i, index]).max() <= traj.tolerance_counts
        capsys.readouterr()
        assert pvt(["jobs", "show", "rec-job", "--store", str(tmp_path / "cell.jobs.sqlite"), "--json"]) == 0
        shown = json.loads(capsys.readouterr().out)
        assert shown["messages"]["/recorder/1"] == shown["messages"]["/recorder/2"] == 128
        assert shown["drive_recording"]["request"]["trigger"] == "movement"
    finally:
        backend.close()
