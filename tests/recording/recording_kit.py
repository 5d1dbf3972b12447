"""Helpers of the recording tests: a job run in virtual time and its recording."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from bus.sim.virtual import VirtualCell
from planner.config import CellConfig
from planner.trajectory import PvtTrajectory
from streamer import demo
from streamer.recording.model import JobRecording, build_recording
from streamer.report import build_report
from streamer.runtime.virtual import VirtualResult, VirtualRuntime
from streamer.splice_planners import make_stop_planner


def drives_for(cell: CellConfig, traj: PvtTrajectory) -> VirtualCell:
    """The cell's simulated drives standing at the plan's start."""
    return VirtualCell(cell, initial_positions=demo.start_positions(cell, traj))


def record_virtual(cell: CellConfig, traj: PvtTrajectory, *, on_sync: Callable[..., Any] | None = None,
                   vcell: VirtualCell | None = None, **kw: Any) -> tuple[VirtualResult, dict[str, Any], JobRecording]:
    """Run `traj` on simulated drives in virtual time; (result, report, recording)."""
    vcell = vcell if vcell is not None else drives_for(cell, traj)
    rt = VirtualRuntime(cell, vcell=vcell)
    result = rt.run(traj, stop_planner=make_stop_planner(cell, traj), on_sync=on_sync, **kw)
    core = result.coordinator.report()
    report = build_report(traj, core, result.trace, sync_period_ms=cell.sync_period_ms,
                          first_sync=result.first_sync, last_sync=result.last_sync)
    rec = build_recording(traj, result.trace, report, first_sync=result.first_sync, start_sync=core.start_sync,
                          sync_period_ms=cell.sync_period_ms, job_id="t", cell=cell.name, epoch_s=time.time(),
                          underflow_watermark=cell.drive.underflow_warning,
                          overflow_watermark=cell.drive.overflow_warning)
    return result, report, rec
