"""The real motion backend of `pvt serve`: the planner plus the real-time runtime on one CAN bus.

Opens the bus once (with `sim`, the cell's simulated drives in this process), configures every drive, and
keeps SYNC running between jobs. `execute` streams a job with `RealtimeRuntime` and keeps its raw material
for `take_recording()`; a `record` section arms the drives' own recorders around it. A failed job leaves
the cell not ready until `reset()` (STYLE.md rule 4). `emergency_stop()` splices the planned emergency stop,
or quick-stops every drive when none is possible or nothing runs. Home jobs run streamer/runtime/homing.py;
with `require_homing`, jobs on unreferenced axes are refused NOT_HOMED.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import threading
import time
from collections.abc import Mapping, Sequence
from typing import Any

from bus import codec
from bus.cob import pack_controlword, rpdo1_id
from bus.engine import engine_spec
from bus.errors import BusError, ProtocolError
from bus.events import AdapterError, Bootup, Event
from bus.network import MasterAdapter
from planner.config import BusConfig, CellConfig
from planner.errors import PlanningError
from planner.job import Job, MoveData, job_from_dict
from planner.motion.travel import resolve_target
from planner.plan import plan_job
from streamer.api import errors as E
from streamer.api.backend import CancelToken, Emit, MotionBackend, Planned, planned_from_trajectory
from streamer.api.errors import MotionError
from streamer.core.coordinator import Coordinator, JobState
from streamer.core.plan_source import Change, ChangeResult, EmergencyStop
from streamer.core.positioning import NotInTarget, PositioningState
from streamer.recording.writer import PlanView, RecordingInputs
from streamer.report import build_report
from streamer.runtime.extension import VelocityChangePlanner
from streamer.runtime.homing import Referencing, home_end_positions, run_homing
from streamer.runtime.realtime import RealtimeRuntime
from streamer.splice_planners import ChangePlanner, make_emergency_planner, make_stop_planner

FIFO_SIZE = 64
log = logging.getLogger(__name__)
CHANGE_ANSWER_S = 2.0  # how long change() waits for the SYNC thread's answer (it comes within a period or two)


@dataclasses.dataclass
class _Piece:
    """The part of the running stream one job owns: the job's plan, or a change spliced into it."""

    traj: Any  # planner PvtTrajectory
    emit: Emit
    t0_ms: float  # where it starts in the stream (ms from the start SYNC)
    duration_ms: float


@dataclasses.dataclass
class _Waiting:
    planner: ChangePlanner | VelocityChangePlanner
    emit: Emit
    done: threading.Event = dataclasses.field(default_factory=threading.Event)
    result: ChangeResult | None = None
    fed_elapsed_ms: float | None = None  # the stream time when the core took the request
CW_QUICK_STOP = 0x000B  # CiA 402 controlword: quick stop (bit 2 low)
EMERGENCY_STOP = "EMERGENCY_STOP"
QUICK_STOP_WAIT_S = 2.0  # how long a resume is BUSY after an emergency quick stop, at most


class RuntimeBackend(MotionBackend):
    can_change = True
    can_emergency_stop = True

    def __init__(self, cell: CellConfig, *, sim: bool = False, bus_config: BusConfig | None = None):
        self.cell = dataclasses.replace(cell, bus=bus_config) if bus_config is not None else cell
        self._lock = threading.Lock()
        self._fault: str = ""
        self._emergency = False  # an emergency stop hit the job that runs (or the idle cell)
        self._quick_stop_t: float | None = None  # when the last quick stop to every drive was sent (adapter clock)
        self._recording: RecordingInputs | None = None
        self.referencing = Referencing(self.cell)
        self._piece: _Piece | None = None  # the running stream's current owner (None: nothing streams)
        self._waiting: list[_Waiting] = []  # changes fed to the core, not answered yet (in order)
        # each axis' positioning state (seed 002's 9020:03), as the running job's core last said (the SYNC thread
        # replaces the dict, telemetry reads it): IDLE until a job ran, then what its last job left
        self._positioning: dict[str, str] = {a.name: "IDLE" for a in cell.axes}
        self._emergency_answer: threading.Event | None = None  # set by the SYNC thread when the core took it
        self._emergency_info: dict[str, Any] | None = None
        self._drives: Any = None  # the simulated drives' process (with `sim`), entered until close()
        try:
            if sim:  # the drives in a process of their own, as hardware is, on a bus that joins processes
                from bus.sim.process import drives_process, joining_bus

                self.cell = joining_bus(self.cell)
                self._drives = contextlib.ExitStack()
                self._drives.enter_context(drives_process(self.cell))
            bus = self.cell.bus
            # the cycle engine owns every bus that joins processes (bus/engine.py); python-can's virtual bus stays
            # in this process (drives simulated here by a test): the adapter sends itself
            self.adapter = MasterAdapter(None, self.cell,
                                         engine=engine_spec(bus.interface, str(bus.channel), bus.bitrate))
            if self.adapter.engine is not None:  # said once: real-time priority, or best-effort and why
                status = self.adapter.engine.realtime
                (log.info if status.fifo else log.warning)("cycle engine on %s:%s: %s", bus.interface, bus.channel,
                                                           status.message)
            self.adapter.on_event(self._on_adapter_event)
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

    def _on_adapter_event(self, ev: Event) -> None:
        if isinstance(ev, Bootup):  # the drive rebooted: it forgot its reference
            self.referencing.forget([ev.node])

    # ---- planning (intake thread)
    def validate(self, body: Mapping[str, Any]) -> Job:
        job = job_from_dict(body, self.cell)
        self.referencing.check(job)
        return job

    def current_positions(self) -> dict[str, float]:
        """Where every axis' position demand stands now, user units (the next plan must start there)."""
        snap = self.runtime.snapshot()
        out: dict[str, float] = {}
        for a in self.cell.axes:
            demand = snap[a.node_id].position_demand
            out[a.name] = 0.0 if demand is None else demand / a.counts_per_unit
        return out

    def plan(self, job: Job, start: Mapping[str, float] | None, *,
             last_target: Mapping[str, float | None] | None = None,
             last_direction: Mapping[str, int] | None = None, lead_ms: int | None = None) -> Planned:
        """Plan `job` from `start` (else where the axes stand); `last_target`/`last_direction` by axis name
        serve the additive and modulo modes (planner/motion/travel.py). The Planned carries the move's resolved
        target as the axes' new last commanded target. `lead_ms` (the job's own, shorter than the cell's):
        segments bounded so that a change or stop acts within about that lead (StreamerSettings.segment_cap_ms)."""
        if job.kind == "home":  # nothing to plan: the drives search; they end at their home positions
            self.referencing.planned(job)
            ends = home_end_positions(job)
            return Planned(job=job, trajectory=None, duration_s=0.0, points=0, end_positions=ends,
                           commanded_target=dict(ends))
        here = self.current_positions()
        begin = [(start or {}).get(a, here[a]) for a in job.axes]
        last = [(last_target or {}).get(a) for a in job.axes]
        dirs = [int((last_direction or {}).get(a, 0)) for a in job.axes]
        t0 = time.perf_counter()
        cap = (self.runtime.settings.segment_cap_ms(lead_ms)
               if lead_ms is not None and lead_ms < self.runtime.settings.lead_ms else None)
        traj = plan_job(job, self.cell, start=begin, last_target=last, last_direction=dirs, max_segment_ms=cap)
        planned = planned_from_trajectory(job, traj, time.perf_counter() - t0)
        data = job.data
        if isinstance(data, MoveData) and data.mode != "velocity":
            # the resolved target itself (not the knot it rounds to): additive moves do not add up rounding
            target = resolve_target(job, self.cell, begin, last, last_direction=dirs)
            planned = dataclasses.replace(planned, commanded_target={
                **planned.commanded_target, **{a: float(x) for a, x in zip(job.axes, target, strict=True)}})
        return planned

    # ---- motion (executor thread)
    def execute(self, planned: Planned, emit: Emit, cancel: CancelToken) -> Mapping[str, Any]:
        with self._lock:
            self._recording = None
        record = planned.record
        if cancel.cancelled:
            return {"result": "cancelled", "message": "cancelled before it started", "faults": [], "axes": []}
        ok, why = self.ready()
        if not ok:
            return {"result": "failed", "error": {"code": "NOT_READY", "node": None, "message": why},
                    "faults": [], "axes": []}
        if planned.job.kind == "home":
            return self._home(planned.job, emit, cancel)
        try:
            self.referencing.check(planned.job, at_start=True)
        except Exception as e:  # a MotionError NOT_HOMED: the home job before it failed
            return {"result": "failed", "error": {"code": getattr(e, "code", "NOT_HOMED"), "node": None,
                                                  "path": "axes", "message": str(e)}, "faults": [], "axes": []}
        report = self._execute_motion(planned, emit, cancel, record)
        self.referencing.finished(planned.job, report)
        return report

    def _home(self, job: Job, emit: Emit, cancel: CancelToken) -> Mapping[str, Any]:
        """A home job: homing mode on its drives over SDO while SYNC runs (streamer/runtime/homing.py)."""
        try:
            report = run_homing(self.cell, job, _RealtimePort(self.adapter), cancelled=lambda: cancel.cancelled,
                                progress=lambda p: emit("running", {"progress": round(p, 4), "state": "homing"}))
        except BusError as e:
            report = {"result": "failed", "kind": "home", "faults": [], "axes": [],
                      "error": {"code": e.code, "node": e.node, "message": e.message}}
            with self._lock:
                self._fault = f"{e.code}: {e.message}"
        self.referencing.finished(job, report)
        return report

    def _execute_motion(self, planned: Planned, emit: Emit, cancel: CancelToken, record: Any) -> Mapping[str, Any]:
        traj = planned.trajectory
        snap = self.runtime.snapshot()
        off = [(str(name), snap[node].position_demand, int(traj.positions[i, 0]))
               for i, (name, node) in enumerate(zip(traj.axis_names, traj.node_ids, strict=True))
               if snap[node].position_demand != int(traj.positions[i, 0])]
        if off:
            # the start is checked in one place: the service (current_positions) re-plans a queued job whose axes
            # stopped elsewhere with the travel memory (last target, direction) it reported the target with; a
            # second re-plan here, without it, could send an additive or modulo move to another target
            name, at, start = off[0]
            return {"result": "failed", "faults": [], "axes": [], "error": {
                "code": "START_MISMATCH", "node": None, "path": "axes",
                "message": f"axis {name!r} stands at {at} counts, the plan starts at {start} counts: a plan is "
                           "streamed from where it starts, never re-planned here (the service checks the start)",
                "detail": {"axes": [{"axis": n, "position_counts": a, "plan_start_counts": s} for n, a, s in off]}}}
        group = None
        if record is not None:
            from streamer.recording.drive import DriveRecordingError

            try:
                group = self._arm_recorders(record, traj)
            except DriveRecordingError as e:
                return {"result": "failed", "error": {"code": e.code, "node": None, "message": e.message,
                                                      "path": e.path}, "faults": [], "axes": []}
        stop = threading.Event()
        cancel.add_callback(stop.set)
        last = [-1.0]
        stopping: dict[str, float] = {}  # after a cancel: the stream's end and where the plan was cut (ms)
        piece = _Piece(traj, emit, 0.0, float(traj.duration_ms) or 1.0)
        with self._lock:
            self._piece = piece
            self._waiting = []
        answered = [0]
        seen_positioning = [-1]
        info_stop = [""]
        names = dict(zip(traj.node_ids, (str(n) for n in traj.axis_names), strict=True))
        before = dict(self._positioning)  # what earlier jobs left (an axis this job never commanded keeps it)

        def job_positioning(core: Coordinator) -> dict[str, str]:
            """The job's axes as its core tracks them; IDLE there means not commanded yet: START while the job
            configures and primes (docs/api.md), else what earlier jobs left (cancelled before the start)."""
            out: dict[str, str] = {}
            ending = core.state in (JobState.DONE, JobState.CANCELLED, JobState.FAILED)
            for n, st in core.positioning().items():
                name = names[n]
                if st is PositioningState.IDLE:
                    out[name] = before.get(name, "IDLE") if ending else "START"
                else:
                    out[name] = st.name
            return out

        def on_change(core: Coordinator) -> None:
            if len(core.change_results) > answered[0]:
                self._answer_changes(core, answered)
            waiter = self._emergency_answer
            if waiter is not None and not waiter.is_set() and core.emergency is not None:
                self._emergency_info = core.emergency
                waiter.set()
            pc = self._piece or piece
            p = core.progress
            moved = core.positioning_change_count != seen_positioning[0]
            if moved:
                seen_positioning[0] = core.positioning_change_count
                self._positioning = {**self._positioning, **job_positioning(core)}
            if core.start_sync is None:
                return  # the first running event marks the synchronous start (docs/api.md section 6)
            first = last[0] < 0.0
            if not first and p - last[0] < 0.01 and not (p >= 1.0 > last[0]) and not moved:
                return
            last[0] = p
            state = core.state.value
            # a velocity move has no end to measure progress against: 0 until it has stopped, and how long it ran
            endless = bool(getattr(pc.traj, "open_ended", False))
            if first and state not in ("cancelling", "halting"):
                # the start itself, by construction: this thread may get to its first call some SYNCs after the
                # start (a busy machine, or the engine fed the core ahead of the wire); the event is the start's
                # all the same (progress 0, the job's axes in START), and the next one shows where they are now
                start = {**self._positioning, **dict.fromkeys(names.values(), "START")}
                pc.emit("running", {"progress": 0.0, "state": state, "positioning": start,
                                    **({"endless": True, "elapsed_s": 0.0} if endless else {})})
                return
            # every axis: the job's as its core tracks them, the others as earlier jobs left them
            positioning = {**self._positioning, **job_positioning(core)}
            elapsed = p * core.stream_duration_ms - pc.t0_ms  # in the current piece
            planned_ms = pc.duration_ms
            if state not in ("cancelling", "halting"):
                progress = 1.0 if p >= 1.0 else 0.0 if endless else min(1.0, max(0.0, elapsed / planned_ms))
                extra = {"endless": True, "elapsed_s": round(max(0.0, elapsed) / 1000.0, 3)} if endless else {}
                pc.emit("running", {"progress": round(progress, 4), "state": state, "positioning": positioning,
                                    **extra})
                return
            if not stopping:  # the first update after the cancel: how the stream ends now
                rep = core.report()
                info = rep.cancel
                info_stop[0] = str(info.get("stop", ""))
                stopping["end"] = (float(rep.duration_ms) or 1.0) - pc.t0_ms
                cut = info["time_ms"] - pc.t0_ms if info.get("stop") == "trajectory" else (
                    planned_ms if info.get("stop") == "plan_end" else None)
                stopping["cut"] = float(cut) if cut is not None else min(planned_ms, elapsed)
            cut = stopping["cut"]
            fields: dict[str, Any] = {"progress": 0.0 if endless else round(min(elapsed, cut) / planned_ms, 4),
                                      "state": state, "positioning": positioning}
            if rep_stop := info_stop[0]:
                fields["stop"] = rep_stop  # trajectory, emergency_trajectory, halt, plan_end
            if stopping["end"] > cut:
                fields["stop_progress"] = round(min(1.0, max(0.0, (elapsed - cut) / (stopping["end"] - cut))), 4)
            pc.emit("running", fields)

        try:
            result = self.runtime.run(traj, stop_planner=make_stop_planner(self.cell, traj), cancel=stop,
                                      on_change=on_change, lead_ms=planned.lead_ms)
        finally:
            with self._lock:
                self._piece = None
                waiting, self._waiting = self._waiting, []
            for w in waiting:  # the job ended before the core took them
                w.done.set()
        core = result.coordinator
        report = build_report(traj, core.report(), result.trace, sync_period_ms=self.cell.sync_period_ms,
                              first_sync=result.first_sync, last_sync=result.last_sync,
                              readings=self.runtime.settings.readings, time_stamp=self.cell.time_stamp,
                              setpoints={n: core.setpoints(n) for n in traj.node_ids})
        outcome = core.outcome
        final = core.report()
        left = {names[n]: before.get(names[n], st) if st == PositioningState.IDLE.name else st
                for n, st in final.positioning.items()}
        self._positioning = {**self._positioning, **left}
        report["positioning"] = left
        if final.warnings:
            report["warnings"] = [self._warning(w, names[w.node]) for w in final.warnings]
        with self._lock:
            emergency = self._emergency
        planned_stop = core.emergency
        if emergency and report["result"] != "done":
            report["result"] = "failed"
            if planned_stop is not None and planned_stop["method"] == "emergency_trajectory":
                message = (f"emergency stop: every axis stopped on its emergency deceleration, a "
                           f"{planned_stop['stop_duration_ms']} ms stop from {planned_stop['time_ms']} ms into the "
                           "motion (after what was queued); the drives stay enabled")
                detail = {"method": "emergency_trajectory", **planned_stop}
            else:
                message = ("emergency stop: quick stop (controlword 0x000B) to every drive; each ramped down on its "
                           "quick stop deceleration (0x6085)")
                detail = {"method": "quick_stop", **({"reason": planned_stop["reason"]} if planned_stop else {})}
            report["error"] = {"code": EMERGENCY_STOP, "node": None, "message": message,
                               "sync": outcome.sync if outcome is not None else None, "detail": detail}
        elif outcome is not None and report["result"] == "failed":
            report["error"] = {"code": outcome.code, "node": outcome.node, "message": outcome.message,
                               "sync": outcome.sync, "detail": dict(outcome.detail)}
            with self._lock:
                self._fault = f"{outcome.code}: {outcome.message}"
        drive = None
        if group is not None:
            drive, info = self._read_recorders(group, traj, result, core.start_sync)
            report["drive_recording"] = info
        recording = RecordingInputs(PlanView.of(traj), result.trace, dict(report), result.first_sync,
                                    core.start_sync, self.cell.sync_period_ms, cell=self.cell.name,
                                    underflow_watermark=self.cell.drive.underflow_warning,
                                    overflow_watermark=self.cell.drive.overflow_warning, drive=drive,
                                    feedback=core.report().feedback)
        with self._lock:
            self._recording = recording
        return report

    def _warning(self, w: NotInTarget, name: str) -> dict[str, Any]:
        """A core warning for the report: the axis by name, the error in counts and in the axis' user units."""
        a = self._axes[name]
        return {"code": w.code, "axis": name, "node": w.node, "error_counts": w.error_counts,
                "error": w.error_counts / a.counts_per_unit, "window_counts": w.window_counts,
                "window": w.window_counts / a.counts_per_unit, "timeout_ms": w.timeout_ms, "unit": a.unit,
                "message": f"axis {name!r} is {w.error_counts:+d} counts ({w.error_counts / a.counts_per_unit:+.6g} "
                           f"{a.unit}) from its target {w.timeout_ms} ms after the plan's end (target window "
                           f"{w.window_counts} counts)"}

    # ---- changes of the running motion (the intake thread asks, the SYNC thread answers)
    def change(self, job: Job, mode: str, emit: Emit, *, last_target: Mapping[str, float | None] | None = None,
               last_direction: Mapping[str, int] | None = None) -> tuple[Planned, dict[str, Any]]:
        """Replace the running job's remainder with `job` (a move; mode "aborting") or append it at the running
        plan's end ("buffered"), without stopping. Returns the new job's `Planned` and what the core did
        (`time_ms`, `reaction_ms`, `overrun_axes`, ...); progress of the new job goes to `emit` from then on.
        A velocity move is planned open-ended from the end of the queue and extended as it runs.
        Raises MotionError COMMAND_REJECTED with the reason when it cannot be made (the running job goes on
        untouched)."""
        with self._lock:
            piece = self._piece
        if piece is None:
            raise MotionError(E.COMMAND_REJECTED, "no job is moving: there is nothing to change", path="buffer")
        names = tuple(str(n) for n in piece.traj.axis_names)
        if tuple(job.axes) != names and set(job.axes) != set(names):
            raise MotionError(E.COMMAND_REJECTED, f"the change moves axes {list(job.axes)} but the running job moves "
                              f"{list(names)}: a change replaces a motion of the same axes", path="axes")
        planner: ChangePlanner | VelocityChangePlanner
        resolved: dict[str, float | None]
        if getattr(job.data, "mode", None) == "velocity":
            if tuple(job.axes) != names:
                raise MotionError(E.COMMAND_REJECTED, f"a velocity change lists the running job's axes in its order "
                                  f"{list(names)}, not {list(job.axes)}", path="axes")
            planner = VelocityChangePlanner(self.cell, job, tuple(int(n) for n in piece.traj.node_ids))
            resolved = {a: None for a in job.axes}
        else:
            target = self._change_target(job, piece, last_target, last_direction)
            resolved = dict(target)
            try:
                planner = ChangePlanner(self.cell, piece.traj, target, tolerance_counts=job.tolerance_counts)
            except ValueError as exc:
                raise MotionError(E.COMMAND_REJECTED, str(exc), path="target") from None
        waiting = _Waiting(planner, emit)
        with self._lock:
            self._waiting.append(waiting)
        if not self.runtime.submit(Change(self.adapter.now(), planner, mode=mode)):
            with self._lock:
                if waiting in self._waiting:
                    self._waiting.remove(waiting)
            raise MotionError(E.COMMAND_REJECTED, "the running job has just ended: submit the move as a new job",
                              path="buffer")
        if not waiting.done.wait(CHANGE_ANSWER_S) or waiting.result is None:
            raise MotionError(E.COMMAND_REJECTED, "the running job ended before the change could be made",
                              path="buffer")
        res = waiting.result
        if not res.accepted:
            err = planner.error
            code = getattr(err, "code", None)
            raise MotionError(E.COMMAND_REJECTED, f"the change cannot be made: {res.reason}", path="target",
                              detail={"reason": res.reason, **({"planner_code": code} if code else {}),
                                      "knot": res.knot, "time_ms": res.time_ms})
        plan = planner.planned
        assert plan is not None
        traj = plan.trajectory
        planned = planned_from_trajectory(job, traj, planner.planning_s)
        planned = dataclasses.replace(planned, commanded_target={**planned.commanded_target, **resolved})
        info: dict[str, Any] = {
            "mode": mode, "time_ms": res.time_ms, "duration_ms": res.duration_ms, "knot": res.knot,
            "reaction_ms": None if waiting.fed_elapsed_ms is None or res.time_ms is None
            else round(res.time_ms - waiting.fed_elapsed_ms, 1),
            "planning_s": round(planner.planning_s, 6),
            "overrun_axes": list(plan.overrun_axes),
            "overrun_counts": list(plan.overrun_counts),
        }
        return planned, info

    def _change_target(self, job: Job, piece: _Piece, last_target: Mapping[str, float | None] | None = None,
                       last_direction: Mapping[str, int] | None = None) -> dict[str, float]:
        """The absolute target of a change, by axis name. The one place a move mode becomes a target
        (planner/motion/travel.py's `resolve_target`): relative and modulo modes from where the running job's demand
        stands now, additive from the last commanded target (the running job's, kept by the service)."""
        data = job.data
        target = [float(x) for x in getattr(data, "target", ())]
        if not isinstance(data, MoveData) or len(target) != len(job.axes):
            raise MotionError(E.COMMAND_REJECTED, f"a {job.kind} job cannot change a running motion: only a move "
                              "with a target can", path="kind")
        here = self.current_positions()
        try:
            resolved = resolve_target(job, self.cell, [here[a] for a in job.axes],
                                      [(last_target or {}).get(a) for a in job.axes],
                                      last_direction=[int((last_direction or {}).get(a, 0)) for a in job.axes])
        except PlanningError as exc:
            raise MotionError(E.COMMAND_REJECTED, f"the change's target cannot be resolved: {exc.message}",
                              path=exc.path or "target", detail={"planner_code": exc.code}) from None
        return {a: float(x) for a, x in zip(job.axes, resolved, strict=True)}

    def _answer_changes(self, core: Coordinator, answered: list[int]) -> None:
        """SYNC thread: hand each new ChangeResult to the change() waiting for it; an accepted change makes its
        job the owner of the stream from its splice on (progress goes to it)."""
        results = core.change_results
        s = core.start_sync
        for res in results[answered[0]:]:
            with self._lock:
                waiting = self._waiting.pop(0) if self._waiting else None
                if waiting is None:
                    continue
                if res.sync is not None and s is not None:
                    waiting.fed_elapsed_ms = float(max(0, res.sync - s) * self.cell.sync_period_ms)
                waiting.result = res
                if res.accepted and waiting.planner.planned is not None and res.time_ms is not None:
                    traj = waiting.planner.planned.trajectory
                    self._piece = _Piece(traj, waiting.emit, float(res.time_ms), float(traj.duration_ms) or 1.0)
            waiting.done.set()
        answered[0] = len(results)

    def emergency_stop(self) -> dict[str, Any]:
        """Stop every axis at its emergency deceleration: a running job gets the planned emergency stop spliced
        after what is queued (streamer.core.EmergencyStop); the quick stop on every drive only when no plan is
        possible in time or nothing runs (see the module docstring). The cell is not ready until reset()
        (resume). Returns {"method": "emergency_trajectory" | "quick_stop", "message", ...}."""
        with self._lock:
            self._emergency = True
            piece = self._piece
        if piece is not None:
            answer = threading.Event()
            self._emergency_info = None
            self._emergency_answer = answer
            try:
                planner = make_emergency_planner(self.cell, piece.traj)
                if self.runtime.submit(EmergencyStop(self.adapter.now(), planner)):
                    answer.wait(CHANGE_ANSWER_S)
            finally:
                self._emergency_answer = None
            info = self._emergency_info
            if info is not None and info.get("method") == "emergency_trajectory":
                with self._lock:
                    self._fault = (f"{EMERGENCY_STOP}: the running job stopped on the emergency deceleration by the "
                                   "operator; resume releases the cell")
                return {"method": "emergency_trajectory", "time_ms": info["time_ms"],
                        "stop_duration_ms": info["stop_duration_ms"],
                        "message": f"emergency stop planned at each axis' emergency deceleration: "
                                   f"{info['stop_duration_ms']} ms long, from {info['time_ms']} ms into the motion "
                                   "(after what is queued)"}
            why = ((info.get("reason") if info is not None else None)
                   or "the running job did not take the emergency stop in time")
            return {"method": "quick_stop", "message": self._quick_stop_all() + f" (no emergency stop plan: {why})"}
        return {"method": "quick_stop", "message": self._quick_stop_all()}

    def _quick_stop_all(self) -> str:
        """Quick stop on every axis, now: today's emergency stop, and the fallback of the planned one."""
        with self._lock:
            self._emergency = True
            self._fault = (f"{EMERGENCY_STOP}: quick stop (0x000B) to every drive by the operator; "
                           "resume (reset) re-enables them")
            self._quick_stop_t = self.adapter.now()
        # a running job: its core fails and quick-stops its axes in that reaction, and sends nothing after
        # (the runtime queues adapter events only while a job runs; otherwise this is a no-op)
        self.runtime._on_event(AdapterError("emergency stop", "requested by the operator", self.adapter.now()))
        sent = []
        for a in self.cell.axes:  # every drive of the cell, idle ones too
            try:
                self.adapter.send(rpdo1_id(a.node_id), pack_controlword(CW_QUICK_STOP))
                sent.append(a.node_id)
            except BusError:
                pass  # the bus refused: the core's own quick stop (running job) or the heartbeat loss acts
        return (f"quick stop (controlword 0x000B) sent to node(s) {sent}: each drive ramps down on its quick "
                "stop deceleration 0x6085 at the next SYNC")

    # ---- the drives' own data recorders (a job's `record` section)
    def _arm_recorders(self, request: Any, traj: Any) -> Any:
        from streamer.recording.drive import recorded_axes
        from streamer.recording.recorder_client import CanopenSdo, Recorder, RecorderGroup

        names = recorded_axes([self._axes[str(n)] for n in traj.axis_names], request.axes)
        nodes = [self._axes[name].node_id for name in names]
        group = RecorderGroup({n: Recorder(CanopenSdo(self.adapter.remote[n])) for n in nodes}, request,
                              now=self.adapter.now)
        group.start()
        return group

    def _read_recorders(self, group: Any, traj: Any, result: Any, start_sync: int | None) -> tuple[Any, Any]:
        """(DriveRecording or None, the report's summary or error). Trigger times on the job's clock: the
        start SYNC (movement), the plan's end (end of profile), the node's first EMCY (error), the force
        write (force); unknown for a digital input and continuous mode."""
        from bus.events import Emcy
        from streamer.recording.drive import DriveRecording, DriveRecordingError

        request = group.request
        try:
            nodes = group.finish(request.span_s + 5.0)
        except DriveRecordingError as e:
            return None, {"error": e.message}
        times = result.trace.sync_times
        t0 = times.get(result.first_sync, min(times.values(), default=0.0))
        start = times.get(start_sync) if start_sync is not None else None
        trigger_t: dict[int, float | None] = {}
        for n in nodes:
            at: float | None = None
            if request.trigger == "movement" and start is not None:
                at = start - t0
            elif request.trigger == "end" and start is not None:
                at = start - t0 + float(traj.duration_s)
            elif request.trigger == "force" and group.forced_at is not None:
                at = group.forced_at - t0
            elif request.trigger == "error":
                emcy = [e.event.t for e in result.trace.noted
                        if isinstance(e.event, Emcy) and e.event.node == n and e.event.code]
                at = emcy[0] - t0 if emcy else None
            trigger_t[n] = None if at is None else round(at, 6)
        names = {a.node_id: a.name for a in self.cell.axes}
        drive = DriveRecording(request, nodes, names={n: names[n] for n in nodes},
                               upload={n: r.last_upload for n, r in group.recorders.items()}, trigger_t=trigger_t)
        info = drive.summary()
        if group.not_triggered:
            info["not_triggered"] = group.not_triggered
        return drive, info

    def take_recording(self) -> RecordingInputs | None:
        """The recording (to build) of the job the last `execute` streamed (None if it streamed nothing),
        once."""
        with self._lock:
            recording, self._recording = self._recording, None
        return recording

    # ---- state (any thread)
    def telemetry(self) -> Sequence[Mapping[str, Any]]:
        snap = self.runtime.snapshot()
        referenced = self.referencing.referenced  # a home job attained on the axis (streamer/runtime/homing.py)
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
                "positioning": self._positioning.get(a.name, "IDLE"),
                "referenced": a.name in referenced,
            })
        return out

    def ready(self) -> tuple[bool, str]:
        with self._lock:
            return (not self._fault, self._fault)

    def _quick_stop_running(self) -> str:
        """Why the quick stop sent to every drive has not ended yet ("" once it has): it acts at the SYNC after it
        was sent (RPDO1 is synchronous), then each drive ramps down and ends switch on disabled (0x605A = 2);
        enabling a drive before that would be undone by the quick stop still on its way. A drive whose last
        statusword still says operation enabled has not taken it yet, one in quick stop active is ramping; a
        drive that reports no statusword here (a cyclic family's TPDO1) is given two SYNC periods. After
        QUICK_STOP_WAIT_S the reset goes ahead whatever (a refused frame must not hold the cell forever)."""
        with self._lock:
            sent = self._quick_stop_t
        if sent is None:
            return ""
        waited = self.adapter.now() - sent
        if waited >= QUICK_STOP_WAIT_S:
            return ""
        snap = self.runtime.snapshot()
        for a in self.cell.axes:
            sw = snap[a.node_id].statusword
            if sw is None:
                if waited < 2.0 * self.cell.sync_period_s:
                    return (f"node {a.node_id} ({a.name}) takes the quick stop sent {1000.0 * waited:.0f} ms ago at "
                            f"the next SYNC")
                continue
            try:
                state = codec.state_from_statusword(sw)
            except ProtocolError:
                continue
            if state is codec.Cia402State.OPERATION_ENABLED:
                return (f"node {a.node_id} ({a.name}) takes the quick stop sent {1000.0 * waited:.0f} ms ago at the "
                        "next SYNC")
            if state in (codec.Cia402State.QUICK_STOP_ACTIVE, codec.Cia402State.FAULT_REACTION_ACTIVE):
                return f"node {a.node_id} ({a.name}) is still ramping down ({state.value}, statusword 0x{sw:04X})"
        return ""

    def reset(self) -> tuple[bool, str]:
        """Re-enable every drive (fault reset when faulted). Raises MotionError BUSY while the quick stop of an
        emergency stop is still taking effect (a resume that comes too early; docs/api.md section 8)."""
        why = self._quick_stop_running()
        if why:
            raise MotionError(E.BUSY, f"the emergency stop is still stopping the drives: {why}; resume when they "
                              "have stopped")
        self.adapter.enable_drives()  # fault reset when faulted, shutdown, enable, buffer clear/enable
        with self._lock:
            self._fault = ""
            self._emergency = False
            self._quick_stop_t = None
        return self.ready()

    def close(self) -> None:
        runtime = getattr(self, "runtime", None)
        if runtime is not None:
            runtime.close()
        adapter = getattr(self, "adapter", None)
        if adapter is not None:
            adapter.close(check=False)
        if self._drives is not None:
            self._drives.close()
            self._drives = None


class _RealtimePort:
    """`HomingPort` of the real-time backend: SDO over the adapter, waiting = sleeping while SYNC runs."""

    def __init__(self, adapter: MasterAdapter):
        self.adapter = adapter

    def write(self, node: int, index: int, sub: int, value: int) -> None:
        self.adapter.write(node, index, sub, value)

    def read(self, node: int, index: int, sub: int) -> int:
        return self.adapter.read(node, index, sub)

    def enable(self) -> None:
        self.adapter.enable_drives()

    def wait(self, seconds: float) -> None:
        time.sleep(seconds)

    def now(self) -> float:
        return self.adapter.now()


def open_backend(cell: CellConfig, *, sim: bool = False, interface: str | None = None,
                 channel: str | None = None, bitrate: int | None = None) -> RuntimeBackend:
    bus = None
    if interface is not None or channel is not None or bitrate is not None:
        bus = BusConfig(interface=interface or cell.bus.interface, channel=channel or cell.bus.channel,
                        bitrate=bitrate or cell.bus.bitrate)
    return RuntimeBackend(cell, sim=sim, bus_config=bus)
