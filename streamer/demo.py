"""`pvt demo`: the whole product in one process, on the embedded default.

A python-can `virtual` bus (or any bus given with --bus), the cell's simulated drives, the master
adapter, the streamer core and the default 6-axis path job. In real time at the cell's SYNC period by
default; `--fast` runs the same core and drive models in virtual time. Writes report.json,
motion.png, bus.log (candump -L format) and job.mcap (the job's recording, streamer/recording: built
from the trace after the job) to the output folder and prints a summary.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import can

from planner.config import CellConfig, load_cell
from planner.errors import PlanningError
from planner.job import Job, job_from_dict, job_to_dict, load_job
from planner.plan import plan_job
from planner.trajectory import PvtTrajectory
from streamer.core.coordinator import Coordinator
from streamer.recording.mcap_io import write_mcap
from streamer.recording.model import build_recording
from streamer.report import build_report, plot_motion, write_report
from streamer.runtime.virtual import VirtualRuntime
from streamer.splice_planners import make_stop_planner

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_JOB = ROOT / "configs" / "jobs" / "demo-path.toml"
IN_PROCESS_SYNC_GAP_FACTOR = 3.0


@dataclass(frozen=True)
class DemoResult:
    report: dict[str, Any]
    trajectory: PvtTrajectory
    out_dir: Path


def fit_job_to_cell(job: Job, cell: CellConfig, *, repeat: bool = False) -> Job:
    """The job on the cell's axes. A job whose axes the cell has keeps them (a job for j5 and j6 moves j5 and
    j6 of a 6-axis cell, the others stand), unless `repeat` (`pvt demo --axes N`) asks for every axis of the
    cell to move. Else, or when the cell lacks one of the job's axes, the job is run on all N axes of the
    cell: axis i like the job's axis (i mod len(job.axes)), positions clipped to that axis' position limits,
    and every per-axis list of the job (scales, tolerances, limits, a velocity move's velocities, ramp times)
    taken from that same axis of the job."""
    names = cell.axis_names()
    if set(job.axes) <= set(names) and (not repeat or len(job.axes) == len(names)):
        return job
    body = job_to_dict(job)
    src = list(job.axes)

    def column(rows: list[list[float]]) -> list[list[float]]:
        out = []
        for row in rows:
            new = []
            for i, ax in enumerate(cell.axes):
                v = float(row[i % len(src)])
                new.append(min(max(v, ax.position_min), ax.position_max))
            out.append(new)
        return out

    def per_axis(values: Any) -> Any:
        """A per-axis list fitted to the cell's axes; a scalar (one value for every axis) as it is."""
        if isinstance(values, list):
            return [values[i % len(src)] for i in range(len(names))]
        return values

    body["axes"] = list(names)
    for key in ("waypoints", "positions"):
        if key in body:
            body[key] = column(body[key])
    for key in ("target", "start"):  # a move's target and its assumed start: one position per axis
        if isinstance(body.get(key), list):
            body[key] = column([body[key]])[0]
    if "velocities" in body:
        body["velocities"] = column(body["velocities"])
    for key in ("velocity_scale", "acceleration_scale", "path_tolerance", "velocity"):
        if key in body:
            body[key] = per_axis(body[key])
    for group in ("limits", "ramps"):  # {name: one value or a per-axis list}
        if isinstance(body.get(group), dict):
            body[group] = {key: per_axis(values) for key, values in body[group].items()}
    body.pop("job_id", None)
    return job_from_dict(body, cell)


class KeptChunks:
    """An extender (the next chunk of an open-ended velocity stream) that keeps every chunk it gave the core,
    in order: the demo judges, plots and records the whole stream the core sent (`whole_stream`), not only
    its first chunk. A demo's velocity job ends by itself (the chunk that brakes before the software position
    limits), so what it keeps is bounded by the axes' travel."""

    def __init__(self, extend: Any) -> None:
        self.extend = extend
        self.chunks: list[PvtTrajectory] = []

    def __call__(self, traj: Any) -> Any:
        chunk = self.extend(traj)
        if chunk is not None:
            self.chunks.append(chunk)
        return chunk


def whole_stream(first: PvtTrajectory, chunks: list[PvtTrajectory], core: Coordinator) -> PvtTrajectory:
    """The stream the core sent as one trajectory: the job's plan, then every chunk the core appended
    (`core.pieces`: (start ms, plan) each), knot 0 of a chunk being the last knot before it. The plan at every
    ms and the knots are joined; the stats are the worst of the pieces'. `first` alone for a closed job."""
    pieces = core.pieces
    dropped = core.pieces_dropped  # an endless job forgets its oldest pieces: pieces[0] is piece `dropped`
    used = chunks[:max(0, dropped + len(pieces) - 1)]
    if not used:
        return first
    import numpy as np

    from planner.motion.reference import Reference

    parts = [first, *used]
    offsets = {dropped + j: offset for j, (offset, _plan) in enumerate(pieces)}
    at = first.duration_ms
    for g, (part, before) in enumerate(zip(used, parts, strict=False), start=1):
        offset = offsets.get(g, at)
        if offset != at or not np.array_equal(part.positions[:, 0], before.positions[:, -1]):
            raise ValueError(f"the core appended a piece at {offset} ms; the chunk kept there does not follow the "
                             f"stream before it (ends at {at} ms, last knot {before.positions[:, -1].tolist()})")
        at += part.duration_ms
    refs = [p.plan for p in parts]
    plan = Reference(
        positions=np.concatenate([refs[0].positions] + [r.positions[:, 1:] for r in refs[1:]], axis=1),
        velocities=np.concatenate([refs[0].velocities] + [r.velocities[:, 1:] for r in refs[1:]], axis=1),
        acc_left=np.concatenate([refs[0].acc_left] + [r.acc_left[:, 1:] for r in refs[1:]], axis=1),
        acc_right=np.concatenate([refs[0].acc_right] + [r.acc_right[:, 1:] for r in refs[1:]], axis=1),
        breaks=np.array([p.duration_ms for p in parts[:-1]], dtype=np.int64).cumsum(),
    )
    stats = tuple(
        replace(max((p.stats[i] for p in parts), key=lambda st: st.max_deviation_counts),
                peak_velocity=max(p.stats[i].peak_velocity for p in parts),
                peak_velocity_rpm=max(p.stats[i].peak_velocity_rpm for p in parts))
        for i in range(first.n_axes))
    last = parts[-1]
    return PvtTrajectory(
        kind=first.kind, axis_names=first.axis_names, node_ids=first.node_ids,
        dt_ms=np.concatenate([p.dt_ms for p in parts]),
        positions=np.concatenate([first.positions] + [p.positions[:, 1:] for p in parts[1:]], axis=1),
        velocities=np.concatenate([first.velocities] + [p.velocities[:, 1:] for p in parts[1:]], axis=1),
        counts_per_unit=first.counts_per_unit, counts_per_rev=first.counts_per_rev,
        tolerance_counts=max(p.tolerance_counts for p in parts), plan=plan, stats=stats,
        info={**first.info, "chunks": float(len(parts))}, open_end=last.open_end)


def prepare(
    config: Path | None = None,
    job_path: Path | None = None,
    *,
    axes: int | None = None,
    sync_ms: int | None = None,
    bus: str | None = None,
    bitrate: int | None = None,
    commissioned: bool = False,
) -> tuple[CellConfig, Job, PvtTrajectory]:
    """The demo's cell (with the options applied), job (fitted to the cell) and plan. `commissioned`: first
    measure what the plan depends on of the simulated drives (`commission`), as `pvt demo` does."""
    cell = load_cell(config or ROOT / "configs" / "demo.toml")
    try:
        loaded = load_job(job_path or DEFAULT_JOB, cell)  # validated against the cell as configured
    except PlanningError as e:
        if job_path is not None:
            raise
        # the user gave no job: say that the default one was used, and why it does not fit their cell
        names = ", ".join(f"{a.name} [{a.unit}]" for a in cell.axes)
        raise PlanningError(
            e.code,
            f"no --job given, so the default demo job {_shown(DEFAULT_JOB)} was used; it is written for the "
            f"demo cell (6 axes j1..j6, rad) and does not fit cell {cell.name!r} ({len(cell.axes)} axes: {names}): "
            f"{e.message}. Give a job for this cell with --job FILE",
            path=e.path,
        ) from None
    if axes is not None:
        cell = cell.with_axes(axes)
    if sync_ms is not None:
        cell = replace(cell, sync_period_ms=sync_ms)
    if bus is not None or bitrate is not None:
        cell = replace(cell, bus=cell.bus.with_spec(bus, bitrate))
    if commissioned:
        cell = commission(cell)
    job = fit_job_to_cell(loaded, cell, repeat=axes is not None)
    traj = plan_job(job, cell)
    return cell, job, traj


def commission(cell: CellConfig) -> CellConfig:
    """The cell with each simulated drive's rounding of its position demand in [axis.probed], measured by
    the standstill probe (`pvt probe --fast`) in virtual time, where the cell does not state it: the plan
    is encoded for it (a drive that truncates needs other knots than one that rounds to nearest), as the
    job service plans with the readings it measures at start-up. The other open points stay for the
    runtime's own probe at configuration (the TPDO latency, for one, is a property of the run's time)."""
    from bus.sim.virtual import VirtualCell

    if all(a.probed.rounding is not None for a in cell.axes if a.profile == "epos-ipm"):
        return cell
    rt = VirtualRuntime(cell, vcell=VirtualCell(cell))
    rt.ensure_readings()
    found = rt.settings.readings
    return replace(cell, axes=tuple(
        replace(a, probed=replace(a.probed, rounding=found[a.node_id].rounding)) if a.node_id in found else a
        for a in cell.axes))


def _shown(path: Path) -> str:
    """`path` relative to the working directory when it is below it (as the user would type it)."""
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def start_positions(cell: CellConfig, traj: PvtTrajectory) -> dict[int, float]:
    """Where the simulated drives stand at power-on: the plan's start, in counts."""
    return {int(n): float(traj.positions[i, 0]) for i, n in enumerate(traj.node_ids)}


def run_fast(cell: CellConfig, traj: PvtTrajectory, out: Path,
             on_sync: Any = None, readings_out: dict[int, Any] | None = None,
             on_start: Any = None, *, plot: bool = True) -> tuple[dict[str, Any], Any]:
    """The job in virtual time. `on_start(plan, core, trace)`: once, at the job's first SYNC (the live view
    follows the trace from there). `plot=False`: no motion.png (see `_finish`)."""
    from bus.sim.virtual import VirtualCell

    out.mkdir(parents=True, exist_ok=True)
    vcell = VirtualCell(cell, initial_positions=start_positions(cell, traj))
    with can.Logger(str(out / "bus.log")) as logger:
        def log(t: float, cob_id: int, data: bytes) -> None:
            logger.on_message_received(
                can.Message(timestamp=t, arbitration_id=cob_id, data=data, is_extended_id=False, channel="vcan0")
            )

        rt = VirtualRuntime(cell, vcell=vcell, log=log)
        wall0 = time.time()  # virtual time starts at 0: the recording's wall clock is the run's start
        from planner.motion.travel import extend_velocity

        kept = KeptChunks(extend_velocity)
        started: list[Any] = []

        def each_sync(core: Coordinator, n: int) -> None:
            if on_start is not None and not started:
                started.append(core)
                on_start(traj, core, rt.trace)
            if on_sync is not None:
                on_sync(core, n)

        result = rt.run(traj, stop_planner=make_stop_planner(cell, traj), on_sync=each_sync, extender=kept)
        traj = whole_stream(traj, kept.chunks, result.coordinator)
    if readings_out is not None:
        readings_out.update(rt.settings.readings)
    epoch = wall0 + result.trace.sync_times.get(result.first_sync, 0.0)
    return _finish(cell, traj, result.coordinator, result.trace, result.first_sync, result.last_sync, out,
                   rt.settings.readings, epoch_s=epoch, plot=plot)


def _finish(cell: CellConfig, traj: PvtTrajectory, core: Coordinator, trace: Any, first: int, last: int,
            out: Path, readings: Any = None, *, epoch_s: float | None = None,
            plot: bool = True) -> tuple[dict[str, Any], Any]:
    """report.json, motion.png (unless not `plot`: matplotlib's import and one drawing cost 2.5-3.7 s of CPU
    here, most of a 3-axis job's own time; `pvt demo --no-plot`), job.mcap."""
    core_report = core.report()
    report_setpoints = {n: core.setpoints(n) for n in traj.node_ids}
    report = build_report(traj, core_report, trace, sync_period_ms=cell.sync_period_ms,
                          first_sync=first, last_sync=last, readings=readings, time_stamp=cell.time_stamp,
                          setpoints=report_setpoints)
    write_report(report, out / "report.json")
    if not plot:
        (out / "motion.png").unlink(missing_ok=True)  # not a plot of an earlier run beside this report
    else:
        plot_motion(traj, trace, report, out / "motion.png", sync_period_ms=cell.sync_period_ms,
                    underflow_watermark=cell.drive.underflow_warning, overflow_watermark=cell.drive.overflow_warning,
                    units=[cell.axis(name).unit for name in traj.axis_names], setpoints=report_setpoints,
                    feedback=core_report.feedback)
    recording = build_recording(traj, trace, report, first_sync=first, start_sync=core_report.start_sync,
                                sync_period_ms=cell.sync_period_ms, job_id="demo", cell=cell.name, epoch_s=epoch_s,
                                underflow_watermark=cell.drive.underflow_warning,
                                overflow_watermark=cell.drive.overflow_warning, feedback=core_report.feedback)
    write_mcap(recording, out / "job.mcap")
    return report, trace


@contextlib.contextmanager
def realtime_cell(cell: CellConfig, traj: PvtTrajectory | None = None, *,
                  external_drives: bool = False) -> Iterator[Any]:
    """The simulated drives in a process of their own (`pvt sim`, unless `external_drives`: they run
    elsewhere on the cell's bus; bus/sim/process.py) and a configured master adapter whose cycle engine owns
    the bus (bus/engine.py). Yields the adapter; its `cell` is the cell on the bus actually used."""
    from bus.engine import engine_spec
    from bus.network import MasterAdapter
    from bus.sim.process import drives_process, joining_bus

    run_cell = cell if external_drives else joining_bus(cell)
    drives = contextlib.nullcontext() if external_drives else drives_process(
        run_cell, positions=start_positions(run_cell, traj) if traj is not None else None)
    with drives:
        bus = run_cell.bus
        adapter = MasterAdapter(None, run_cell, engine=engine_spec(bus.interface, str(bus.channel), bus.bitrate))
        try:
            adapter.configure_drives()
            yield adapter
        finally:
            adapter.close()


def run_realtime(cell: CellConfig, traj: PvtTrajectory, out: Path, *, external_drives: bool = False,
                 on_change: Any = None, cancel: threading.Event | None = None, job: Job | None = None,
                 on_engine: Any = None, on_runtime: Any = None, plot: bool = True) -> tuple[dict[str, Any], Any]:
    """The job in real time: the drives in a process of their own (or `external_drives` on the cell's bus),
    the cycle engine in another, the core here. The drives' readings are measured first (the standstill
    probe); when `job` is given and a drive rounds its demand otherwise than the plan assumed, the job is
    planned again for the drives on the bus (whatever the master learns about a drive, it learns from it)."""
    from streamer.runtime.extension import PrefetchExtender
    from streamer.runtime.realtime import RealtimeRuntime

    out.mkdir(parents=True, exist_ok=True)
    with realtime_cell(cell, traj, external_drives=external_drives) as adapter:
        rt = RealtimeRuntime(adapter.cell, adapter, log_path=out / "bus.log")
        if on_runtime is not None:
            on_runtime(rt)  # the live view reads its `live` (the running job)
        try:
            rt.ensure_readings()
            if job is not None:
                measured = replace(cell, axes=tuple(
                    replace(a, probed=replace(a.probed, rounding=rt.known[a.node_id].rounding))
                    if a.probed.rounding is None and a.node_id in rt.known else a for a in cell.axes))
                if measured != cell:
                    cell = measured
                    traj = plan_job(job, cell)
            if on_engine is not None:
                on_engine(adapter)
            prefetch = PrefetchExtender()
            prefetch.prefetch(traj)  # the first chunk's successor, while the drives are primed
            kept = KeptChunks(prefetch)
            try:
                result = rt.run(traj, stop_planner=make_stop_planner(cell, traj), on_change=on_change,
                                cancel=cancel, extender=kept)
            finally:
                prefetch.close()
        finally:
            rt.close()
    traj = whole_stream(traj, kept.chunks, result.coordinator)
    time.sleep(0.05)
    return _finish(cell, traj, result.coordinator, result.trace, result.first_sync, result.last_sync, out,
                   rt.settings.readings, plot=plot)
