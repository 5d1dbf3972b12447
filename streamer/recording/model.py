"""A job's recording in memory: per SYNC and axis samples, the job's events, the CAN frames.

Theory of operation. `build_recording` turns a runtime's `JobTrace` (record=True), the plan and the report
into one `JobRecording`, after the job, off the streaming thread. The MCAP writer, the CSV and HTML
exports and `pvt jobs show` read this one shape, and `mcap_io.read_mcap` gives it back from a file.
Times: `t` in seconds since the job's first SYNC, `epoch_s` the wall-clock time of that SYNC; positions
in counts. Per axis and SYNC (`AxisSamples`, columnar): planned (the plan's demand rounded as the drive
rounds; the original plan after a cancel), actual, demand, following_error, fifo_fill or setpoint
(either may be absent), statusword and buffer_status. A job with a `record` section also carries its
drives' own recordings (`drive`, a `DriveRecording`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from streamer.recording.drive import DriveRecording
from streamer.runtime.trace import positions_by_sync

FORMAT_VERSION = 1

# event kinds (the `kind` of a RecordedEvent)
STATE = "state"  # a job state change (configuring -> priming -> ... -> done / cancelled / failed)
START = "start"  # the start SYNC: every axis entered ip mode active
FAULT = "fault"  # the job failed: code, node, message
CANCEL = "cancel"  # a cancel request reached the streamer core
EMCY = "emcy"
HEARTBEAT_LOST = "heartbeat_lost"
BOOTUP = "bootup"
SEND_FAILED = "send_failed"
ADAPTER_ERROR = "adapter_error"
EVENT_KINDS = (STATE, START, FAULT, CANCEL, EMCY, HEARTBEAT_LOST, BOOTUP, SEND_FAILED, ADAPTER_ERROR)

SAMPLE_FIELDS = ("planned", "actual", "demand", "following_error", "fifo_fill", "setpoint", "statusword",
                 "buffer_status")


class RecordingError(ValueError):
    """A recording that cannot be built or read; `code` is machine-readable, `path` names the field."""

    def __init__(self, code: str, message: str, path: str = ""):
        super().__init__(message)
        self.code = code
        self.message = message
        self.path = path


@dataclass(frozen=True)
class AxisInfo:
    name: str
    node_id: int
    counts_per_unit: float

    def __post_init__(self) -> None:
        if not self.name:
            raise RecordingError("RECORDING", "axis name must not be empty", "axes.name")
        if not 1 <= self.node_id <= 127:
            raise RecordingError("RECORDING", f"node_id of axis '{self.name}' must be 1..127, got {self.node_id}",
                                 "axes.node_id")
        if not (math.isfinite(self.counts_per_unit) and self.counts_per_unit > 0):
            raise RecordingError("RECORDING", f"counts_per_unit of axis '{self.name}' must be > 0, got "
                                 f"{self.counts_per_unit}", "axes.counts_per_unit")


@dataclass
class AxisSamples:
    """One axis' samples, columnar: entry k of every list belongs to SYNC `sync[k]` at time `t[k]`."""

    sync: list[int] = field(default_factory=list)
    t: list[float] = field(default_factory=list)
    planned: list[int | None] = field(default_factory=list)
    actual: list[int | None] = field(default_factory=list)
    demand: list[int | None] = field(default_factory=list)
    following_error: list[int | None] = field(default_factory=list)
    fifo_fill: list[int | None] = field(default_factory=list)
    setpoint: list[int | None] = field(default_factory=list)
    statusword: list[int | None] = field(default_factory=list)
    buffer_status: list[int | None] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.sync)

    def append(self, sync: int, t: float, values: Mapping[str, int | None]) -> None:
        self.sync.append(sync)
        self.t.append(t)
        for name in SAMPLE_FIELDS:
            getattr(self, name).append(values.get(name))

    def row(self, k: int) -> dict[str, int | None]:
        return {name: getattr(self, name)[k] for name in SAMPLE_FIELDS}

    def column(self, name: str) -> list[int | None]:
        if name not in SAMPLE_FIELDS:
            raise RecordingError("RECORDING", f"no sample field {name!r}; fields are {', '.join(SAMPLE_FIELDS)}")
        values: list[int | None] = getattr(self, name)
        return values

    def present(self, name: str) -> list[int]:
        return [v for v in self.column(name) if v is not None]


@dataclass(frozen=True)
class RecordedEvent:
    t: float
    sync: int | None
    kind: str
    state: str | None = None
    code: str | None = None
    node: int | None = None
    message: str = ""

    def __post_init__(self) -> None:
        if self.kind not in EVENT_KINDS:
            raise RecordingError("RECORDING", f"event kind {self.kind!r} is not one of {', '.join(EVENT_KINDS)}",
                                 "events.kind")

    def label(self) -> str:
        """A short human line: 'state running', 'fault BUFFER_UNDERFLOW node 2: ...'."""
        parts = [self.kind]
        if self.state:
            parts.append(self.state)
        if self.code:
            parts.append(self.code)
        if self.node is not None:
            parts.append(f"node {self.node}")
        text = " ".join(parts)
        return f"{text}: {self.message}" if self.message else text


@dataclass
class Frames:
    """CAN frames, columnar: time (s since the first SYNC), COB-ID, DLC, data."""

    t: list[float] = field(default_factory=list)
    cob_id: list[int] = field(default_factory=list)
    dlc: list[int] = field(default_factory=list)
    data: list[bytes] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.t)

    def append(self, t: float, cob_id: int, dlc: int, data: bytes) -> None:
        self.t.append(t)
        self.cob_id.append(cob_id)
        self.dlc.append(dlc)
        self.data.append(bytes(data))


@dataclass(frozen=True)
class JobRecording:
    """Everything recorded about one job (see the module docstring)."""

    job_id: str
    cell: str
    result: str
    sync_period_ms: int
    first_sync: int
    start_sync: int | None
    epoch_s: float
    axes: tuple[AxisInfo, ...]
    samples: Mapping[str, AxisSamples]
    events: tuple[RecordedEvent, ...]
    frames: Frames
    report: Mapping[str, Any]
    fifo_size: int = 64
    underflow_watermark: int | None = None
    overflow_watermark: int | None = None
    tolerance_counts: int | None = None
    frames_dropped: int = 0
    format_version: int = FORMAT_VERSION
    drive: DriveRecording | None = None  # the drives' own data recorders (a job's `record` section)

    def __post_init__(self) -> None:
        if self.sync_period_ms < 1:
            raise RecordingError("RECORDING", f"sync_period_ms must be >= 1, got {self.sync_period_ms}",
                                 "sync_period_ms")
        names = [a.name for a in self.axes]
        if len(set(names)) != len(names):
            raise RecordingError("RECORDING", f"axis names repeat: {names}", "axes")
        missing = [n for n in names if n not in self.samples]
        if missing:
            raise RecordingError("RECORDING", f"no samples for axes {missing}", "samples")
        if not math.isfinite(self.epoch_s):
            raise RecordingError("RECORDING", f"epoch_s is {self.epoch_s}", "epoch_s")

    @property
    def duration_s(self) -> float:
        ends = [s.t[-1] for s in self.samples.values() if len(s)]
        return max(ends, default=0.0)

    def axis(self, name: str) -> AxisInfo:
        for a in self.axes:
            if a.name == name:
                return a
        raise RecordingError("RECORDING", f"no axis {name!r} in the recording; axes are "
                             f"{', '.join(a.name for a in self.axes)}", "axes")

    def axis_summary(self) -> list[dict[str, Any]]:
        """Per axis, what the samples say (independent of the report's own numbers)."""
        out = []
        for a in self.axes:
            s = self.samples[a.name]
            fe = s.present("following_error")
            fills = s.present("fifo_fill")
            dev = [abs(d - p) for d, p in zip(s.demand, s.planned, strict=True) if d is not None and p is not None]
            actual = s.present("actual")
            planned = s.present("planned")
            out.append({
                "name": a.name,
                "node_id": a.node_id,
                "samples": len(s),
                "max_following_error_counts": max((abs(v) for v in fe), default=None),
                "fifo_min": min(fills, default=None),
                "fifo_max": max(fills, default=None),
                "max_demand_vs_plan_counts": max(dev, default=None),
                "final_actual_counts": actual[-1] if actual else None,
                "final_planned_counts": planned[-1] if planned else None,
            })
        return out


def plan_index(sync: int, start_sync: int | None, period_ms: int, duration_ms: int) -> int:
    """The ms of the plan the drive's demand stands at, at SYNC `sync` (the plan starts at the start SYNC)."""
    if start_sync is None or sync <= start_sync:
        return 0
    return min((sync - start_sync) * period_ms, duration_ms)


def _event_from_noted(sync: int, ev: object, t: float) -> RecordedEvent:
    from bus.events import AdapterError, Bootup, Cancel, Emcy, HeartbeatLost, SendFailed

    if isinstance(ev, Emcy):
        return RecordedEvent(t, sync, EMCY, code=f"0x{ev.code:04X}", node=ev.node,
                             message=f"error register 0x{ev.register:02X}, data {ev.data.hex()}")
    if isinstance(ev, HeartbeatLost):
        return RecordedEvent(t, sync, HEARTBEAT_LOST, node=ev.node)
    if isinstance(ev, Bootup):
        return RecordedEvent(t, sync, BOOTUP, node=ev.node)
    if isinstance(ev, Cancel):
        return RecordedEvent(t, sync, CANCEL)
    if isinstance(ev, SendFailed):
        return RecordedEvent(t, sync, SEND_FAILED, message=ev.reason)
    if isinstance(ev, AdapterError):
        return RecordedEvent(t, sync, ADAPTER_ERROR, message=f"{ev.where}: {ev.reason}")
    raise RecordingError("RECORDING", f"cannot record event {type(ev).__name__}")


def change_events(c: Any, t: float) -> list[RecordedEvent]:
    """The events of one job state change (a `streamer.runtime.trace.NotedChange`) at `t`: the state, and
    the fault its outcome carries (the recording and the live channels both read them so)."""
    events = [RecordedEvent(t, c.sync, STATE, state=c.state, message=c.message)]
    if c.code is not None:
        events.append(RecordedEvent(t, c.sync, FAULT, state=c.state, code=str(c.code), node=c.node,
                                    message=c.message))
    return events


def noted_event(noted: Any, t: float) -> RecordedEvent:
    """The event of a `streamer.runtime.trace.NotedEvent` at `t`."""
    return _event_from_noted(noted.sync, noted.event, t)


def build_recording(
    traj: Any,
    trace: Any,
    report: Mapping[str, Any],
    *,
    first_sync: int,
    start_sync: int | None,
    sync_period_ms: int,
    job_id: str = "",
    cell: str = "",
    epoch_s: float | None = None,
    underflow_watermark: int | None = None,
    overflow_watermark: int | None = None,
    drive: DriveRecording | None = None,
    feedback: Mapping[int, Any] | None = None,
) -> JobRecording:
    """The recording of one finished job from its plan (`PvtTrajectory`), its `JobTrace` and report.

    `feedback`: per node, what its drive reported as the streamer core attributed it (`JobReport.feedback`,
    streamer/core/attribution.py): each TPDO2's actual and demand are recorded at the SYNC it answers, as the
    report measures them; a drive that answers late has its answer arrive after the next SYNC, so by its
    arrival tag (the trace, used for a node with no log) it would be one SYNC off its plan.

    `epoch_s`: wall-clock time of the job's first SYNC; None when the runtime's clock is the wall clock
    (the real-time runtime's python-can timestamps), so the first SYNC's own time is used."""
    sync_times: Mapping[int, float] = trace.sync_times
    t0 = sync_times[first_sync] if first_sync in sync_times else min(sync_times.values(), default=0.0)
    period_s = sync_period_ms / 1000.0

    def rel(t: float) -> float:  # seconds since the first SYNC, to the microsecond (CAN timestamps' grain)
        return round(t - t0, 6)

    def t_of(sync: int) -> float:
        t = sync_times.get(sync)
        return rel(t) if t is not None else round((sync - first_sync) * period_s, 6)

    planned_ms = traj.planned_demand()
    duration_ms = int(traj.duration_ms)
    axes: list[AxisInfo] = []
    samples: dict[str, AxisSamples] = {}
    for i, (name, node) in enumerate(zip(traj.axis_names, traj.node_ids, strict=True)):
        axes.append(AxisInfo(str(name), int(node), float(traj.counts_per_unit[i])))
        ax = trace.axes.get(int(node))
        rows: dict[int, dict[str, int | None]] = {}
        if ax is not None:
            recorded_status = len(ax.statusword) == len(ax.fill_sync)
            # in order, never by index: an endless job's columns read their spilled blocks back in sequence
            status = zip(ax.statusword, ax.buffer_status, strict=True) if recorded_status else None
            for s, fill in zip(ax.fill_sync, ax.fill, strict=True):
                row = rows.setdefault(s, {})
                row["fifo_fill"] = fill
                if status is not None:
                    row["statusword"], row["buffer_status"] = next(status)
        for s, actual, demand in zip(*positions_by_sync(ax, (feedback or {}).get(int(node))), strict=True):
            row = rows.setdefault(int(s), {})
            row["actual"], row["demand"], row["following_error"] = actual, demand, actual - demand
        if ax is not None:
            for s, sp in zip(ax.setpoint_sync, ax.setpoint, strict=True):
                rows.setdefault(s, {})["setpoint"] = sp
        series = AxisSamples()
        for s in sorted(rows):
            row = rows[s]
            row["planned"] = int(planned_ms[i, plan_index(s, start_sync, sync_period_ms, duration_ms)])
            series.append(s, t_of(s), row)
        samples[str(name)] = series

    events: list[RecordedEvent] = []
    for c in trace.changes:
        events += change_events(c, rel(c.t) if c.t else t_of(c.sync if c.sync is not None else first_sync))
    for noted in trace.noted:
        events.append(noted_event(noted, rel(float(noted.event.t))))
    if start_sync is not None:
        events.append(RecordedEvent(t_of(start_sync), start_sync, START,
                                    message=f"every axis in ip mode from SYNC {start_sync}"))
    events.sort(key=lambda e: e.t)

    frames = Frames()
    log = trace.frame_log
    for ft, cob_id, dlc, data in log.frames():
        frames.append(rel(ft), cob_id, dlc, data)

    return JobRecording(
        job_id=job_id,
        cell=cell,
        result=str(report.get("result", "")),
        sync_period_ms=sync_period_ms,
        first_sync=first_sync,
        start_sync=start_sync,
        epoch_s=t0 if epoch_s is None else epoch_s,
        axes=tuple(axes),
        samples=samples,
        events=tuple(events),
        frames=frames,
        report=dict(report),
        underflow_watermark=underflow_watermark,
        overflow_watermark=overflow_watermark,
        tolerance_counts=int(traj.tolerance_counts),
        frames_dropped=int(log.dropped),
        drive=drive,
    )


def merge_syncs(samples: Sequence[AxisSamples]) -> list[tuple[int, float]]:
    """Every SYNC any axis has a sample for, with its time, in order (the rows of a CSV export)."""
    seen: dict[int, float] = {}
    for s in samples:
        for sync, t in zip(s.sync, s.t, strict=True):
            seen.setdefault(sync, t)
    return sorted(seen.items())
