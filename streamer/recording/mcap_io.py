"""A job's recording as an MCAP file: JSON messages with JSON Schema channels.

Theory of operation. MCAP is a chunked, indexed, zstd-compressed container of timestamped messages that
Foxglove and PlotJuggler open; channels use the `json` encoding with `jsonschema` schemas. Channels
(docs/recording.md has the schemas): `/axis/<name>` (pvt.AxisSample per SYNC the axis answered; a field
without a value is left out), `/job/events` (pvt.JobEvent), `/can/frames` (pvt.CanFrame), and for a job
with a `record` section `/recorder/<node>` (pvt.RecorderSample) with the `pvt.recorder` metadata. The
`pvt.job` metadata and the `report.json` attachment make one file the whole job: `read_mcap` rebuilds the
`JobRecording` from it alone. Log times are ns since the epoch (`epoch_s + t`), `t` seconds since the
job's first SYNC. Written after the job, to a temporary name then renamed: no reader sees half a file.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import IO, Any

from streamer.recording.drive import DriveRecording, DriveVariable, NodeRecording, RecordRequest
from streamer.recording.model import (
    FORMAT_VERSION,
    SAMPLE_FIELDS,
    AxisInfo,
    AxisSamples,
    Frames,
    JobRecording,
    RecordedEvent,
    RecordingError,
)

PROFILE = ""  # no well-known MCAP profile fits (ros1/ros2 need their own message encodings)
LIBRARY = "pvt-motion recording"
METADATA_NAME = "pvt.job"
REPORT_ATTACHMENT = "report.json"
AXIS_TOPIC_PREFIX = "/axis/"
EVENTS_TOPIC = "/job/events"
FRAMES_TOPIC = "/can/frames"
RECORDER_TOPIC_PREFIX = "/recorder/"
RECORDER_METADATA = "pvt.recorder"

_INT = {"type": "integer"}

AXIS_SAMPLE_SCHEMA: dict[str, Any] = {
    "title": "pvt.AxisSample",
    "description": "One axis at one SYNC: the plan and what the drive reported (positions in counts).",
    "type": "object",
    "properties": {
        "t": {"type": "number", "description": "seconds since the job's first SYNC"},
        "sync": {"type": "integer", "description": "SYNC counter (the master's count since SYNC started)"},
        "node": {"type": "integer", "description": "CANopen node id"},
        "planned": {"type": "integer", "description": "the plan's position demand at this SYNC, counts"},
        "actual": {"type": "integer", "description": "position actual value 0x6064, counts"},
        "demand": {"type": "integer", "description": "position demand value 0x6062, counts"},
        "following_error": {"type": "integer", "description": "actual - demand, counts"},
        "fifo_fill": {"type": "integer", "description": "records in the drive's FIFO (EPOS), 0..64"},
        "setpoint": {"type": "integer", "description": "set point sent for this SYNC (cyclic drives), counts"},
        "statusword": {"type": "integer", "description": "statusword 0x6041"},
        "buffer_status": {"type": "integer", "description": "interpolation buffer status 0x20C4:01"},
    },
    "required": ["t", "sync", "node", "planned"],
    "additionalProperties": False,
}

JOB_EVENT_SCHEMA: dict[str, Any] = {
    "title": "pvt.JobEvent",
    "description": "Something that happened to the job (not a per-SYNC sample).",
    "type": "object",
    "properties": {
        "t": {"type": "number", "description": "seconds since the job's first SYNC"},
        "sync": {"type": "integer", "description": "the last SYNC before the event"},
        "kind": {"type": "string", "enum": ["state", "start", "fault", "cancel", "emcy", "heartbeat_lost",
                                            "bootup", "send_failed", "adapter_error"]},
        "state": {"type": "string", "description": "the job state (kind state, fault)"},
        "code": {"type": "string", "description": "error code (fault) or EMCY code 0xNNNN (emcy)"},
        "node": {"type": "integer", "description": "the node concerned, when one is"},
        "message": {"type": "string"},
    },
    "required": ["t", "kind"],
    "additionalProperties": False,
}

CAN_FRAME_SCHEMA: dict[str, Any] = {
    "title": "pvt.CanFrame",
    "description": "One CAN frame on the bus (11-bit identifier).",
    "type": "object",
    "properties": {
        "t": {"type": "number", "description": "seconds since the job's first SYNC"},
        "id": {"type": "integer", "description": "COB-ID"},
        "dlc": {"type": "integer", "description": "data length code, 0..8"},
        "data": {"type": "string", "description": "data bytes, hex, 2*dlc characters"},
    },
    "required": ["t", "id", "dlc", "data"],
    "additionalProperties": False,
}

RECORDER_SAMPLE_SCHEMA: dict[str, Any] = {
    "title": "pvt.RecorderSample",
    "description": "One sample of a drive's own data recorder (0x201B); every other field is a recorded variable "
                   "(by its name, drive units).",
    "type": "object",
    "properties": {
        "t": {"type": "number", "description": "seconds since the trigger (the trigger's sample is at 0)"},
        "k": {"type": "integer", "description": "sample index in the recorded vector"},
        "node": {"type": "integer", "description": "CANopen node id"},
        "t_job": {"type": "number", "description": "seconds since the job's first SYNC, when the trigger's time "
                                                   "is known"},
    },
    "required": ["t", "k", "node"],
    "additionalProperties": {"type": "integer"},
}

SCHEMAS = {s["title"]: s for s in (AXIS_SAMPLE_SCHEMA, JOB_EVENT_SCHEMA, CAN_FRAME_SCHEMA, RECORDER_SAMPLE_SCHEMA)}


def _dumps(obj: Mapping[str, Any]) -> bytes:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


def sample_message(t: float, sync: int, node: int, row: Mapping[str, int | None]) -> dict[str, Any]:
    """One `pvt.AxisSample` message (a field without a value is left out); the recording and the live
    channels (streamer/live) both write this."""
    msg: dict[str, Any] = {"t": t, "sync": sync, "node": node}
    for name in SAMPLE_FIELDS:
        v = row.get(name)
        if v is not None:
            msg[name] = v
    return msg


def event_message(e: RecordedEvent) -> dict[str, Any]:
    """One `pvt.JobEvent` message (the recording's and the live channel's)."""
    ev: dict[str, Any] = {"t": e.t, "kind": e.kind}
    if e.sync is not None:
        ev["sync"] = e.sync
    if e.state is not None:
        ev["state"] = e.state
    if e.code is not None:
        ev["code"] = e.code
    if e.node is not None:
        ev["node"] = e.node
    if e.message:
        ev["message"] = e.message
    return ev


def _ns(epoch_s: float, t: float) -> int:
    return max(0, round((epoch_s + t) * 1e9))


def _metadata(rec: JobRecording) -> dict[str, str]:
    def opt(v: int | None) -> str:
        return "" if v is None else str(v)

    return {
        "format_version": str(rec.format_version),
        "job_id": rec.job_id,
        "cell": rec.cell,
        "result": rec.result,
        "sync_period_ms": str(rec.sync_period_ms),
        "first_sync": str(rec.first_sync),
        "start_sync": opt(rec.start_sync),
        "epoch_s": repr(rec.epoch_s),
        "fifo_size": str(rec.fifo_size),
        "underflow_watermark": opt(rec.underflow_watermark),
        "overflow_watermark": opt(rec.overflow_watermark),
        "tolerance_counts": opt(rec.tolerance_counts),
        "frames_dropped": str(rec.frames_dropped),
        "axes": json.dumps([{"name": a.name, "node_id": a.node_id, "counts_per_unit": a.counts_per_unit}
                            for a in rec.axes]),
    }


def write_mcap_stream(rec: JobRecording, out: IO[bytes]) -> int:
    """Write `rec` to a binary stream; returns the number of messages."""
    from mcap.writer import Writer

    writer = Writer(out)
    writer.start(profile=PROFILE, library=LIBRARY)
    ids = {title: writer.register_schema(name=title, encoding="jsonschema", data=_dumps(schema))
           for title, schema in SCHEMAS.items()}
    axis_channels = {
        a.name: writer.register_channel(topic=f"{AXIS_TOPIC_PREFIX}{a.name}", message_encoding="json",
                                        schema_id=ids["pvt.AxisSample"],
                                        metadata={"node_id": str(a.node_id),
                                                  "counts_per_unit": repr(a.counts_per_unit)})
        for a in rec.axes
    }
    events_channel = writer.register_channel(topic=EVENTS_TOPIC, message_encoding="json",
                                             schema_id=ids["pvt.JobEvent"])
    frames_channel = writer.register_channel(topic=FRAMES_TOPIC, message_encoding="json",
                                             schema_id=ids["pvt.CanFrame"])
    # messages go in time order across channels (readers replay in log-time order anyway; chunks whose
    # time ranges overlap cost the reader a merge)
    queue: list[tuple[float, int, int, bytes]] = []
    for a in rec.axes:
        s = rec.samples[a.name]
        ch = axis_channels[a.name]
        for k in range(len(s)):
            queue.append((s.t[k], 0, ch, _dumps(sample_message(s.t[k], s.sync[k], a.node_id, s.row(k)))))
    for e in rec.events:
        queue.append((e.t, 1, events_channel, _dumps(event_message(e))))
    f = rec.frames
    for k in range(len(f)):
        queue.append((f.t[k], 2, frames_channel,
                      _dumps({"t": f.t[k], "id": f.cob_id[k], "dlc": f.dlc[k], "data": f.data[k].hex()})))
    if rec.drive is not None:
        queue += _recorder_messages(writer, rec.drive, ids["pvt.RecorderSample"])
        writer.add_metadata(RECORDER_METADATA, _recorder_metadata(rec.drive))
    queue.sort(key=lambda q: (q[0], q[1]))
    seq: dict[int, int] = {}
    for t, _, ch, data in queue:
        n = seq.get(ch, 0)
        seq[ch] = n + 1
        ns = _ns(rec.epoch_s, t)
        writer.add_message(channel_id=ch, log_time=ns, publish_time=ns, data=data, sequence=n)
    writer.add_metadata(METADATA_NAME, _metadata(rec))
    now = _ns(rec.epoch_s, 0.0)
    writer.add_attachment(create_time=now, log_time=now, name=REPORT_ATTACHMENT, media_type="application/json",
                          data=json.dumps(rec.report, indent=2, default=str).encode())
    writer.finish()  # type: ignore[no-untyped-call]  # mcap leaves it unannotated
    return len(queue)


def _recorder_messages(writer: Any, drive: DriveRecording, schema_id: int) -> list[tuple[float, int, int, bytes]]:
    """One channel per node; log time = the job's time of the sample where the trigger's time is known, else
    the first sample at the job's first SYNC."""
    out: list[tuple[float, int, int, bytes]] = []
    for node, nr in sorted(drive.nodes.items()):
        ch = writer.register_channel(topic=f"{RECORDER_TOPIC_PREFIX}{node}", message_encoding="json",
                                     schema_id=schema_id, metadata={"node_id": str(node),
                                                                    "axis": drive.names.get(node, "")})
        trigger_t = drive.trigger_t.get(node)
        for k, t in enumerate(nr.t):
            msg: dict[str, Any] = {"t": t, "k": k, "node": node}
            if trigger_t is not None:
                msg["t_job"] = round(trigger_t + t, 9)
            for v in nr.variables:
                msg[v.name] = nr.values[v.name][k]
            at = trigger_t + t if trigger_t is not None else t - nr.t[0]
            out.append((at, 3, ch, _dumps(msg)))
    return out


def _recorder_metadata(drive: DriveRecording) -> dict[str, str]:
    req = drive.request
    request = {"variables": [{"name": v.name, "index": v.index, "sub": v.sub, "bits": v.bits, "signed": v.signed,
                              "unit": v.unit} for v in req.variables],
               "trigger": req.trigger, "period_units": req.period_units, "preceding_samples": req.preceding_samples,
               "axes": list(req.axes)}
    nodes = {str(n): {"name": drive.names.get(n, ""), "samples": r.samples, "offset": r.offset,
                      "triggered": r.triggered, "trigger_index": r.trigger_index, "period_s": r.period_s,
                      "upload": drive.upload.get(n, ""), "trigger_t": drive.trigger_t.get(n)}
             for n, r in sorted(drive.nodes.items())}
    return {"request": json.dumps(request), "nodes": json.dumps(nodes)}


def _read_drive(meta: dict[str, str], messages: dict[int, list[dict[str, Any]]]) -> DriveRecording:
    req = json.loads(meta["request"])
    variables = tuple(DriveVariable(str(v["name"]), int(v["index"]), int(v["sub"]), int(v["bits"]), bool(v["signed"]),
                                    str(v.get("unit", ""))) for v in req["variables"])
    units = int(req["period_units"])
    request = RecordRequest(variables, trigger=str(req["trigger"]), period_ms=units / 10,
                            preceding_ms=int(req["preceding_samples"]) * units / 10, axes=tuple(req.get("axes", [])))
    nodes: dict[int, NodeRecording] = {}
    names: dict[int, str] = {}
    upload: dict[int, str] = {}
    trigger_t: dict[int, float | None] = {}
    for key, info in json.loads(meta["nodes"]).items():
        n = int(key)
        msgs = sorted(messages.get(n, []), key=lambda m: int(m["k"]))
        nodes[n] = NodeRecording(
            n, variables, tuple(float(m["t"]) for m in msgs),
            {v.name: tuple(int(m[v.name]) for m in msgs) for v in variables}, float(info["period_s"]),
            bool(info["triggered"]), info["trigger_index"], int(info["offset"]), int(info["samples"]))
        names[n] = str(info.get("name", ""))
        upload[n] = str(info.get("upload", ""))
        trigger_t[n] = info.get("trigger_t")
    return DriveRecording(request, nodes, names=names, upload=upload, trigger_t=trigger_t)


def write_mcap(rec: JobRecording, path: Path) -> int:
    """Write `rec` to `path` (via a temporary file in the same folder, then renamed); returns messages."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as out:
            n = write_mcap_stream(rec, out)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return n


def _opt_int(text: str | None) -> int | None:
    return int(text) if text not in (None, "") else None


def read_mcap(path: Path) -> JobRecording:
    """The `JobRecording` stored in an MCAP file written by `write_mcap`."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            meta: dict[str, str] | None = None
            recorder_meta: dict[str, str] | None = None
            for m in reader.iter_metadata():
                if m.name == METADATA_NAME:
                    meta = dict(m.metadata)
                elif m.name == RECORDER_METADATA:
                    recorder_meta = dict(m.metadata)
            if meta is None:
                raise RecordingError("NOT_A_RECORDING", f"{path} has no {METADATA_NAME!r} metadata record: "
                                     "not a pvt job recording", "metadata")
            report: dict[str, Any] = {}
            for att in reader.iter_attachments():
                if att.name == REPORT_ATTACHMENT:
                    report = json.loads(att.data)
            axes = tuple(AxisInfo(str(a["name"]), int(a["node_id"]), float(a["counts_per_unit"]))
                         for a in json.loads(meta["axes"]))
            samples = {a.name: AxisSamples() for a in axes}
            events: list[RecordedEvent] = []
            frames = Frames()
            recorder: dict[int, list[dict[str, Any]]] = {}
            for _schema, channel, message in reader.iter_messages(log_time_order=True):
                obj = json.loads(message.data)
                topic = channel.topic
                if topic == FRAMES_TOPIC:
                    frames.append(float(obj["t"]), int(obj["id"]), int(obj["dlc"]), bytes.fromhex(obj["data"]))
                elif topic == EVENTS_TOPIC:
                    events.append(RecordedEvent(float(obj["t"]), obj.get("sync"), str(obj["kind"]), obj.get("state"),
                                                obj.get("code"), obj.get("node"), str(obj.get("message", ""))))
                elif topic.startswith(AXIS_TOPIC_PREFIX):
                    name = topic[len(AXIS_TOPIC_PREFIX):]
                    if name in samples:
                        samples[name].append(int(obj["sync"]), float(obj["t"]), obj)
                elif topic.startswith(RECORDER_TOPIC_PREFIX):
                    recorder.setdefault(int(obj["node"]), []).append(obj)
            drive = _read_drive(recorder_meta, recorder) if recorder_meta is not None else None
    except (McapError, OSError, KeyError, ValueError) as exc:
        if isinstance(exc, RecordingError):
            raise
        raise RecordingError("NOT_A_RECORDING", f"cannot read {path} as a job recording: "
                             f"{type(exc).__name__}: {exc}") from exc
    version = int(meta.get("format_version", "0"))
    if version > FORMAT_VERSION:
        raise RecordingError("NOT_A_RECORDING", f"{path} has recording format {version}; this pvt reads up to "
                             f"{FORMAT_VERSION}", "format_version")
    return JobRecording(
        job_id=meta.get("job_id", ""),
        cell=meta.get("cell", ""),
        result=meta.get("result", ""),
        sync_period_ms=int(meta["sync_period_ms"]),
        first_sync=int(meta["first_sync"]),
        start_sync=_opt_int(meta.get("start_sync")),
        epoch_s=float(meta["epoch_s"]),
        axes=axes,
        samples=samples,
        events=tuple(events),
        frames=frames,
        report=report,
        fifo_size=int(meta.get("fifo_size", "64")),
        underflow_watermark=_opt_int(meta.get("underflow_watermark")),
        overflow_watermark=_opt_int(meta.get("overflow_watermark")),
        tolerance_counts=_opt_int(meta.get("tolerance_counts")),
        frames_dropped=int(meta.get("frames_dropped", "0")),
        format_version=version,
        drive=drive,
    )
