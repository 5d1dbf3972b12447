"""The motion plot and the recording place each TPDO2 sample at the SYNC the streamer core attributed it to
(`JobReport.feedback`), as the report measures, not by its arrival tag: drives that answer late (the
`tpdo_late` reading of tests/reliability/conftest.py: 0.9 period stated, up to 15 ms in fact) have about one
answer in five reach the master after the next SYNC, one SYNC off the plan by its arrival."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from planner.plan import plan_job
from planner.readings import SimDriveOptions
from streamer import demo
from streamer.recording.mcap_io import read_mcap

TPDO_LATE = {"tpdo_latency_ms": 9.0, "tpdo_jitter_ms": 6.0}  # tests/reliability/conftest.py VARIANTS


def test_recording_of_late_answers_matches_the_plan(tmp_path: Path) -> None:
    base, job, _traj = demo.prepare(axes=3)
    cell = demo.commission(dataclasses.replace(
        base, axes=tuple(dataclasses.replace(a, sim=SimDriveOptions(**TPDO_LATE, seed=7)) for a in base.axes)))
    traj = plan_job(job, cell)
    report, _trace = demo.run_fast(cell, traj, tmp_path, plot=False)
    assert report["result"] == "done", report["message"]
    recording = read_mcap(tmp_path / "job.mcap")
    tol = traj.tolerance_counts
    checked = 0
    for a in report["axes"]:
        samples = recording.samples[a["name"]]
        start, end = a["start_sync"], a["start_sync"] + traj.duration_ms // cell.sync_period_ms
        for s, planned, demand in zip(samples.sync, samples.planned, samples.demand, strict=True):
            if demand is None or planned is None or not start <= s <= end:
                continue
            assert abs(demand - planned) <= tol, (a["name"], s, demand, planned)
            checked += 1
    assert checked > 3 * traj.duration_ms // cell.sync_period_ms // 2  # most SYNCs of the motion, every axis
