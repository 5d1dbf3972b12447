"""FIFO feeder: the per-axis state machine that keeps one drive's 64-entry PVT FIFO fed and verified.

Owns one axis' stream position on the wire (`confirmed`, `sent_end`), its loss and duplicate accounting
and telemetry; the coordinator attributes TPDOs and asks what to send (`take`). No I/O, no clock.

Accounting. The drive reports how many records it holds, never which: with E = sent minus consumed by the
plan, a fill F > E is a duplicate (PROTOCOL), F < E a loss. A record can be resent without reordering only
if nothing later was sent, so a feeder keeps at most one unconfirmed batch: a whole missing batch is
resent, a partial one is POINT_LOST. A deficit waits `loss_confirm_syncs` (a late record arrives); a resend
too near its due time is a predicted BUFFER_UNDERFLOW. Batches are one period's consumption, so with
segments of a period or more every isolated loss is repairable (docs/reliability.md); swapped records are
caught by the demand check. The drive's readings (planner/readings.py) add an origin or a second end
record, a hidden record in the fill, or consumption as an interval (drive_time.py). Records and frames
are `Window`s, so a retired prefix keeps every index.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

from bus.events import Send
from planner.encoding.hermite import coefficients, evaluate, round_counts, rpm_to_counts_per_ms, truncate_counts
from planner.encoding.record import PvtRecord
from streamer.core import outcome as oc
from streamer.core.axis_state import FIFO_TRANSITIONS, AxisStateMachine, FeederState
from streamer.core.window import Window, bisect_right


class Failure(NamedTuple):
    code: str
    message: str
    detail: dict[str, Any]


@dataclass(frozen=True)
class AxisTelemetry:
    """One axis' counters for the job report (fills are records, as reported by the drive)."""

    node_id: int
    state: str
    points_sent: int  # distinct records sent (resends not counted)
    frames_sent: int  # records + controlwords sent to this node
    resends: int
    losses_detected: int
    losses_repaired: int
    late_batches: int  # deficits that resolved by themselves (records late, not lost)
    min_fifo: int | None  # over SYNCs from the start while >= U records were left
    max_fifo: int | None
    underflow_warnings: int  # buffer status bit 0 over the same SYNCs
    overflow_warnings: int  # buffer status bit 1 from the start
    start_sync: int | None
    end_sync: int | None
    last_fill: int | None
    max_demand_error_counts: int
    errors: tuple[str, ...] = field(default=())


def stream_framing(start_position: int, end: PvtRecord, first_record: str | None,
                   fifo_count: str | None) -> tuple[PvtRecord | None, PvtRecord | None]:
    """(lead, tail) records around the plan's for a drive with these readings: the origin record (the
    start at rest) for a drive that takes the first record as the point at time zero, a second end record
    for one that counts the target out of its FIFO (see the module docstring); None where none is needed."""
    lead = PvtRecord(start_position, 0, 1) if first_record == "time_zero" else None
    tail = end if fifo_count == "until_segment_start" else None
    return lead, tail


def framed(records: Sequence[PvtRecord], start_position: int, first_record: str | None,
           fifo_count: str | None) -> list[PvtRecord]:
    """Every record a drive with these readings is sent for the plan's `records` (end record included)."""
    lead, tail = stream_framing(start_position, records[-1], first_record, fifo_count)
    return [*([lead] if lead else []), *records, *([tail] if tail else [])]


class FifoFeeder(AxisStateMachine):
    """One axis. The coordinator owns the timing and calls `account`, `take` and `fire`."""

    transitions = FIFO_TRANSITIONS

    def __init__(
        self,
        axis: int,
        node_id: int,
        start_position: int,
        records: list[PvtRecord],
        sends: list[Send],
        *,
        sync_period_ms: int,
        loss_confirm_syncs: int,
        repair_margin_ms: int,
        counts_per_rev: int | None,
        lead: Send | None = None,
        tail: Send | None = None,
        hides_target: bool = False,
        rounding: str | None = "nearest",
        open_end: bool = False,
        echoed: bool = False,
    ) -> None:
        self.axis = axis
        self.node_id = node_id
        self.start_position = start_position
        # the plan's records (the stop trajectory or the next chunk is spliced in) and the stream's frames,
        # by index from the stream's start; an endless job drops the prefix no one can read again (`retire`)
        self.records: Window[PvtRecord] = Window(records)
        self.lead = 1 if lead is not None else 0
        self._lead_send = lead
        self._tail_send = tail
        self.open_end = open_end  # the stream goes on (an open-ended plan): no tail until a closed part follows
        self.tail = 1 if tail is not None and not open_end else 0
        self.sends: Window[Send] = Window(self._stream(sends))  # lead + the plan's frames + tail
        self.hides_target = hides_target  # the reported fill leaves out the record being interpolated towards
        self._rounders = {"nearest": (round_counts,), "toward_zero": (truncate_counts,),
                          None: (round_counts, truncate_counts)}[rounding]
        self.state = FeederState.WAITING
        self._period = sync_period_ms
        self._confirm_syncs = loss_confirm_syncs
        self._margin = repair_margin_ms
        self._cpr = counts_per_rev
        # stream position
        self.confirmed = 0
        self.sent_end = 0
        self.batch_tag = 0  # SYNC from which the batch [confirmed, sent_end) is counted in the fill
        # the runtime feeds our records as the bus carried them (`on_wire`): a batch counts from the SYNC after
        # its last frame was on the wire, and not at all while a frame of it has not come back
        self.echoed = echoed
        self.in_flight = 0  # frames taken whose echo has not come back (with `echoed`)
        self.suspect_sync: int | None = None
        self.repair_pending = 0
        self.max_sent = 0
        # feedback bookkeeping (set by the coordinator)
        self.last_tpdo1 = -1
        self.last_tpdo2 = -1
        self.first_status: tuple[int, int, int] | None = None  # (statusword, buffer status, fill)
        self.first_demand: int | None = None
        self.status_heard = -1  # the newest SYNC on the wire when first_status / first_demand arrived
        self.demand_heard = -1
        # telemetry
        self.frames_sent = 0
        self.resends = 0
        self.losses_detected = 0
        self.losses_repaired = 0
        self.late_batches = 0
        self.min_fifo: int | None = None
        self.max_fifo: int | None = None
        self.underflow_warnings = 0
        self.overflow_warnings = 0
        self.start_sync: int | None = None
        self.end_sync: int | None = None
        self.last_fill: int | None = None
        self.max_demand_error = 0
        self.errors: list[str] = []

    def _stream(self, plan_sends: list[Send]) -> list[Send]:
        out = [self._lead_send] if self._lead_send is not None else []
        out += plan_sends
        if self._tail_send is not None and not self.open_end:
            out.append(self._tail_send)
        return out

    @property
    def plan_len(self) -> int:
        return len(self.sends) - self.lead - self.tail

    def stream_prefix(self, plan_prefix: int) -> int:
        """Records of this axis' stream to have sent for the first `plan_prefix` records of the plan."""
        if plan_prefix <= 0:
            return 0
        if plan_prefix >= self.plan_len:
            return len(self.sends)
        return plan_prefix + self.lead

    def stream_consumed(self, plan_consumed: int, activated: bool) -> int:
        """Stream records the drive has consumed when it consumed `plan_consumed` plan records."""
        return plan_consumed + self.lead if activated else 0

    def splice(self, k: int, records: list[PvtRecord], sends: list[Send], *, open_end: bool = False) -> None:
        """Replace the plan after record k (a stop, a change, the next chunk of an open-ended plan); the stream
        keeps its lead, and its tail (a second end record) repeats the new end record once the stream is
        closed (`open_end` false)."""
        self.records.truncate(k)
        self.records.extend(records)
        self.sends.truncate(self.lead + k)  # the lead and the plan's first k frames (the old tail goes)
        self.sends.extend(sends)
        self.open_end = open_end
        if self._tail_send is not None and not open_end:
            self._tail_send = sends[-1]  # the new end record: the tail is a copy of it
        self.tail = 1 if self._tail_send is not None and not open_end else 0
        if self.tail and self._tail_send is not None:
            self.sends.append(self._tail_send)

    def retire(self, k: int) -> int:
        """Forget the plan's records before index k and the stream's frames before them (and before
        `confirmed`: a frame not yet confirmed in the FIFO may be resent). The caller (the coordinator)
        picks k so that nothing before it is read again: consumed by every drive, behind every SYNC still
        to be attributed, behind every splice point. Returns the records and frames dropped."""
        k = max(0, min(k, self.confirmed - self.lead - 1))
        return self.records.drop_before(k) + self.sends.drop_before(min(self.lead + k, self.confirmed))

    @property
    def pending(self) -> bool:
        """An unconfirmed batch is out, or a deficit is being watched: send nothing new."""
        return self.sent_end > self.confirmed or self.suspect_sync is not None

    # ---- accounting -------------------------------------------------------------------------------
    def account(
        self, sync: int, consumed: int, fill: int, slack_ms: Callable[[int], float], congested: bool = False,
        consumed_hi: int | None = None, hidden: int = 0,
    ) -> Failure | None:
        """Check the fill the drive reported at SYNC `sync` against the records sent and consumed.

        `consumed`..`consumed_hi` are the stream records the drive may have consumed by then (one value
        for a drive locked to SYNC), `hidden` the record it interpolates towards when it does not count
        it. `slack_ms(i)` is the time from SYNC `sync` until record i becomes the interpolation target
        (infinite before the start). `congested`: the measured bus load is over the limit, so missing
        records are presumed late, not lost: keep waiting while there is time, never resend (a late
        original would then arrive twice), and fail BUS_OVERLOAD when the time is up. Returns a Failure,
        or None (possibly after scheduling a resend).
        """
        visible = self.batch_visible(sync)
        c_hi = consumed if consumed_hi is None else max(consumed, consumed_hi)
        expected = self.expected_fill(sync, consumed, hidden)  # nothing missing, the least consumption
        lowest = expected - (c_hi - consumed)  # ... and the most consumption the drive's clock allows
        batch = self.sent_end - self.confirmed if visible else 0
        lo, hi = self.confirmed, self.sent_end
        node = self.node_id
        if fill > expected:
            return Failure(
                oc.PROTOCOL,
                f"node {node}: the FIFO holds {fill} records at SYNC {sync}, {fill - expected} more "
                f"than sent and not consumed ({expected}): a record arrived twice",
                {"expected_fill": expected, "fill": fill},
            )
        if fill >= lowest and (batch == 0 or fill == expected):
            if visible:
                self.confirmed = self.sent_end
                if self.repair_pending:
                    self.losses_repaired += self.repair_pending
                    self.repair_pending = 0
            if self.suspect_sync is not None:
                self.late_batches += 1
                self.suspect_sync = None
            return None
        # missing records: between d_min and d_max of the unconfirmed batch (a range only when the drive's
        # clock leaves the consumption open)
        d_min = max(0, lowest - fill)
        d_max = expected - fill
        if d_min > batch:
            return Failure(
                oc.PROTOCOL,
                f"node {node}: the FIFO holds {fill} records at SYNC {sync}, {d_min} fewer than expected "
                f"({lowest}) but only {batch} are unconfirmed: the drive consumed records the "
                f"plan does not explain",
                {"expected_fill": lowest, "fill": fill, "unconfirmed": batch},
            )
        if self.suspect_sync is None:
            self.suspect_sync = sync
        slack = slack_ms(lo)
        ambiguous = d_min < d_max and (d_min == 0 or d_min < batch <= d_max)
        if slack >= self._period + self._margin and (
            congested or ambiguous or sync - self.suspect_sync < self._confirm_syncs
        ):
            return None  # maybe late (or consumed early), not lost: wait, send nothing new meanwhile
        if d_min == 0:
            # out of time with a reading that needs no loss: take it (a resend could arrive twice)
            self.confirmed = self.sent_end
            self.late_batches += 1
            self.suspect_sync = None
            return None
        deficit = d_min if d_min == d_max else (batch if d_min <= batch <= d_max else d_min)
        if congested:
            return Failure(
                oc.BUS_OVERLOAD,
                f"node {node}: {deficit} of records {lo}..{hi - 1} still not delivered at SYNC {sync} on an "
                f"overloaded bus, and record {lo} is due in {slack:g} ms",
                {"missing": deficit, "first_record": lo, "slack_ms": slack},
            )
        self.losses_detected += deficit
        if deficit < batch:
            return Failure(
                oc.POINT_LOST,
                f"node {node}: {deficit} of the {batch} records {lo}..{hi - 1} sent in one cycle did not "
                f"arrive; which ones is unknown, so no resend can keep the execution order",
                {"lost": deficit, "batch": batch, "first_record": lo},
            )
        if slack < self._margin:
            return Failure(
                oc.BUFFER_UNDERFLOW,
                f"node {node}: records {lo}..{hi - 1} were lost and record {lo} is due in {slack:g} ms, "
                f"too soon to resend (predicted underflow)",
                {"predicted": True, "lost": deficit, "first_record": lo, "slack_ms": slack},
            )
        # the whole batch is missing and nothing later was sent: resend it, order unchanged
        self.repair_pending += deficit
        self.sent_end = self.confirmed
        self.suspect_sync = None
        return None

    def batch_visible(self, sync: int) -> bool:
        """Can the drive's fill at SYNC `sync` hold the unconfirmed batch? From its tag on, and with `echoed`
        only once all of its frames came back from the bus (an answer fed before that was sampled before)."""
        return self.sent_end > self.confirmed and self.batch_tag <= sync and self.in_flight == 0

    def on_wire(self, sync_count: int | None) -> None:
        """One of our record frames came back from the bus after SYNC `sync_count`: the last of a batch sets
        the SYNC it counts from (`sync_count` + 1, whatever SYNC it was meant for: a frame the machine held up
        counts later, one sent early counts earlier). An echo with no frame taken is not this job's."""
        if self.in_flight == 0:
            return
        self.in_flight -= 1
        if self.in_flight == 0 and sync_count is not None:
            self.batch_tag = sync_count + 1

    def expected_fill(self, sync: int, consumed: int, hidden: int = 0) -> int:
        """The fill the drive can report at SYNC `sync` with nothing missing, having consumed `consumed`
        stream records (the unconfirmed batch counts from its tag on). More is never possible there: a fill
        above it is a duplicate, or an answer to another SYNC (the attribution tries that first)."""
        return (self.sent_end if self.batch_visible(sync) else self.confirmed) - hidden - consumed

    def possible_fill(self, sync: int, consumed: int, consumed_hi: int, hidden: int = 0) -> tuple[int, int]:
        """[least, most] fill the drive can report at SYNC `sync` without a PROTOCOL fault: most = nothing
        missing and the least consumption; least = the whole unconfirmed batch missing and the most
        consumption its clock allows. Outside it the answer is to another SYNC, or a fault."""
        most = self.expected_fill(sync, consumed, hidden)
        batch = self.sent_end - self.confirmed if self.batch_visible(sync) else 0
        return most - (max(consumed, consumed_hi) - consumed) - batch, most

    def take(self, n: int, tag: int) -> list[Send]:
        """The next n frames of the stream, sent now and counted in the fill from SYNC `tag`."""
        lo = self.sent_end
        hi = lo + n
        out = self.sends[lo:hi]
        if lo < self.max_sent:
            self.resends += min(hi, self.max_sent) - lo
        if hi > self.max_sent:
            self.max_sent = hi
        self.sent_end = hi
        self.batch_tag = tag
        self.frames_sent += n
        if self.echoed:
            self.in_flight += n
        return out

    # ---- position demand prediction ---------------------------------------------------------------
    def expected_demand(self, elapsed_ms: int, ends: Sequence[int]) -> int | None:
        """The drive's position demand after `elapsed_ms` of interpolation, rounded to nearest (None: not
        predictable here, i.e. inside a segment without counts_per_rev)."""
        out = self.demand_candidates(elapsed_ms, ends)
        return out[0] if out else None

    def demand_candidates(self, elapsed_ms: int, ends: Sequence[int]) -> tuple[int, ...]:
        """The position demand after `elapsed_ms` ms of interpolation under each rounding reading the axis
        may have (one when known, nearest and toward zero when not); () when not predictable."""
        recs = self.records
        if elapsed_ms <= 0:
            return (self.start_position,)
        if elapsed_ms >= ends[-1]:
            return (recs[-1].position,)
        k = bisect_right(ends, elapsed_ms)  # records consumed; record k is the current target
        prev_end = ends[k - 1] if k else 0
        if elapsed_ms == prev_end:
            return (recs[k - 1].position,)
        cpr = self._cpr
        if cpr is None:
            return ()
        rec = recs[k]
        if k:
            prev = recs[k - 1]
            p_prev, v_prev = prev.position, rpm_to_counts_per_ms(prev.velocity, cpr)
        else:
            p_prev, v_prev = self.start_position, 0.0
        coeffs = coefficients(
            p_prev, v_prev, rec.position, rpm_to_counts_per_ms(rec.velocity, cpr), rec.time_ms
        )
        x = evaluate(coeffs, elapsed_ms - ends[k])[0]
        return tuple(r(x) for r in self._rounders)

    def end_acceleration(self, index: int) -> float | None:
        """The drive's Hermite acceleration (counts/ms^2) at the end of record `index`'s segment."""
        cpr = self._cpr
        if cpr is None or index < 0:
            return None if cpr is None else 0.0
        rec = self.records[index]
        if index:
            prev = self.records[index - 1]
            p_prev, v_prev = prev.position, rpm_to_counts_per_ms(prev.velocity, cpr)
        else:
            p_prev, v_prev = self.start_position, 0.0
        coeffs = coefficients(
            p_prev, v_prev, rec.position, rpm_to_counts_per_ms(rec.velocity, cpr), rec.time_ms
        )
        return evaluate(coeffs, 0.0)[2]

    # ---- telemetry --------------------------------------------------------------------------------
    def observe_fill(self, fill: int, underflow_warning: int, overflow_warning: int, in_window: bool) -> None:
        """The drive's fill at a SYNC; its warnings are what 0x20C4:01 bits 0 and 1 say (seed 000
        4.3.6.2: below the underflow level 0x20C4:02, above the overflow level 0x20C4:03), counted from
        the fill since TPDO1 does not carry the buffer status."""
        self.last_fill = fill
        if fill > overflow_warning:
            self.overflow_warnings += 1
        if in_window:
            if self.min_fifo is None or fill < self.min_fifo:
                self.min_fifo = fill
            if self.max_fifo is None or fill > self.max_fifo:
                self.max_fifo = fill
            if fill < underflow_warning:
                self.underflow_warnings += 1

    def telemetry(self) -> AxisTelemetry:
        return AxisTelemetry(
            node_id=self.node_id,
            state=self.state.value,
            points_sent=self.max_sent,
            frames_sent=self.frames_sent,
            resends=self.resends,
            losses_detected=self.losses_detected,
            losses_repaired=self.losses_repaired,
            late_batches=self.late_batches,
            min_fifo=self.min_fifo,
            max_fifo=self.max_fifo,
            underflow_warnings=self.underflow_warnings,
            overflow_warnings=self.overflow_warnings,
            start_sync=self.start_sync,
            end_sync=self.end_sync,
            last_fill=self.last_fill,
            max_demand_error_counts=self.max_demand_error,
            errors=tuple(self.errors),
        )
