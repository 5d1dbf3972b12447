"""The real motion backend of `pvt serve`: the planner plus the real-time runtime on one CAN bus.

Implements `streamer.api.backend.MotionBackend`. It opens the bus once (the cell's [bus], or
`interface`/`channel`/`bitrate` given on the command line), starts the cell's simulated drives in
this process when `sim` is true, configures every drive over SDO, and keeps SYNC running between
jobs so heartbeats and TPDOs keep the telemetry live. Each `execute` streams one planned job with
`RealtimeRuntime` on the service's executor thread (the SYNC-driven loop; planning happened on the
intake thread) and returns the demo's report shape.

Every job that streamed is recorded: after the job `execute` keeps its raw material (the trace, the
plan's demand per ms, the report: `RecordingInputs`, no Python loop over the samples here) until the
service takes it with `take_recording()` and has it built and written beside its journal, in a worker
process (streamer/recording/writer.py). The SYNC loop pays only the trace's appends.

A failed job leaves the cell NOT ready until `reset()` (fault reset + re-enable over SDO): after a
fault nothing moves again without a deliberate act (STYLE.md rule 4).
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Mapping, Sequence
from typing import Any

from bus import codec
from bus.network import MasterAdapter
from planner.config import BusConfig, CellConfig
from planner.job import Job, job_from_dict
from planner.plan import plan_job
from streamer.api.backend import CancelToken, Emit, Planned, planned_from_trajectory
from streamer.core.coordinator import Coordinator
from streamer.recording.writer import PlanView, RecordingInputs
from streamer.report import build_report
from streamer.runtime.realtime import RealtimeRuntime
from streamer.stop import make_stop_planner

FIFO_SIZE = 64


class RuntimeBackend:
    def __init__(self, cell: CellConfig, *, sim: bool = False, bus_config: BusConfig | None = None):
        self.cell = dataclasses.replace(cell, bus=bus_config) if bus_config is not None else cell
        self._sim: Any = None
        self._lock = threading.Lock()
        self._fault: str = ""
        self._recording: RecordingInputs | None = None
        if sim:
            from bus.sim.node import SimulatedCell
            from streamer.demo import IN_PROCESS_SYNC_GAP_FACTOR

            self._sim = SimulatedCell(self.cell, sync_gap_factor=IN_PROCESS_SYNC_GAP_FACTOR).start()
        try:
            self.adapter = MasterAdapter(None, self.cell)
            self.adapter.configure_drives()
            self.runtime = RealtimeRuntime(self.cell, self.adapter)
            # what the cell does not state of the drives' readings, measured once at start-up (no motion);
            # the plans are then made for the drives as they are (bus/probe.py)
            self.runtime.ensure_readings()
            self.cell = dataclasses.replace(self.cell, axes=tuple(
                dataclasses.replace(a, probed=self.runtime.known[a.node_id]) for a in self.cell.axes))
            self.adapter.enable_drives()
            self.adapter.start_sync()
        except BaseException:
            self.close()
            raise
        self._axes = {a.name: a for a in self.cell.axes}

    # ---- planning (intake thread)
    def validate(self, body: Mapping[str, Any]) -> Job:
        return job_from_dict(body, self.cell)

    def current_positions(self) -> dict[str, float]:
        """Where every axis' position demand stands now, user units (the next plan must start there)."""
        snap = self.runtime.snapshot()
        out: dict[str, float] = {}
        for a in self.cell.axes:
            demand = snap[a.node_id].position_demand
            out[a.name] = 0.0 if demand is None else demand / a.counts_per_unit
        return out

    def plan(self, job: Job, start: Mapping[str, float] | None) -> Planned:
        here = self.current_positions()
        begin = [(start or {}).get(a, here[a]) for a in job.axes]
        t0 = time.perf_counter()
        traj = plan_job(job, self.cell, start=begin)
        return planned_from_trajectory(job, traj, time.perf_counter() - t0)

    # ---- motion (executor thread)
    def execute(self, planned: Planned, emit: Emit, cancel: CancelToken) -> Mapping[str, Any]:
        with self._lock:
            self._recording = None
        if cancel.cancelled:
            return {"result": "cancelled", "message": "cancelled before it started", "faults": [], "axes": []}
        ok, why = self.ready()
        if not ok:
            return {"result": "failed", "error": {"code": "NOT_READY", "node": None, "message": why},
                    "faults": [], "axes": []}
        traj = planned.trajectory
        snap = self.runtime.snapshot()
        off = [name for i, (name, node) in enumerate(zip(traj.axis_names, traj.node_ids, strict=True))
               if snap[node].position_demand != int(traj.positions[i, 0])]
        if off:  # an earlier job ended elsewhere (cancelled or failed): plan again from here
            planned = self.plan(planned.job, None)
            traj = planned.trajectory
        stop = threading.Event()
        cancel.add_callback(stop.set)
        last = [-1.0]

        def on_change(core: Coordinator) -> None:
            p = core.progress
            if p - last[0] >= 0.01 or (p >= 1.0 > last[0]):
                last[0] = p
                emit("running", {"progress": round(p, 4), "state": core.state.value})

        result = self.runtime.run(traj, stop_planner=make_stop_planner(self.cell, traj), cancel=stop,
                                  on_change=on_change)
        core = result.coordinator
        report = build_report(traj, core.report(), result.trace, sync_period_ms=self.cell.sync_period_ms,
                              first_sync=result.first_sync, last_sync=result.last_sync,
                              readings=self.runtime.settings.readings, time_stamp=self.cell.time_stamp,
                              setpoints={n: core.setpoints(n) for n in traj.node_ids})
        outcome = core.outcome
        if outcome is not None and report["result"] == "failed":
            report["error"] = {"code": outcome.code, "node": outcome.node, "message": outcome.message,
                               "sync": outcome.sync, "detail": dict(outcome.detail)}
            with self._lock:
                self._fault = f"{outcome.code}: {outcome.message}"
        recording = RecordingInputs(PlanView.of(traj), result.trace, dict(report), result.first_sync,
                                    core.start_sync, self.cell.sync_period_ms, cell=self.cell.name,
                                    underflow_watermark=self.cell.drive.underflow_warning,
                                    overflow_watermark=self.cell.drive.overflow_warning)
        with self._lock:
            self._recording = recording
        return report

    def take_recording(self) -> RecordingInputs | None:
        """The recording (to build) of the job the last `execute` streamed (None if it streamed nothing),
        once."""
        with self._lock:
            recording, self._recording = self._recording, None
        return recording

    # ---- state (any thread)
    def telemetry(self) -> Sequence[Mapping[str, Any]]:
        snap = self.runtime.snapshot()
        out = []
        for a in self.cell.axes:
            s = snap[a.node_id]
            state = "unknown" if s.statusword is None else codec.state_from_statusword(s.statusword).value
            out.append({
                "name": a.name,
                "node_id": a.node_id,
                "position": None if s.position_actual is None else s.position_actual / a.counts_per_unit,
                "position_demand": None if s.position_demand is None else s.position_demand / a.counts_per_unit,
                "velocity": s.velocity_counts_per_s / a.counts_per_unit,
                "fifo_fill": None if s.free_size is None else FIFO_SIZE - s.free_size,
                "state": state,
            })
        return out

    def ready(self) -> tuple[bool, str]:
        with self._lock:
            return (not self._fault, self._fault)

    def reset(self) -> tuple[bool, str]:
        self.adapter.enable_drives()  # fault reset when faulted, shutdown, enable, buffer clear/enable
        with self._lock:
            self._fault = ""
        return self.ready()

    def close(self) -> None:
        runtime = getattr(self, "runtime", None)
        if runtime is not None:
            runtime.close()
        adapter = getattr(self, "adapter", None)
        if adapter is not None:
            adapter.close(check=False)
        if self._sim is not None:
            self._sim.stop()
            self._sim = None


def open_backend(cell: CellConfig, *, sim: bool = False, interface: str | None = None,
                 channel: str | None = None, bitrate: int | None = None) -> RuntimeBackend:
    bus = None
    if interface is not None or channel is not None or bitrate is not None:
        bus = BusConfig(interface=interface or cell.bus.interface, channel=channel or cell.bus.channel,
                        bitrate=bitrate or cell.bus.bitrate)
    return RuntimeBackend(cell, sim=sim, bus_config=bus)
