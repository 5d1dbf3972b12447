"""Exports of a job's recording: CSV (one row per SYNC), the interactive HTML report, a text summary.

The HTML report is `render_report` (html.py) fed with the job's series: per axis one panel of
positions (planned, actual and the drive's demand in user units on the left scale, the following
error in counts on the right) and one of the FIFO fill with both watermarks (or the set point of a
cyclic drive, when there is one); the job's events are the markers.
"""

from __future__ import annotations

import csv
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from streamer.recording.html import (
    Figure,
    Level,
    Marker,
    PanelSpec,
    ReportOptions,
    Series,
    build_figure,
    figure_to_html,
)
from streamer.recording.model import JobRecording, merge_syncs

# the CSV's per-axis columns, in order; a column nobody has a value for is left out
CSV_FIELDS = ("planned", "actual", "demand", "following_error", "fifo_fill", "setpoint")


def csv_columns(rec: JobRecording) -> list[str]:
    cols = ["time_s", "sync"]
    for a in rec.axes:
        s = rec.samples[a.name]
        cols += [f"{a.name}.{f}" for f in CSV_FIELDS if any(v is not None for v in s.column(f))]
    return cols


def write_csv(rec: JobRecording, path: Path) -> int:
    """Per SYNC one row: time_s (since the job's first SYNC), sync, then per axis `<axis>.<field>` in
    counts (records for fifo_fill); empty where the axis had no sample. Returns the number of rows."""
    cols = csv_columns(rec)
    index = {a.name: {sync: k for k, sync in enumerate(rec.samples[a.name].sync)} for a in rec.axes}
    rows = merge_syncs([rec.samples[a.name] for a in rec.axes])
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(cols)
        for sync, t in rows:
            values: dict[str, Any] = {"time_s": f"{t:.6f}", "sync": sync}
            for a in rec.axes:
                k = index[a.name].get(sync)
                if k is None:
                    continue
                s = rec.samples[a.name]
                for field_name in CSV_FIELDS:
                    v = s.column(field_name)[k]
                    if v is not None:
                        values[f"{a.name}.{field_name}"] = v
            w.writerow([values.get(c, "") for c in cols])
    return len(rows)


def job_markers(rec: JobRecording) -> list[Marker]:
    """The job's events as markers; per-state changes get a short label, faults and EMCYs a loud one."""
    out = []
    for e in rec.events:
        short = e.state if e.kind == "state" and e.state else (e.code or e.kind)
        out.append(Marker(e.t, e.label(), e.kind, short or e.kind))
    return out


def job_series(rec: JobRecording) -> tuple[list[Series], ReportOptions]:
    series: list[Series] = []
    levels: list[Level] = []
    panels: list[PanelSpec] = []
    for a in rec.axes:
        s = rec.samples[a.name]
        cpu = a.counts_per_unit

        def units(values: Sequence[int | None], cpu: float = cpu) -> list[float | None]:
            return [None if v is None else v / cpu for v in values]

        pos = f"{a.name}: position"
        series += [
            Series(f"{a.name} planned", pos, s.t, units(s.planned), unit="unit", color="#1f77b4", group=a.name),
            Series(f"{a.name} actual 0x6064", pos, s.t, units(s.actual), unit="unit", color="#ff7f0e",
                   group=a.name),
            Series(f"{a.name} demand 0x6062", pos, s.t, units(s.demand), unit="unit", color="#9467bd",
                   dash="dot", group=a.name),
            Series(f"{a.name} following error", pos, s.t, list(s.following_error), side="right", unit="counts",
                   color="#d62728", group=a.name),
        ]
        panels.append(PanelSpec(pos, "position [unit]", "following error [counts]"))
        has_fill = any(v is not None for v in s.fifo_fill)
        has_setpoint = any(v is not None for v in s.setpoint)
        if has_fill:
            fifo = f"{a.name}: FIFO"
            series.append(Series(f"{a.name} FIFO fill", fifo, s.t, list(s.fifo_fill), unit="records", hold=True,
                                 color="#2ca02c", group=a.name))
            if rec.underflow_watermark is not None:
                levels.append(Level(f"{a.name} underflow watermark {rec.underflow_watermark}", fifo,
                                    rec.underflow_watermark, color="#d62728"))
            if rec.overflow_watermark is not None:
                levels.append(Level(f"{a.name} overflow watermark {rec.overflow_watermark}", fifo,
                                    rec.overflow_watermark, color="#9467bd"))
            panels.append(PanelSpec(fifo, "FIFO fill [records]", left_range=(-1.0, rec.fifo_size + 2.0)))
        if has_setpoint:
            series.append(Series(f"{a.name} set point", pos, s.t, units(s.setpoint), unit="unit", color="#17becf",
                                 dash="dash", group=a.name))
    report = rec.report
    bits = [f"result {rec.result or report.get('result', '?')}", f"SYNC {rec.sync_period_ms} ms",
            f"start SYNC {rec.start_sync}", f"{rec.duration_s:.2f} s recorded", f"{len(rec.frames)} frames"]
    if "bus_load_peak" in report:
        bits.append(f"peak bus load {100 * float(report['bus_load_peak']):.1f}%")
    options = ReportOptions(subtitle=", ".join(bits), levels=tuple(levels), panels=tuple(panels),
                            time_title="time since the job's first SYNC [s]")
    return series, options


def job_title(rec: JobRecording) -> str:
    who = f"job {rec.job_id}" if rec.job_id else "job"
    where = f" on cell {rec.cell}" if rec.cell else ""
    return f"pvt {who}{where}: {len(rec.axes)} axes"


def job_figure(rec: JobRecording) -> Figure:
    series, options = job_series(rec)
    return build_figure(job_title(rec), series, job_markers(rec), options)


def write_html(rec: JobRecording, path: Path) -> Figure:
    """The interactive report of the job (self-contained HTML); returns the figure drawn."""
    fig = job_figure(rec)
    Path(path).write_text(figure_to_html(fig), encoding="utf-8")
    return fig


def summary(rec: JobRecording) -> dict[str, Any]:
    """What `pvt jobs show` prints: identity, counts, per-axis numbers from the samples, events."""
    topics: dict[str, int] = {f"/axis/{a.name}": len(rec.samples[a.name]) for a in rec.axes}
    topics["/job/events"] = len(rec.events)
    topics["/can/frames"] = len(rec.frames)
    drive = rec.drive
    if drive is not None:
        for n, r in sorted(drive.nodes.items()):
            topics[f"/recorder/{n}"] = len(r.t)
    out: dict[str, Any] = {
        "job_id": rec.job_id,
        "cell": rec.cell,
        "result": rec.result,
        "sync_period_ms": rec.sync_period_ms,
        "first_sync": rec.first_sync,
        "start_sync": rec.start_sync,
        "epoch_s": rec.epoch_s,
        "duration_s": round(rec.duration_s, 6),
        "frames": len(rec.frames),
        "frames_dropped": rec.frames_dropped,
        "messages": topics,
        "axes": rec.axis_summary(),
        "events": [{"t": round(e.t, 6), "sync": e.sync, "kind": e.kind, "label": e.label()} for e in rec.events],
    }
    if drive is not None:
        out["drive_recording"] = drive.summary()
    return out


def report_axes(report: Mapping[str, Any]) -> dict[str, Mapping[str, Any]]:
    return {str(a.get("name")): a for a in report.get("axes", []) if isinstance(a, Mapping)}
