"""A real-time master that lags behind the bus: its records reach the drives one SYNC later than the
core planned. With the runtime's `wire_sync` hint the core counts them from the right SYNC and the job
ends DONE with nothing resent; a fill that dips below the underflow watermark on a quiet bus is a late
master, not an overload, and is only fatal when the drive is one segment from underflowing."""

from __future__ import annotations

from dataclasses import dataclass, field

from streamer_doubles import CPR, Rig, make_plan

from bus.events import Send, Sync
from streamer.core import outcome as oc
from streamer.core.coordinator import JobState
from streamer.core.settings import StreamerSettings


@dataclass
class LaggingRig(Rig):
    """Records sent while `lagging` reach the drives after the next SYNC (the master was late), and
    the runtime tells the core so through `wire_sync` when `hint` is on."""

    lagging: bool = False
    hint: bool = True
    stalled: bool = False  # records pile up and go out only when the stall ends
    lag_all: bool = False  # while lagging, every frame (the start controlword too) goes after the next SYNC
    held: list[Send] = field(default_factory=list)

    def feed(self, event: object) -> None:
        wire = self.count + 1 if (self.lagging and self.hint) else None
        reaction = self.core.handle(event, wire_sync=wire)
        self.changes.extend(reaction.changes)
        for send in reaction.sends:
            self.sent.append((self.count, send))
            if self.stalled and send.cob_id & 0x780 == 0x300:
                self.held.append(send)
            elif self.lagging and (self.lag_all or send.cob_id & 0x780 == 0x300):
                self.delayed.append(send)
            else:
                self.deliver(send)


def _run(hint: bool, lag_syncs: range, lead_ms: int = 200, lag_all: bool = False) -> LaggingRig:
    plan = make_plan(3, 4000, seed=41)
    settings = StreamerSettings(counts_per_rev=dict.fromkeys(plan.node_ids, CPR), lead_ms=lead_ms)
    rig = LaggingRig(plan, settings, hint=hint, lag_all=lag_all)
    for _ in range(2000):
        if rig.core.state in (JobState.DONE, JobState.FAILED, JobState.CANCELLED):
            break
        rig.lagging = rig.count in lag_syncs
        rig.sync()
    return rig


def test_late_records_with_the_wire_hint_are_neither_lost_nor_resent() -> None:
    rig = _run(hint=True, lag_syncs=range(60, 90))
    assert rig.core.state is JobState.DONE, rig.core.outcome
    for t in rig.core.telemetry():
        assert t.resends == 0 and t.losses_detected == 0


def test_a_master_lagging_through_the_start_starts_every_drive_at_the_sync_its_controlword_reaches() -> None:
    """The master lags a SYNC through priming and the start (no cycle engine: its frames go out when it gets
    to them): the start controlword reaches the drives after the SYNC after the one the core decided at, so
    the start SYNC is the one after the newest on the wire, not after the core's (a false START_FAILED)."""
    rig = _run(hint=True, lag_syncs=range(0, 400), lag_all=True)
    assert rig.core.state is JobState.DONE, rig.core.outcome


def test_without_the_hint_the_same_lag_is_misread() -> None:
    rig = _run(hint=False, lag_syncs=range(60, 90))
    tel = rig.core.telemetry()
    # the core takes the late batches for missing ones: it holds them (late_batches) or fails
    assert rig.core.state is JobState.FAILED or any(t.late_batches > 0 for t in tel)


def _stalled_run(stall: range, lead_ms: int) -> Rig:
    """The master's thread stalls (a GC pause, a busy interpreter) during `stall`: the drives go on
    answering every SYNC, the core sees nothing; when it wakes it works through the queued events,
    and what it sends goes out after the newest SYNC (it passes that as `wire_sync`)."""
    plan = make_plan(3, 4000, seed=41)
    settings = StreamerSettings(counts_per_rev=dict.fromkeys(plan.node_ids, CPR), lead_ms=lead_ms)
    rig = Rig(plan, settings)
    queued: list[object] = []
    assert rig.drives is not None
    for _ in range(2000):
        if rig.core.state in (JobState.DONE, JobState.FAILED, JobState.CANCELLED):
            break
        m = rig.count
        events: list[object] = [Sync(m, rig.t)]
        for drive in rig.drives.values():
            events.extend(drive.on_sync(m, rig.t))
        queued.extend(events)
        if m not in stall:
            for ev in queued:
                reaction = rig.core.handle(ev, wire_sync=m)
                for send in reaction.sends:
                    rig.deliver(send)
            queued = []
        rig.count += 1
    return rig


def test_master_stalls_of_growing_length_end_done_or_fail_before_an_unforeseen_underflow() -> None:
    """Stalls of 1..14 SYNCs at lead 60 ms: short ones dip below the watermark and end DONE (no resend,
    no loss); a stall that leaves less than two periods of motion queued fails BUS_OVERLOAD at once;
    only a stall so long the drive ran dry while the master slept ends in the drive's underflow EMCY."""
    seen: dict[str, int] = {}
    dipped_but_done = False
    for length in range(1, 15):
        rig = _stalled_run(range(60, 60 + length), lead_ms=60)
        outcome = rig.core.outcome
        assert outcome is not None
        code = outcome.code or "DONE"
        seen[code] = seen.get(code, 0) + 1
        tel = rig.core.telemetry()
        if code == "DONE":
            assert all(t.resends == 0 and t.losses_detected == 0 for t in tel)
            dipped_but_done |= min(t.min_fifo for t in tel if t.min_fifo is not None) < 4
        elif code == oc.BUS_OVERLOAD:
            # (a drive may already have run dry while the master slept: nothing could be sent then)
            assert outcome.detail["covered_ms"] < 2 * 10
        else:
            assert code == oc.BUFFER_UNDERFLOW and "EMCY" in outcome.message, outcome
    assert dipped_but_done, seen
    assert seen.get(oc.BUS_OVERLOAD, 0) >= 1, seen
