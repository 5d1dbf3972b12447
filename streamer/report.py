"""The job report (report.json), the motion plot (motion.png) and the candump cross-check.

Built from three sources that do not trust each other: the plan, what the drives reported every SYNC
(`JobTrace`) and the core's own accounting (`Coordinator.report()`). The drive's deviation from the plan
is measured two ways and the larger reported: at every ms from the records streamed, through the drive's
interpolation (`decode_candump` proves the wire carried exactly these), and at every SYNC from the demand
the drive reported, at the SYNC the core attributed it to (streamer/core/attribution.py). A cyclic axis
is measured the same two ways, from its set points (`decode_setpoints`).
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from bus.cob import RPDO2_BASE
from bus.profile import SetpointSlot
from planner.config import DEFAULT_UNIT
from planner.encoding import cyclic
from planner.encoding.record import PvtRecord, unpack
from planner.readings import DriveReadings
from planner.trajectory import PvtTrajectory
from streamer.core.coordinator import JobReport
from streamer.core.drive_time import DriveTime
from streamer.core.settings import REFERENCE_READINGS
from streamer.runtime.trace import JobTrace, positions_by_sync


def _plan_index(sync: int, start_sync: int | None, period_ms: int, duration_ms: int) -> int:
    if start_sync is None or sync <= start_sync:
        return 0
    return min((sync - start_sync) * period_ms, duration_ms)


def _clock_ms(sync: int, k: int, t_start: float | None, sync_times: Mapping[int, float], duration_ms: int) -> float:
    """The plan ms a drive with its own clock (or one timed by the SYNCs it receives) has reached at SYNC `sync`:
    the time that SYNC left after the start SYNC (such a drive runs on time, not on SYNC counts: a SYNC 4 ms late
    found it 4 ticks further on, which the SYNC count's plan ms missed by 19-70 counts in virtual time and
    bench_realtime counted as a missed guarantee), else the SYNC count's plan ms k."""
    t = sync_times.get(sync)
    if t is None or t_start is None:
        return float(k)
    return min(max(0.0, (t - t_start) * 1000.0), float(duration_ms))


def build_report(
    traj: PvtTrajectory,
    core: JobReport,
    trace: JobTrace,
    *,
    sync_period_ms: int,
    first_sync: int,
    last_sync: int,
    faults: Sequence[Mapping[str, Any]] = (),
    readings: Mapping[int, DriveReadings] | None = None,
    time_stamp: bool = False,
    setpoints: Mapping[int, cyclic.Setpoints | None] | None = None,
) -> dict[str, Any]:
    """`readings`: what the master knew of each drive (rounding: the plan is rounded as the drive rounds;
    an own clock: the demand is compared with the plan at the drive's own time, and against SYNC time
    within what the clock's stated error explains). `setpoints`: what the core sent each cyclic axis
    (`Coordinator.setpoints`)."""
    outcome = core.outcome
    result = outcome.result.value if outcome is not None else core.state
    by_rounding = {tz: (traj.planned_demand(tz), np.abs(traj.deviation(tz)).max(axis=1)) for tz in (False, True)}
    axes_out: list[dict[str, Any]] = []
    telemetry = {t.node_id: t for t in core.axes}
    t_start = trace.sync_times.get(core.start_sync) if core.start_sync is not None else None
    for i, (name, node) in enumerate(zip(traj.axis_names, traj.node_ids, strict=True)):
        ax = trace.axes[node]
        tel = telemetry.get(node)
        r = (readings or {}).get(node, REFERENCE_READINGS)
        # the plan rounded as the drive rounds; unknown rounding: the worse of both readings
        tz = r.rounding == "toward_zero"
        planned, encoder_dev = by_rounding[tz]
        if r.rounding is None:
            encoder_dev = np.maximum(by_rounding[False][1], by_rounding[True][1])
        interp = traj.stats[i].interpolation
        # the core's clock of the drive: its own, or timed by the SYNCs it receives (0x1006 absent), or locked
        clock = DriveTime.of_reading(r, sync_period_ms, cyclic=interp != "pvt", time_stamped=time_stamp)
        own_clock = not clock.exact
        sampled_dev = explained = unexplained = 0
        log = core.feedback.get(node)
        for s, d, late_us in zip(log.sync if log is not None else (), log.demand if log is not None else (),
                                 log.late if log is not None else (), strict=True):
            if core.start_sync is not None and s > core.start_sync + traj.duration_ms // sync_period_ms + 1:
                break  # after the plan's end: the stop or hold is not the plan
            k = _plan_index(int(s), core.start_sync, sync_period_ms, traj.duration_ms)
            dev = abs(int(d) - int(planned[i, k]))
            sampled_dev = max(sampled_dev, dev)
            if own_clock:
                lo, hi = clock.plan_window(_clock_ms(int(s), k, t_start, trace.sync_times, traj.duration_ms),
                                           int(late_us), traj.duration_ms)
                window = planned[i, lo:hi + 1]
                explained = max(explained, int(np.abs(window - planned[i, k]).max()))
                outside = max(0, int(window.min()) - int(d), int(d) - int(window.max()))
                unexplained = max(unexplained, outside - traj.tolerance_counts)
        sent = (setpoints or {}).get(node)
        if interp != "pvt":
            # a cyclic axis: its drive interpolates the set points it was sent (up to a cancel's stop)
            cut = core.cancel.get("time_ms") if core.cancel.get("stop") == "trajectory" else None
            encoder_dev = np.zeros(traj.n_axes, dtype=np.int64)
            if sent is not None:
                encoder_dev[i] = cyclic.deviation(traj.plan.positions[i], sent, interp, until_ms=cut)[0]
        if own_clock:
            # the deviation proper is the one at the drive's own time (the core checks every TPDO2 there)
            drive_time_dev = max(int(encoder_dev[i]), tel.max_demand_error_counts if tel else 0)
        else:
            drive_time_dev = max(int(encoder_dev[i]), sampled_dev)
        final_actual = trace.final_actual(node)
        target = int(traj.positions[i, -1])
        last_active = log.last_active_sync if log is not None else None
        end_sync = last_active + 1 if last_active is not None else None
        if interp != "pvt" and tel is not None:
            end_sync = tel.end_sync
        axes_out.append(
            {
                "name": name,
                "node_id": node,
                "start_sync": core.start_sync,
                "end_sync": end_sync,
                "interpolation": interp,
                "points_sent": tel.points_sent if tel else 0,
                "min_fifo": tel.min_fifo if tel else None,
                "max_fifo": tel.max_fifo if tel else None,
                "max_deviation_counts": int(drive_time_dev),
                "max_following_error_counts": ax.max_following_error(),
                "final_position_error_counts": (final_actual - target) if final_actual is not None else None,
                "underflow_warnings": tel.underflow_warnings if tel else 0,
                "overflow_warnings": tel.overflow_warnings if tel else 0,
                "resends": tel.resends if tel else 0,
                "errors": list(tel.errors) if tel else [],
                **({"drive_clock": "own", "max_deviation_sync_time_counts": sampled_dev,
                    "clock_explained_counts": explained, "unexplained_counts": max(0, unexplained)}
                   if own_clock else {}),
            }
        )
    fault_list = list(faults)
    if outcome is not None and outcome.code is not None:
        fault_list.append(
            {"code": outcome.code, "node": outcome.node, "message": outcome.message, "sync": outcome.sync}
        )
    return {
        "result": result,
        "message": outcome.message if outcome is not None else "",
        "sync_period_ms": sync_period_ms,
        "duration_s": traj.duration_s,
        "planned_points": traj.n_points,
        "syncs": last_sync - first_sync + 1,
        "job_start_s": min(trace.sync_times.values()) if trace.sync_times else None,
        "frames": trace.frames,
        "frames_per_point": core.frames_per_point,
        "bus_load_peak": round(trace.bus_load_peak(), 4),
        "faults": fault_list,
        "axes": axes_out,
    }


def write_report(report: Mapping[str, Any], path: Path) -> None:
    path.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")


def decode_candump(path: Path, node_ids: Iterable[int], since_s: float | None = None) -> dict[int, list[PvtRecord]]:
    """The 0x20C1 records sent to each node, in bus order, read back from a candump (-L) log; from
    `since_s` on (the report's `job_start_s`: the standstill probe's records before the job are not the
    job's)."""
    import can

    wanted = {RPDO2_BASE + n: n for n in node_ids}
    out: dict[int, list[PvtRecord]] = {n: [] for n in wanted.values()}
    with can.LogReader(str(path)) as reader:
        for msg in reader:
            node = wanted.get(msg.arbitration_id)
            if node is not None and (since_s is None or msg.timestamp >= since_s - 1e-6):
                out[node].append(unpack(bytes(msg.data)))
    return out


def decode_setpoints(path: Path, slots: Mapping[int, SetpointSlot], start: Mapping[int, int],
                     since_s: float | None = None) -> dict[int, list[tuple[float, int, int]]]:
    """(time, position counts, velocity counts/s) of every set point frame sent to each cyclic node, in bus
    order, read back from a candump (-L) log from `since_s` on. 16-bit positions are rebuilt as the drive
    does, nearest the previous set point (the first nearest the node's `start`)."""
    import can

    by_cob: dict[int, list[SetpointSlot]] = {}
    for slot in slots.values():
        by_cob.setdefault(slot.cob_id, []).append(slot)
    prev = dict(start)
    out: dict[int, list[tuple[float, int, int]]] = {n: [] for n in slots}
    with can.LogReader(str(path)) as reader:
        for msg in reader:
            members = by_cob.get(msg.arbitration_id)
            if members is None or (since_s is not None and msg.timestamp < since_s - 1e-6):
                continue
            data = bytes(msg.data)
            for slot in members:
                o = slot.offset
                pb, vb = slot.position_bits // 8, slot.velocity_bits // 8
                raw = int.from_bytes(data[o:o + pb], "little", signed=pb == 4)
                if pb == 2:
                    base = prev.get(slot.node, 0)
                    raw = base + ((raw - base + 0x8000) & 0xFFFF) - 0x8000
                vel = int.from_bytes(data[o + pb:o + pb + vb], "little", signed=True) if vb else 0
                prev[slot.node] = raw
                out[slot.node].append((msg.timestamp, raw, vel))
    return out


def plot_motion(
    traj: PvtTrajectory,
    trace: JobTrace,
    report: Mapping[str, Any],
    path: Path,
    *,
    sync_period_ms: int,
    underflow_watermark: int,
    overflow_watermark: int,
    units: Sequence[str] | None = None,
    setpoints: Mapping[int, cyclic.Setpoints | None] | None = None,
    feedback: Mapping[int, Any] | None = None,
) -> None:
    """Per axis: commanded vs actual position and their difference; FIFO fill with both watermarks, or for
    an axis fed one set point per SYNC, its drive's interpolation minus the plan at every ms. `units`: each
    axis' user unit (the cell's `unit`, default rad) for the position labels. `feedback`: per node, the
    TPDO2 samples at the SYNC the core attributed them to (`JobReport.feedback`, as the report measures);
    a node without one is plotted by the samples' arrival tags (the trace)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = traj.n_axes
    fig, grid = plt.subplots(n, 2, figsize=(13, 2.2 * n + 1.0), squeeze=False, sharex="col")
    start = next((a["start_sync"] for a in report["axes"] if a["start_sync"] is not None), None)
    period_s = sync_period_ms / 1000.0
    sync0 = min(trace.sync_times) if trace.sync_times else 0
    planned = traj.planned_demand()
    for i, (name, node) in enumerate(zip(traj.axis_names, traj.node_ids, strict=True)):
        ax = trace.axes[node]
        cpu = float(traj.counts_per_unit[i])
        left, right = grid[i][0], grid[i][1]
        pos_sync, actual_in, demand_in = positions_by_sync(ax, (feedback or {}).get(node))
        ts = np.array([(s - sync0) * period_s for s in pos_sync])
        actual = np.array(actual_in, dtype=float)
        demand = np.array(demand_in, dtype=float)
        idx = [_plan_index(s, start, sync_period_ms, traj.duration_ms) for s in pos_sync]
        commanded = planned[i, idx].astype(float) if len(idx) else np.array([])
        left.plot(ts, commanded / cpu, color="#1f77b4", lw=1.6, label="commanded (plan)")
        left.plot(ts, actual / cpu, color="#ff7f0e", lw=1.0, ls="--", label="actual 0x6064")
        unit = units[i] if units is not None and i < len(units) else DEFAULT_UNIT
        left.set_ylabel(f"{name}\nposition [{unit}]")
        twin = left.twinx()
        twin.plot(ts, actual - commanded, color="#d62728", lw=0.8, alpha=0.7, label="actual - commanded")
        twin.set_ylabel("diff [counts]", color="#d62728")
        twin.tick_params(axis="y", colors="#d62728")
        if start is not None:
            left.axvline((start - sync0) * period_s, color="green", lw=0.8, ls=":", label="start SYNC")
        if i == 0:
            h1, l1 = left.get_legend_handles_labels()
            h2, l2 = twin.get_legend_handles_labels()
            left.legend(h1 + h2, l1 + l2, loc="upper left", fontsize=7, ncol=2)
        interp = traj.stats[i].interpolation
        sent = (setpoints or {}).get(node)
        if interp != "pvt":
            t0 = (start - sync0) * period_s if start is not None else 0.0
            if sent is not None:
                curve = cyclic.drive_curve(sent, interp)
                plan = traj.plan.positions[i]
                m = min(curve.size, plan.size)
                tm = t0 + np.arange(m) / 1000.0
                right.plot(tm, curve[:m] - plan[:m], color="#2ca02c", lw=0.8,
                           label=f"drive's {interp} interpolation - plan")
            tol = traj.tolerance_counts
            right.axhline(tol, color="#d62728", lw=0.8, ls="--", label=f"tolerance +-{tol}")
            right.axhline(-tol, color="#d62728", lw=0.8, ls="--")
            right.set_ylabel("counts")
            right.legend(loc="upper right", fontsize=7)
            continue
        tf = np.array([(s - sync0) * period_s for s in ax.fill_sync])
        right.step(tf, list(ax.fill), where="post", color="#2ca02c", lw=1.0, label="FIFO fill")
        right.axhline(underflow_watermark, color="#d62728", lw=0.8, ls="--",
                      label=f"underflow wm {underflow_watermark}")
        right.axhline(overflow_watermark, color="#9467bd", lw=0.8, ls="--",
                      label=f"overflow wm {overflow_watermark}")
        if start is not None:
            right.axvline((start - sync0) * period_s, color="green", lw=0.8, ls=":", label="start SYNC")
        right.set_ylim(0, 66)
        right.set_ylabel("records")
        if i == 0:
            right.legend(loc="upper right", fontsize=7, ncol=2)
        del demand
    grid[-1][0].set_xlabel("time [s]")
    grid[-1][1].set_xlabel("time [s]")
    fig.suptitle(
        f"{report['result'].upper()}: {n} axes, {report['duration_s']:.2f} s, SYNC {sync_period_ms} ms, "
        f"peak bus load {100 * report['bus_load_peak']:.1f}%"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
