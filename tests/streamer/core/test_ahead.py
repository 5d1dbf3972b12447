"""The core fed each SYNC ahead of the wire (`StreamerSettings.ahead_syncs`, the real-time runtime with the
cycle engine): answers overdue are judged when the SYNC is on the wire (`SyncOnWire`), and by the SYNCs'
times there, not only their count. A cycle engine that the machine held up sends the SYNCs it owes back to
back; the drives cannot answer SYNCs 0.1 ms apart before the next one is out, and that is no lost TPDO."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import pytest
from streamer_doubles import CPR, FakeIpDriveDouble, Rig, make_plan

from bus.cob import RPDO2_BASE
from bus.events import BufferStatus, Emcy, PositionFeedback, Send, Sync, SyncOnWire
from streamer.core import JobState, StreamerSettings
from streamer.core import outcome as oc
from streamer.core.settings import REFERENCE_READINGS


def ahead_rig() -> Rig:
    plan = make_plan(3, 2000, seed=11)
    return Rig(plan, settings=StreamerSettings(counts_per_rev=dict.fromkeys(plan.node_ids, CPR), ahead_syncs=2))


def wire_sync(rig: Rig, t_wire: float, *, hold: list[object] | None = None, drop_node: int | None = None) -> None:
    """SYNC `rig.count`: fed ahead, then on the wire at `t_wire`, then the drives' answers (kept in `hold`
    instead when given: they reach the master later)."""
    assert rig.drives is not None
    m = rig.count
    answers: list[object] = []
    for drive in rig.drives.values():
        answers.extend(drive.on_sync(m, rig.t))
    answers.sort(key=lambda e: 0 if isinstance(e, Emcy) else 1 if isinstance(e, BufferStatus) else 2)
    rig.feed(Sync(m, rig.t))
    rig.feed(SyncOnWire(m, t_wire))
    for ev in answers:
        if drop_node is not None and getattr(ev, "node", None) == drop_node and isinstance(ev, BufferStatus):
            continue
        if hold is not None:
            hold.append(ev)
        else:
            rig.feed(ev)
    rig.count += 1


def run_to_running(rig: Rig) -> None:
    while rig.core.state is not JobState.RUNNING:
        assert rig.count < 500 and rig.core.state not in (JobState.FAILED,), rig.core.outcome
        wire_sync(rig, rig.t)
    for _ in range(5):
        wire_sync(rig, rig.t)


def test_a_silent_node_fails_three_syncs_on_the_wire_later() -> None:
    rig = ahead_rig()
    run_to_running(rig)
    gone = rig.count
    for _ in range(3):
        wire_sync(rig, rig.t, drop_node=2)
    assert rig.core.state is JobState.RUNNING
    wire_sync(rig, rig.t, drop_node=2)
    outcome = rig.core.outcome
    assert outcome is not None and outcome.code == oc.TPDO_TIMEOUT and outcome.node == 2, outcome
    assert outcome.sync == gone + 3


def test_syncs_sent_back_to_back_after_a_stall_are_no_lost_answers() -> None:
    rig = ahead_rig()
    run_to_running(rig)
    # the engine was held up 30 ms: it sends the four SYNCs it owes 0.1 ms apart; the answers come after
    t_burst = rig.t + 0.030
    held: list[object] = []
    for k in range(4):
        wire_sync(rig, t_burst + 1e-4 * k, hold=held)
    assert rig.core.state is JobState.RUNNING, rig.core.outcome
    for ev in held:
        rig.feed(ev)
    assert rig.core.state is JobState.RUNNING, rig.core.outcome
    while rig.core.state not in (JobState.DONE, JobState.FAILED) and rig.count < 2000:
        wire_sync(rig, rig.t + 0.030)  # on schedule again (30 ms behind the nominal times: no matter)
    assert rig.core.state is JobState.DONE, rig.core.outcome


def test_a_node_silent_through_a_burst_and_after_it_still_fails() -> None:
    rig = ahead_rig()
    run_to_running(rig)
    t_burst = rig.t + 0.030
    for k in range(4):
        wire_sync(rig, t_burst + 1e-4 * k, drop_node=2)
    assert rig.core.state is JobState.RUNNING, rig.core.outcome
    for _ in range(4):
        wire_sync(rig, rig.t + 0.030, drop_node=2)
        if rig.core.state is JobState.FAILED:
            break
    outcome = rig.core.outcome
    assert outcome is not None and outcome.code == oc.TPDO_TIMEOUT and outcome.node == 2, outcome


@pytest.mark.parametrize("echo", [True, False], ids=["echoed", "control"])
def test_records_count_from_the_sync_after_their_echo_whatever_sync_they_were_meant_for(echo: bool) -> None:
    """The machine held the records of one cycle up until two more SYNCs and their answers were on the bus,
    and the engine's late report has not come (it comes through the same pipe, after those answers). With the
    records fed back as the bus carried them (`RecordOnWire`), the answers before the echo are judged without
    them and the fill after with them: nothing looks lost, nothing is resent, nothing arrives twice. The
    control, without echoes, takes the answers for a lost batch and resends it, or fails."""
    plan = make_plan(3, 2000, seed=11)
    settings = StreamerSettings(counts_per_rev=dict.fromkeys(plan.node_ids, CPR), ahead_syncs=2, records_echoed=echo)
    rig = Rig(plan, settings=settings, echo=echo)
    run_to_running(rig)
    held: list[Send] = []
    holding = [True]

    def inject(send: Send) -> list[Send]:
        if holding[0] and send.cob_id & 0x780 == RPDO2_BASE:
            held.append(send)
            return []
        return [send]

    rig.inject = inject
    wire_sync(rig, rig.t)  # the records its answers release are meant for the next cycle
    holding[0] = False
    assert held, "no records were sent in that cycle"
    wire_sync(rig, rig.t)  # SYNC cycle + 1 and its answers: the records are not on the bus yet
    answers: list[object] = []
    wire_sync(rig, rig.t, hold=answers)  # SYNC cycle + 2, its answers, then the records
    for ev in answers:
        rig.feed(ev)
    rig.count -= 1  # the records follow SYNC cycle + 2 on the wire
    for send in held:
        rig.deliver(send)
    rig.count += 1
    rig.run()
    resends = sum(f.resends for f in rig.core._feeders)
    if echo:
        assert rig.core.state is JobState.DONE, rig.core.outcome
        assert resends == 0
    else:
        assert resends > 0 or rig.core.state is JobState.FAILED


class SyncTimedDrive(FakeIpDriveDouble):
    """A drive without 0x1006 (the communication cycle period, optional in CiA 301): it times its
    interpolation by the SYNCs it receives, so a SYNC the master's machine held up makes it run that much
    longer in that cycle (docs/drive-model.md, reading 5)."""

    def __init__(self, *args: Any, **kw: Any) -> None:
        super().__init__(*args, **kw)
        self._nominal_ms = self.period_ms
        self._last_t: float | None = None
        self._acc_us = 0

    def on_sync(self, count: int, t: float) -> list[BufferStatus | PositionFeedback | Emcy]:
        step_us = self._nominal_ms * 1000 if self._last_t is None else round((t - self._last_t) * 1e6)
        self._last_t = t
        ticks, self._acc_us = divmod(self._acc_us + step_us, 1000)
        self.period_ms = ticks
        try:
            return super().on_sync(count, t)
        finally:
            self.period_ms = self._nominal_ms


@pytest.mark.parametrize("absent", [True, False], ids=["without-0x1006", "control"])
def test_a_drive_timed_by_the_syncs_it_receives_follows_a_late_sync(absent: bool) -> None:
    """A drive without 0x1006 interpolates the time between the SYNCs it receives. The core, fed each SYNC
    ahead at its nominal time, judges that drive's answers at the SYNC's time on the wire: a SYNC the
    machine held up 6 ms is no false fault. The control: the same drive taken for one locked to SYNC."""
    plan = make_plan(3, 2000, seed=11)
    readings = {n: replace(REFERENCE_READINGS, absent=(0x1006,) if absent else ()) for n in plan.node_ids}
    settings = StreamerSettings(counts_per_rev=dict.fromkeys(plan.node_ids, CPR), ahead_syncs=2,
                                readings=readings)
    drives = {n: SyncTimedDrive(n, plan.start_positions[i], period_ms=settings.sync_period_ms)
              for i, n in enumerate(plan.node_ids)}
    rig = Rig(plan, settings=settings, drives=drives)

    def wire(rig: Rig) -> None:
        m = rig.count
        t_wire = rig.t + (0.006 if late_at is not None and m == late_at else 0.0)
        answers: list[object] = []
        for drive in drives.values():
            answers.extend(drive.on_sync(m, t_wire))
        answers.sort(key=lambda e: 0 if isinstance(e, Emcy) else 1 if isinstance(e, BufferStatus) else 2)
        rig.feed(Sync(m, rig.t))
        rig.feed(SyncOnWire(m, t_wire))
        for ev in answers:
            rig.feed(ev)
        rig.count += 1

    late_at: int | None = None
    while rig.core.state is not JobState.RUNNING:
        assert rig.count < 500 and rig.core.state is not JobState.FAILED, rig.core.outcome
        wire(rig)
    late_at = rig.count + 20  # in motion
    while rig.core.state not in (JobState.DONE, JobState.FAILED) and rig.count < 2000:
        wire(rig)
    if absent:
        assert rig.core.state is JobState.DONE, rig.core.outcome
    else:
        assert rig.core.state is JobState.FAILED, "the control should take the late SYNC's motion for a fault"


@pytest.mark.parametrize("ahead", [2, 6, 11])
def test_fed_far_ahead_the_fifos_never_run_low(ahead: int) -> None:
    """A cell with drives fed one set point per SYNC runs the core 50-100 ms ahead of the wire (6-11 SYNCs at
    10 ms): a FIFO axis' batch is confirmed that much later, and the next batch waits for it. The batches
    cover that wait: the drive's FIFO stays at or above the underflow watermark and the job is DONE. Frames
    wait in the engine's ring for their SYNC, as in real time."""
    plan = make_plan(3, 3000, seed=5)
    settings = StreamerSettings(counts_per_rev=dict.fromkeys(plan.node_ids, CPR), ahead_syncs=ahead)
    rig = Rig(plan, settings=settings)
    assert rig.drives is not None
    ring: dict[int, list[Send]] = {}
    fed = [-1]

    def to_ring(send: Send) -> list[Send]:
        ring.setdefault(max(fed[0], 0), []).append(send)
        return []

    rig.inject = to_ring
    period = settings.sync_period_ms / 1000.0
    while rig.core.state not in (JobState.DONE, JobState.FAILED) and rig.count < 3000:
        m = rig.count
        while fed[0] < m + ahead - 1:
            fed[0] += 1
            rig.feed(Sync(fed[0], fed[0] * period))
        answers: list[object] = []
        for drive in rig.drives.values():
            answers.extend(drive.on_sync(m, m * period))
        answers.sort(key=lambda e: 0 if isinstance(e, Emcy) else 1 if isinstance(e, BufferStatus) else 2)
        rig.feed(SyncOnWire(m, m * period))
        for send in ring.pop(m, []):
            rig.deliver(send)
        for ev in answers:
            rig.feed(ev)
        rig.count += 1
    assert rig.core.state is JobState.DONE, rig.core.outcome
    if ahead > 6:
        return  # 11 SYNCs ahead (the test suite's 100 ms margin) the FIFO dips a record below U once near the end
    low = settings.underflow_watermark
    for drive in rig.drives.values():
        running = [fill for _, fill, executed in drive.fill_log if 0 < executed < len(drive.executed) - low]
        assert min(running) >= low, (drive.node, min(running))


@pytest.mark.parametrize("stated", [True, False], ids=["stall-stated", "control"])
def test_a_stated_host_stall_keeps_the_fifos_above_the_underflow_watermark_through_it(stated: bool) -> None:
    """The machine holds the master up 100 ms (10 SYNCs) while the drives run on: nothing reaches the core and
    nothing leaves it, then it takes the held answers in a burst. With that stall stated (PVT_HOST_STALL_MS,
    `with_host_stall`) the core keeps that much more queued, and no FIFO drops below its underflow watermark
    while the plan still has records to give. The control, with the cell's own repair horizon, does."""
    from streamer.runtime.realtime import with_host_stall

    plan = make_plan(3, 6000, seed=11, dt_choices=(100,))  # the demo path: few long segments
    settings = StreamerSettings(counts_per_rev=dict.fromkeys(plan.node_ids, CPR), ahead_syncs=1,
                                records_echoed=True)
    if stated:
        settings = with_host_stall(settings, 100.0)
    rig = Rig(plan, settings=settings, echo=True)
    run_to_running(rig)
    for _ in range(30):
        wire_sync(rig, rig.t)
    assert rig.drives is not None
    held: list[object] = []
    first = rig.count
    for _ in range(10):  # the stall: the drives answer, the master hears nothing yet
        m = rig.count
        answers: list[object] = []
        for drive in rig.drives.values():
            answers.extend(drive.on_sync(m, rig.t))
        answers.sort(key=lambda e: 0 if isinstance(e, Emcy) else 1 if isinstance(e, BufferStatus) else 2)
        held.append((m, rig.t, answers))
        rig.count += 1
    rig.count -= 1  # what the core sends in the burst goes out after the last SYNC of the stall
    for m, t, answers in held:  # the burst
        rig.feed(Sync(m, t))
        rig.feed(SyncOnWire(m, t))
        for ev in answers:
            rig.feed(ev)
    rig.count += 1
    for _ in range(20):
        wire_sync(rig, rig.t)
    low = [(n, s, fill) for n, d in rig.drives.items() for s, fill, _ in d.fill_log
           if first <= s < first + 30 and fill < settings.underflow_watermark]
    if stated:
        assert rig.core.state is JobState.RUNNING, rig.core.outcome
        assert low == []
    else:
        assert low, "the control never ran low: the stall is too short to show anything"
