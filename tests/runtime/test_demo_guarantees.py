"""`pvt demo`'s promises (issue 4 section 3), asserted on the virtual bus in virtual time for 1, 3, 6
and 16 axes, and once in real time on python-can's virtual bus."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from wire_context import explain_failure

from streamer import demo
from streamer.cli import main as pvt
from streamer.cli.demo import guarantees
from streamer.report import decode_candump


def _check(report: dict, traj, out: Path, cell, trace=None) -> None:
    axes = report["axes"]
    assert report["result"] == "done", explain_failure(report, out, trace)
    assert len(axes) == traj.n_axes
    assert len({a["start_sync"] for a in axes}) == 1 and axes[0]["start_sync"] is not None
    low, high = cell.drive.underflow_warning, cell.drive.overflow_warning
    for a in axes:
        assert a["errors"] == [], a
        assert a["underflow_warnings"] == 0 and a["overflow_warnings"] == 0, a
        assert low <= a["min_fifo"] <= a["max_fifo"] <= high, a
        assert a["max_deviation_counts"] <= traj.tolerance_counts, a
        assert a["final_position_error_counts"] == 0, a
        assert a["points_sent"] == traj.n_points, a  # N records + the time-0 end record
    # the bus log decodes back to the planned PVT records exactly, in order
    sent = decode_candump(out / "bus.log", traj.node_ids, report["job_start_s"])
    for i, node in enumerate(traj.node_ids):
        assert sent[node] == traj.records(i), f"node {node}: the wire differs from the plan"
    assert guarantees(report, traj.tolerance_counts) == []


@pytest.mark.virtual  # virtual time only: `make test` runs it on every core
@pytest.mark.parametrize("n_axes", [1, 3, 6, 16])
def test_demo_virtual_time(tmp_path: Path, n_axes: int) -> None:
    cell, _job, traj = demo.prepare(axes=n_axes)
    report, _trace = demo.run_fast(cell, traj, tmp_path)
    _check(report, traj, tmp_path, cell)
    assert json.loads((tmp_path / "report.json").read_text()) == report
    assert (tmp_path / "motion.png").stat().st_size > 10_000


@pytest.mark.virtual  # virtual time only: `make test` runs it on every core
def test_demo_fifo_stays_within_watermarks_every_sync(tmp_path: Path) -> None:
    cell, _job, traj = demo.prepare(axes=6)
    report, trace = demo.run_fast(cell, traj, tmp_path, plot=False)
    start = report["axes"][0]["start_sync"]
    knot_ms = traj.knot_times_ms
    low, high = cell.drive.underflow_warning, cell.drive.overflow_warning
    checked = 0
    for ax in trace.axes.values():
        for s, fill in zip(ax.fill_sync, ax.fill, strict=True):
            if s < start:
                assert fill <= high
                continue
            elapsed_ms = (s - start) * cell.sync_period_ms
            # records the drive still has to execute: segments not finished yet, plus the end record
            left = int((knot_ms > elapsed_ms).sum()) + 1 if elapsed_ms < traj.duration_ms else 0
            assert min(low, left) <= fill <= high, (ax.name, s, fill, left)
            checked += 1
    assert checked > 6 * 300


@pytest.mark.virtual  # virtual time only: `make test` runs it on every core
def test_cli_demo_fast_writes_outputs(tmp_path: Path) -> None:
    assert pvt(["demo", "--fast", "--quiet", "--axes", "3", "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "report.json").read_text())
    assert set(report) >= {"result", "sync_period_ms", "duration_s", "syncs", "frames", "bus_load_peak",
                           "faults", "axes"}
    assert set(report["axes"][0]) >= {"name", "node_id", "start_sync", "end_sync", "points_sent", "min_fifo",
                                      "max_fifo", "max_deviation_counts", "max_following_error_counts",
                                      "final_position_error_counts", "underflow_warnings", "errors"}
    for name in ("report.json", "motion.png", "bus.log"):
        assert (tmp_path / name).exists()


@pytest.mark.virtual  # virtual time only: `make test` runs it on every core
def test_cli_demo_no_plot_writes_the_rest_and_leaves_no_earlier_plot(tmp_path: Path, capsys) -> None:
    (tmp_path / "motion.png").write_bytes(b"an earlier run's plot")
    assert pvt(["demo", "--fast", "--quiet", "--no-plot", "--axes", "1", "--out", str(tmp_path)]) == 0
    assert not (tmp_path / "motion.png").exists()  # not beside a report it does not show
    for name in ("report.json", "bus.log", "job.mcap"):
        assert (tmp_path / name).stat().st_size > 0
    wrote = capsys.readouterr().out.replace("\n", "")
    assert "report.json" in wrote and "motion.png" not in wrote


@pytest.mark.virtual  # virtual time only: `make test` runs it on every core
def test_cli_demo_rejects_bad_bus_spec(tmp_path: Path) -> None:
    assert pvt(["demo", "--fast", "--quiet", "--bus", "vcan0", "--out", str(tmp_path)]) == 2


@pytest.mark.realtime
@pytest.mark.slow
def test_demo_real_time_on_virtual_bus(tmp_path: Path) -> None:
    cell, _job, traj = demo.prepare(axes=6)
    report, trace = demo.run_realtime(cell, traj, tmp_path, plot=False)
    _check(report, traj, tmp_path, cell, trace)
