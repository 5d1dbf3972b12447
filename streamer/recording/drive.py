"""The drive's own data recorder, host side: what to record, and the decoding of what was recorded.

Theory of operation. An EPOS records up to four of its objects every n x 0.1 ms into 512 words of ring
buffers (seed 004; simulated: bus/sim/data_recorder.py). Pure. `RecordRequest` (for `pvt record`, the
`Recorder` and a job's `record` section) names the variables, the period or total time, the trigger and
the time kept before it, is validated on construction (`DriveRecordingError` naming the field and value)
and becomes the registers 0x2011-0x2016. `decode_buffer` turns 0x201B, 0x2018, 0x2019 and 0x2017 into
one series per variable, trigger at t = 0, by seed 004's "Data Buffer Segmentation". `DriveRecording`
holds several nodes and writes CSV, PNG and HTML. Values stay in drive units.
"""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

TOTAL_WORDS = 512
MAX_VARIABLES = 4
UNIT_MS = 0.1  # 0x2012 counts 0.1 ms (the current regulator's cycle)
MAX_PERIOD_UNITS = 0xFFFF

# 0x2011 trigger bits and 0x2017 status bits (seed 004 tables 2 and 3)
TRIGGER_BITS: Mapping[str, int] = {"movement": 1 << 0, "error": 1 << 1, "input": 1 << 2, "end": 1 << 3,
                                   "continuous": 0, "force": 0}
TRIGGERS = tuple(TRIGGER_BITS)
STATUS_RUNNING = 1 << 0
STATUS_TRIGGERED = 1 << 1
CONTROL_STOP, CONTROL_START, CONTROL_FORCE = 0, 1, 3  # 0x2010 (bit 0 start, bit 1 force trigger)


class DriveRecordingError(ValueError):
    """Bad recorder input or a buffer that does not decode; `code` is machine-readable, `path` the field."""

    def __init__(self, code: str, message: str, path: str = ""):
        super().__init__(message)
        self.code = code
        self.message = message
        self.path = path


BAD_RECORD = "BAD_RECORD"  # the request: an unknown variable, too many, a period the buffer cannot hold
RECORDER = "RECORDER"  # the drive: refused the configuration, no recorder, a buffer that does not decode


@dataclass(frozen=True)
class DriveVariable:
    """One object the recorder samples: where it is, its size and signedness, and its unit."""

    name: str
    index: int
    sub: int
    bits: int
    signed: bool
    unit: str = ""

    @property
    def words(self) -> int:
        return 2 if self.bits == 32 else 1

    @property
    def ref(self) -> str:
        return f"0x{self.index:04X}:{self.sub:02X}"


# the named variables of `pvt record --var` (seed 004's example records the first four)
VARIABLES: Mapping[str, DriveVariable] = {v.name: v for v in (
    DriveVariable("position_demand", 0x6062, 0, 32, True, "counts"),
    DriveVariable("position_actual", 0x6064, 0, 32, True, "counts"),
    DriveVariable("velocity_actual", 0x606C, 0, 32, True, "rpm"),
    DriveVariable("current_actual", 0x6078, 0, 16, True, "mA"),
    DriveVariable("statusword", 0x6041, 0, 16, False, "raw"),
    DriveVariable("ip_buffer_status", 0x20C4, 1, 16, False, "raw"),
    DriveVariable("following_error", 0x60F4, 0, 32, True, "counts"),
    DriveVariable("fifo_free", 0x60C4, 2, 32, False, "records"),
)}

_REF = re.compile(r"^0x([0-9a-fA-F]{1,4}):(?:0x)?([0-9a-fA-F]{1,2})$")


def parse_variable(text: str, *, path: str = "var") -> DriveVariable:
    """A variable by name (`VARIABLES`) or as "0xIIII:SS" of an 8, 16 or 32-bit readable object of the
    EPOS drive's object dictionary (bus/sim/od.py's EPOS_TABLE, which configs/drives/epos-ipm.eds is
    rendered from: the recorder is maxon's)."""
    from bus.sim.od import EPOS_TABLE, DataType

    if not isinstance(text, str):
        raise DriveRecordingError(BAD_RECORD, f"{path}: a variable is a name or 0xIIII:SS, got {text!r}", path)
    named = VARIABLES.get(text)
    if named is not None:
        return named
    m = _REF.match(text.strip())
    if m is None:
        raise DriveRecordingError(BAD_RECORD, f"{path}: unknown variable {text!r}; use one of "
                                  f"{', '.join(VARIABLES)} or an object as 0xIIII:SS", path)
    index, sub = int(m.group(1), 16), int(m.group(2), 16)
    spec = EPOS_TABLE.objects.get((index, sub))
    if spec is None:
        raise DriveRecordingError(BAD_RECORD, f"{path}: {text!r}: the drive has no object 0x{index:04X}:{sub:02X}",
                                  path)
    if not spec.readable or spec.dtype in (DataType.VISIBLE_STRING, DataType.DOMAIN) or spec.dtype.bits > 32:
        raise DriveRecordingError(BAD_RECORD, f"{path}: {text!r} ({spec.name}) is not a readable 8, 16 or "
                                  "32-bit object; the recorder cannot sample it", path)
    for v in VARIABLES.values():
        if (v.index, v.sub) == (index, sub):
            return v
    return DriveVariable(f"0x{index:04X}_{sub:02X}", index, sub, spec.dtype.bits, spec.dtype.signed, "raw")


# the drive families (bus/families.py) that have seed 004's data recorder: it is maxon's, and other
# families use its object indices for other things (the XtrapulsPac's 0x2010 is its boot-up message)
RECORDER_PROFILES = frozenset({"epos-ipm"})


class _Axis(Protocol):
    @property
    def name(self) -> str: ...
    @property
    def node_id(self) -> int: ...
    @property
    def profile(self) -> str: ...


def recorded_axes(axes: Sequence[_Axis], requested: Sequence[str] = (), *, path: str = "record.axes") -> list[str]:
    """The names of `axes` (a job's, or the nodes asked for) whose recorders to use: the `requested` ones,
    each of which must have a recorder (`RECORDER` naming the axis, its node and family otherwise: nothing
    is written to a drive whose object 0x2010 means something else), or, with none requested, every axis
    that has one (`RECORDER` when none has)."""
    by_name = {a.name: a for a in axes}
    if not requested:
        names = [a.name for a in axes if a.profile in RECORDER_PROFILES]
        if not names:
            raise DriveRecordingError(RECORDER, "no axis of the job has a data recorder (drive families "
                                      f"{sorted(RECORDER_PROFILES)}; the axes are "
                                      f"{', '.join(f'{a.name} ({a.profile})' for a in axes)})", path)
        return names
    for i, name in enumerate(requested):
        a = by_name.get(name)
        if a is not None and a.profile not in RECORDER_PROFILES:
            raise DriveRecordingError(RECORDER, f"{path}[{i}]: axis {name!r} (node {a.node_id}) is a {a.profile} "
                                      f"drive: it has no data recorder (seed 004 is maxon EPOS's: "
                                      f"{sorted(RECORDER_PROFILES)})", f"{path}[{i}]")
    return list(requested)


def max_samples(variables: Sequence[DriveVariable]) -> int:
    """0x2018 for these variables: 512 words / the sum of their sizes in words."""
    words = sum(v.words for v in variables)
    return TOTAL_WORDS // words if words else 0


def _number(value: Any, path: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise DriveRecordingError(BAD_RECORD, f"{path} must be a number of ms, got {value!r}", path)
    return float(value)


@dataclass(frozen=True)
class RecordRequest:
    """What to record on each node (see the module docstring). Exactly one of `period_ms`, `total_ms`."""

    variables: tuple[DriveVariable, ...]
    trigger: str = "movement"
    period_ms: float | None = None
    total_ms: float | None = None
    preceding_ms: float = 0.0
    axes: tuple[str, ...] = ()  # a job's record section: the axes to record (empty: all of the job's)

    def __post_init__(self) -> None:
        if not self.variables:
            raise DriveRecordingError(BAD_RECORD, "record at least one variable", "variables")
        if len(self.variables) > MAX_VARIABLES:
            raise DriveRecordingError(BAD_RECORD, f"the recorder takes at most {MAX_VARIABLES} variables, got "
                                      f"{len(self.variables)} ({', '.join(v.name for v in self.variables)})",
                                      "variables")
        refs = [(v.index, v.sub) for v in self.variables]
        if len(set(refs)) != len(refs):
            raise DriveRecordingError(BAD_RECORD, f"a variable is named twice: {[v.name for v in self.variables]}",
                                      "variables")
        if self.trigger not in TRIGGER_BITS:
            raise DriveRecordingError(BAD_RECORD, f"trigger must be one of {', '.join(TRIGGERS)}, got "
                                      f"{self.trigger!r}", "trigger")
        if (self.period_ms is None) == (self.total_ms is None):
            raise DriveRecordingError(BAD_RECORD, "give either the sampling period or the total time, not "
                                      f"{'both' if self.period_ms is not None else 'neither'}", "period_ms")
        samples = self.max_samples
        if self.period_ms is not None:
            p = _number(self.period_ms, "period_ms")
            units = p / UNIT_MS
            if not 1 <= round(units) <= MAX_PERIOD_UNITS or abs(units - round(units)) > 1e-6:
                raise DriveRecordingError(BAD_RECORD, f"period_ms {p:g} is not a whole number of 0.1 ms in "
                                          f"0.1..{MAX_PERIOD_UNITS * UNIT_MS:g} ms (0x2012)", "period_ms")
        else:
            total = _number(self.total_ms, "total_ms")
            if total <= 0:
                raise DriveRecordingError(BAD_RECORD, f"total_ms must be > 0, got {total:g}", "total_ms")
            units_needed = math.ceil(total / (samples * UNIT_MS) - 1e-9)
            if units_needed > MAX_PERIOD_UNITS:
                raise DriveRecordingError(
                    BAD_RECORD, f"total_ms {total:g} needs a sampling period of {units_needed * UNIT_MS:g} ms for "
                    f"the {samples} samples the buffer holds of {', '.join(v.name for v in self.variables)}; the "
                    f"longest period is {MAX_PERIOD_UNITS * UNIT_MS:g} ms", "total_ms")
        pre = _number(self.preceding_ms, "preceding_ms")
        if pre < 0:
            raise DriveRecordingError(BAD_RECORD, f"preceding_ms must be >= 0, got {pre:g}", "preceding_ms")
        if self.trigger == "continuous" and pre > 0:
            raise DriveRecordingError(BAD_RECORD, "preceding_ms means nothing in continuous mode (no trigger), got "
                                      f"{pre:g}", "preceding_ms")
        if self.preceding_samples >= samples:
            period = self.period_units * UNIT_MS
            raise DriveRecordingError(
                BAD_RECORD, f"preceding_ms {pre:g} is {self.preceding_samples} samples at {period:g} ms; the buffer "
                f"holds {samples}, so at most {(samples - 1) * period:g} ms can precede the trigger", "preceding_ms")

    @property
    def max_samples(self) -> int:
        return max_samples(self.variables)

    @property
    def period_units(self) -> int:
        """0x2012: the sampling period in 0.1 ms (from `total_ms`: the shortest that spans it)."""
        if self.period_ms is not None:
            return round(self.period_ms / UNIT_MS)
        assert self.total_ms is not None
        return max(1, math.ceil(self.total_ms / (self.max_samples * UNIT_MS) - 1e-9))

    @property
    def period_s(self) -> float:
        return self.period_units * UNIT_MS / 1000.0

    @property
    def preceding_samples(self) -> int:
        """0x2013: the samples before the trigger's (the preceding time rounded up to whole periods)."""
        return math.ceil(self.preceding_ms / (self.period_units * UNIT_MS) - 1e-9)

    @property
    def span_s(self) -> float:
        """The time the full buffer spans."""
        return self.max_samples * self.period_s

    def registers(self) -> list[tuple[int, int, int]]:
        """The writes (index, sub, value) that configure the recorder (0x2011-0x2016), before a start."""
        out = [(0x2011, 0, TRIGGER_BITS[self.trigger]), (0x2012, 0, self.period_units),
               (0x2013, 0, self.preceding_samples), (0x2014, 0, len(self.variables))]
        for k, v in enumerate(self.variables, start=1):
            out += [(0x2015, k, v.index), (0x2016, k, v.sub)]
        return out

    def describe(self) -> dict[str, Any]:
        return {"variables": [f"{v.name} ({v.ref})" for v in self.variables], "trigger": self.trigger,
                "period_ms": round(self.period_units * UNIT_MS, 1), "samples": self.max_samples,
                "preceding_samples": self.preceding_samples, "span_ms": round(self.span_s * 1000.0, 1)}

    @classmethod
    def from_mapping(cls, data: Any, *, path: str = "record") -> RecordRequest:
        """From a job's `record` section (JSON/TOML/msgpack): {variables: [...], period_ms | total_ms,
        trigger, preceding_ms}. Unknown keys are refused."""
        if not isinstance(data, Mapping):
            raise DriveRecordingError(BAD_RECORD, f"{path} must be a table/object, got {type(data).__name__}", path)
        allowed = {"variables", "period_ms", "total_ms", "trigger", "preceding_ms", "axes"}
        unknown = sorted(str(k) for k in data if k not in allowed)
        if unknown:
            raise DriveRecordingError(BAD_RECORD, f"unknown field {unknown[0]!r} in {path} (allowed: "
                                      f"{sorted(allowed)})", f"{path}.{unknown[0]}")
        raw = data.get("variables")
        if not isinstance(raw, list | tuple) or not raw:
            raise DriveRecordingError(BAD_RECORD, f"{path}.variables must be a non-empty list of names or "
                                      f"0xIIII:SS, got {raw!r}", f"{path}.variables")
        variables = tuple(parse_variable(v, path=f"{path}.variables[{k}]") for k, v in enumerate(raw))
        axes = data.get("axes", [])
        if not isinstance(axes, list | tuple) or not all(isinstance(a, str) for a in axes):
            raise DriveRecordingError(BAD_RECORD, f"{path}.axes must be a list of axis names, got {axes!r}",
                                      f"{path}.axes")
        try:
            return cls(variables, trigger=data.get("trigger", "movement"), period_ms=data.get("period_ms"),
                       total_ms=data.get("total_ms"), preceding_ms=data.get("preceding_ms", 0.0),
                       axes=tuple(axes))
        except DriveRecordingError as e:
            raise DriveRecordingError(e.code, f"{path}.{e.path}: {e.message}", f"{path}.{e.path}") from None


@dataclass(frozen=True)
class NodeRecording:
    """One node's recording: per variable one series, all on the time axis `t` (s, trigger at 0)."""

    node: int
    variables: tuple[DriveVariable, ...]
    t: tuple[float, ...]
    values: Mapping[str, tuple[int, ...]]
    period_s: float
    triggered: bool
    trigger_index: int | None  # the trigger's sample (None: continuous, t = 0 at the first sample)
    offset: int  # 0x2019 as read
    samples: int  # 0x2018 as read

    def series(self, name: str) -> tuple[int, ...]:
        try:
            return self.values[name]
        except KeyError:
            raise DriveRecordingError(BAD_RECORD, f"node {self.node} recorded no {name!r}; it recorded "
                                      f"{', '.join(self.values)}") from None


def _word(data: bytes, word: int) -> int:
    return int.from_bytes(data[2 * word:2 * word + 2], "little")


def decode_buffer(data: bytes, variables: Sequence[DriveVariable], *, samples: int, offset: int, status: int,
                  preceding: int, period_s: float, node: int = 0) -> NodeRecording:
    """One node's 0x201B as one series per variable (see the module docstring). `samples` = 0x2018,
    `offset` = 0x2019, `status` = 0x2017 (bit 1: a trigger happened, so the trigger's sample is
    `preceding` samples after the first), `preceding` = 0x2013 as written."""
    words = [v.words for v in variables]
    if samples < 1:
        raise DriveRecordingError(RECORDER, f"node {node}: 0x2018 says {samples} samples per variable")
    if sum(words) * samples > TOTAL_WORDS:
        raise DriveRecordingError(RECORDER, f"node {node}: {samples} samples of {sum(words)} words exceed the "
                                  f"{TOTAL_WORDS}-word buffer")
    need = 2 * sum(words) * samples
    if len(data) < need:
        raise DriveRecordingError(RECORDER, f"node {node}: 0x201B has {len(data)} bytes; {samples} samples of "
                                  f"{', '.join(v.name for v in variables)} need {need}")
    if not 0 <= offset < samples:
        raise DriveRecordingError(RECORDER, f"node {node}: 0x2019 offset {offset} is outside 0..{samples - 1}")
    values: dict[str, tuple[int, ...]] = {}
    start = 0
    for v, w in zip(variables, words, strict=True):
        ring: list[int] = []
        for row in range(samples):
            at = start + row * w
            raw = _word(data, at) | (_word(data, at + 1) << 16 if w == 2 else 0)
            bits = 16 * w
            if v.signed and raw >= 1 << (bits - 1):
                raw -= 1 << bits
            ring.append(raw)
        values[v.name] = tuple(ring[(offset + k) % samples] for k in range(samples))
        start += samples * w
    triggered = bool(status & STATUS_TRIGGERED)
    trigger_index = min(preceding, samples - 1) if triggered else None
    zero = trigger_index or 0
    t = tuple(round((k - zero) * period_s, 9) for k in range(samples))
    return NodeRecording(node, tuple(variables), t, values, period_s, triggered, trigger_index, offset, samples)


@dataclass(frozen=True)
class DriveRecording:
    """What `pvt record` (or a job's `record` section) got from every node, and how it was asked for."""

    request: RecordRequest
    nodes: Mapping[int, NodeRecording]
    names: Mapping[int, str] = field(default_factory=dict)  # node -> axis name
    upload: Mapping[int, str] = field(default_factory=dict)  # node -> "block" | "segmented" | "direct"
    trigger_t: Mapping[int, float | None] = field(default_factory=dict)  # node -> trigger time on the caller's
    # clock (s since the job's first SYNC in a job's recording), when known

    def columns(self) -> list[str]:
        return ["time_s"] + [f"{n}.{v.name}" for n, rec in sorted(self.nodes.items()) for v in rec.variables]

    def rows(self) -> list[list[float | int | None]]:
        """One row per sample index: the time, then every node's variables (nodes share the time axis)."""
        recs = [self.nodes[n] for n in sorted(self.nodes)]
        if not recs:
            return []
        t = recs[0].t
        out: list[list[float | int | None]] = []
        for k, tk in enumerate(t):
            row: list[float | int | None] = [tk]
            for rec in recs:
                for v in rec.variables:
                    series = rec.values[v.name]
                    row.append(series[k] if k < len(series) else None)
            out.append(row)
        return out

    def summary(self) -> dict[str, Any]:
        return {"request": self.request.describe(), "nodes": {
            str(n): {"samples": r.samples, "offset": r.offset, "triggered": r.triggered,
                     "trigger_index": r.trigger_index, "upload": self.upload.get(n, ""),
                     "trigger_t": self.trigger_t.get(n)} for n, r in sorted(self.nodes.items())}}


def write_csv(rec: DriveRecording, path: Path) -> int:
    """`time_s`, then `<node>.<variable>` per node and variable, in drive units. Returns the rows written."""
    rows = rec.rows()
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(rec.columns())
        for row in rows:
            w.writerow([f"{row[0]:.6f}", *("" if v is None else v for v in row[1:])])
    return len(rows)


def _label(rec: DriveRecording, node: int) -> str:
    name = rec.names.get(node)
    return f"node {node} ({name})" if name else f"node {node}"


def html_page(rec: DriveRecording, title: str = "") -> str:
    """The interactive report page (streamer/recording/html.py): one panel per variable, one curve per
    node, the trigger as a marker at t = 0; sample-and-hold display by default (what the drive sampled)."""
    from streamer.recording.html import HOLD, Marker, PanelSpec, ReportOptions, Series, render_report

    series: list[Series] = []
    panels: list[PanelSpec] = []
    first = next(iter(rec.nodes.values()), None)
    variables = first.variables if first is not None else ()
    for v in variables:
        panel = f"{v.name} ({v.ref})"
        panels.append(PanelSpec(panel, f"{v.name} [{v.unit}]" if v.unit else v.name))
        for n in sorted(rec.nodes):
            r = rec.nodes[n]
            series.append(Series(f"{_label(rec, n)} {v.name}", panel, r.t, list(r.values[v.name]), unit=v.unit,
                                 group=_label(rec, n)))
    markers = [Marker(0.0, f"trigger: {rec.request.trigger}", kind="trigger", short=rec.request.trigger)] \
        if any(r.triggered for r in rec.nodes.values()) else []
    d = rec.request.describe()
    subtitle = (f"nodes {', '.join(str(n) for n in sorted(rec.nodes))}; period {d['period_ms']} ms, "
                f"{d['samples']} samples, {d['preceding_samples']} before the trigger; trigger {rec.request.trigger}")
    opts = ReportOptions(display=HOLD, subtitle=subtitle, panels=tuple(panels),
                         time_title="time since the trigger [s]")
    return render_report(title or "pvt record: the drives' data recorder", series, markers, opts)


def write_html(rec: DriveRecording, path: Path, title: str = "") -> None:
    Path(path).write_text(html_page(rec, title), encoding="utf-8")


def write_png(rec: DriveRecording, path: Path, title: str = "") -> None:
    """One panel per variable, one curve per node (drawn as sampled: steps), the trigger marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    first = next(iter(rec.nodes.values()), None)
    variables = first.variables if first is not None else ()
    fig, axes = plt.subplots(max(1, len(variables)), 1, figsize=(11, 2.6 * max(1, len(variables))), sharex=True,
                             squeeze=False)
    for ax, v in zip(axes[:, 0], variables, strict=False):
        for n in sorted(rec.nodes):
            r = rec.nodes[n]
            ax.step(r.t, r.values[v.name], where="post", linewidth=1.0, label=_label(rec, n))
        if any(r.triggered for r in rec.nodes.values()):
            ax.axvline(0.0, color="#2ca02c", linestyle=":", linewidth=1.0)
        ax.set_ylabel(f"{v.name}\n[{v.unit}]" if v.unit else v.name, fontsize=8)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    axes[-1, 0].set_xlabel("time since the trigger [s]")
    fig.suptitle(title or f"pvt record: trigger {rec.request.trigger}, period "
                 f"{rec.request.period_units * UNIT_MS:g} ms", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
