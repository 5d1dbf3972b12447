"""Every fault path: quick stop to every axis in the failing reaction, FAILED with code and node, then
nothing is ever sent again. Plus loss repair, duplicates, reordering, late frames, overload."""

from __future__ import annotations

import random
from collections.abc import Callable

import pytest
from streamer_doubles import CPR, Rig, make_plan

from bus.cob import RPDO1_BASE, RPDO2_BASE, unpack_controlword
from bus.events import (
    AdapterError,
    Bootup,
    BufferStatus,
    BusLoad,
    Cancel,
    Emcy,
    HeartbeatLost,
    PositionFeedback,
    Send,
    SendFailed,
    Sync,
)
from planner.encoding.record import unpack
from streamer.core import Coordinator, JobState, StreamerSettings, StreamPlan
from streamer.core import outcome as oc
from streamer.core.coordinator import CW_QUICK_STOP, CW_START_IP, TERMINAL


def running_rig(plan: StreamPlan | None = None, syncs_into_motion: int = 5, **kw: object) -> Rig:
    rig = Rig(plan or make_plan(3, 2000, seed=11), **kw)  # type: ignore[arg-type]
    rig.run(until=lambda r: r.core.state is JobState.RUNNING)
    for _ in range(syncs_into_motion):
        rig.sync()
    assert rig.core.state is JobState.RUNNING
    return rig


def assert_failed_and_poisoned(rig: Rig, code: str, node: int | None, first_new: int) -> None:
    outcome = rig.core.outcome
    assert rig.core.state is JobState.FAILED, outcome
    assert outcome is not None and outcome.code == code, outcome
    assert outcome.node == node, outcome
    assert str(node) in outcome.message if node is not None else True
    # quick stop to every axis, once, in the failing reaction
    new = [s for _, s in rig.sent[first_new:]]
    quick = [s for s in new if s.cob_id & 0x780 == RPDO1_BASE and unpack_controlword(s.data) == CW_QUICK_STOP]
    assert sorted(s.cob_id - RPDO1_BASE for s in quick) == sorted(rig.plan.node_ids)
    assert rig.drives is not None
    # poisoned: events keep coming, nothing is sent
    n = len(rig.sent)
    for _ in range(20):
        rig.sync()
    rig.feed(Cancel(rig.t))
    rig.feed(Emcy(rig.plan.node_ids[0], 0x8611, 0, bytes(8), rig.t))
    rig.feed(SendFailed("again", rig.t))
    assert len(rig.sent) == n
    assert not rig.sends_after_terminal
    for drive in rig.drives.values():
        assert not drive.active


# ---- drive- and bus-reported faults ------------------------------------------------------------------
@pytest.mark.parametrize(
    ("code", "data", "expected"),
    [
        (0x8611, bytes(8), oc.FOLLOWING_ERROR),
        (0x8780, bytes(8), oc.SYNC_LOST),
        (0x8782, bytes(3) + (0x0100).to_bytes(2, "little") + bytes(3), oc.BUFFER_UNDERFLOW),
        (0x8782, bytes(3) + (0x0200).to_bytes(2, "little") + bytes(3), oc.BUFFER_OVERFLOW),
        (0x8782, (0x0200).to_bytes(2, "little") + bytes(3), oc.BUFFER_OVERFLOW),  # 5 manufacturer bytes only
        (0x8130, bytes(8), oc.DRIVE_FAULT),
        (0xFF10, bytes(8), oc.DRIVE_FAULT),
        (0x5530, bytes(8), oc.DRIVE_FAULT),
    ],
)
def test_emcy_fails_the_job_with_its_code(code: int, data: bytes, expected: str) -> None:
    rig = running_rig()
    first = len(rig.sent)
    rig.feed(Emcy(2, code, 0x81, data, rig.t))
    assert_failed_and_poisoned(rig, expected, 2, first)
    assert rig.core.outcome is not None
    assert rig.core.outcome.detail["emcy_code"] == code
    assert f"0x{code:04X}" in rig.core.outcome.message


@pytest.mark.parametrize(
    ("make_event", "code", "node"),
    [
        (lambda t: HeartbeatLost(3, t), oc.NODE_LOST, 3),
        (lambda t: Bootup(1, t), oc.NODE_REBOOT, 1),
        (lambda t: SendFailed("bus-off", t), oc.BUS_ERROR, None),
        (lambda t: AdapterError("rx thread", "KeyError: 7", t), oc.BUS_ERROR, None),
    ],
)
def test_node_and_bus_faults(make_event: Callable[[float], object], code: str, node: int | None) -> None:
    rig = running_rig()
    first = len(rig.sent)
    rig.feed(make_event(rig.t))
    assert_failed_and_poisoned(rig, code, node, first)


def test_a_fault_during_priming_also_quick_stops() -> None:
    rig = Rig(make_plan(2, 1000, seed=12))
    rig.run(until=lambda r: r.core.state is JobState.PRIMING and len(r.sent) > 4)
    first = len(rig.sent)
    rig.feed(HeartbeatLost(2, rig.t))
    assert_failed_and_poisoned(rig, oc.NODE_LOST, 2, first)


def test_events_from_other_nodes_and_emcy_reset_are_ignored() -> None:
    rig = running_rig()
    rig.feed(Emcy(99, 0x8611, 0, bytes(8), rig.t))
    rig.feed(HeartbeatLost(42, rig.t))
    rig.feed(Bootup(42, rig.t))
    rig.feed(Emcy(1, 0x0000, 0, bytes(8), rig.t))  # "error reset / no error"
    rig.feed(BufferStatus(77, 0x0027, 0x4000, 64, rig.t))
    rig.feed(PositionFeedback(77, 0, 0, rig.t))
    rig.run()
    assert rig.core.state is JobState.DONE


@pytest.mark.parametrize(
    ("bit", "code"),
    [
        (0x0100, oc.BUFFER_UNDERFLOW),
        (0x0200, oc.BUFFER_OVERFLOW),
        (0x0400, oc.DRIVE_FAULT),
        (0x0800, oc.DRIVE_FAULT),
    ],
)
def test_buffer_error_bits_in_the_tpdo(bit: int, code: str) -> None:
    rig = running_rig()
    assert rig.drives is not None
    rig.drives[2].errors |= bit
    first = len(rig.sent)
    rig.sync()
    assert_failed_and_poisoned(rig, code, 2, first)


def test_statusword_fault_bit_without_emcy() -> None:
    rig = running_rig()
    assert rig.drives is not None
    rig.drives[3].faulted = True  # a fault reaction without an EMCY on the bus
    rig.drives[3].active = False
    first = len(rig.sent)
    rig.sync()
    assert_failed_and_poisoned(rig, oc.DRIVE_FAULT, 3, first)


def test_tpdos_missing_for_three_syncs() -> None:
    rig = running_rig()
    gone = rig.count
    rig.tpdo_filter = lambda ev: not (getattr(ev, "node", 0) == 2 and isinstance(ev, BufferStatus))
    first = len(rig.sent)
    for _ in range(3):
        rig.sync()  # SYNCs gone, gone+1, gone+2 unanswered by node 2's TPDO1
    assert rig.core.state is JobState.RUNNING
    rig.sync()  # Sync(gone + 3): three SYNCs without TPDO1 from node 2
    assert rig.core.outcome is not None and rig.core.outcome.sync == gone + 3
    assert_failed_and_poisoned(rig, oc.TPDO_TIMEOUT, 2, first)


def test_a_wider_tpdo_timeout_waits_that_many_syncs() -> None:
    # [drive] tpdo_timeout_syncs in the cell TOML (tests/streamer/core/test_units.py: it reaches
    # StreamerSettings.from_cell); a host that stalls longer than three SYNCs needs it
    plan = make_plan(3, 2000, seed=11)
    rig = running_rig(plan, settings=StreamerSettings(counts_per_rev=dict.fromkeys(plan.node_ids, CPR),
                                                      tpdo_timeout_syncs=6))
    gone = rig.count
    rig.tpdo_filter = lambda ev: not (getattr(ev, "node", 0) == 2 and isinstance(ev, BufferStatus))
    first = len(rig.sent)
    for _ in range(6):
        rig.sync()  # three more unanswered SYNCs than the default waits for
    assert rig.core.state is JobState.RUNNING
    rig.sync()
    assert rig.core.outcome is not None and rig.core.outcome.sync == gone + 6
    assert_failed_and_poisoned(rig, oc.TPDO_TIMEOUT, 2, first)


def test_two_missing_tpdos_are_tolerated() -> None:
    rig = running_rig()
    gone = rig.count
    rig.tpdo_filter = lambda ev: not (getattr(ev, "node", 0) == 2 and gone <= rig.count < gone + 2)
    rig.run()
    assert rig.core.state is JobState.DONE, rig.core.outcome
    assert rig.drives is not None
    assert rig.drives[2].executed == list(rig.plan.records[1][:-1])


def test_sync_count_jump_is_sync_lost() -> None:
    rig = running_rig()
    first = len(rig.sent)
    rig.count += 1  # the runtime skipped a SYNC count
    rig.sync()
    assert_failed_and_poisoned(rig, oc.SYNC_LOST, None, first)


def test_sync_gap_check_is_optional() -> None:
    plan = make_plan(2, 1000, seed=13)
    settings = StreamerSettings(counts_per_rev=dict.fromkeys(plan.node_ids, CPR), sync_gap_factor=1.5)
    core = Coordinator(plan, settings)
    core.handle(Sync(0, 0.0))
    core.handle(Sync(1, 0.014))  # 1.4 periods: fine
    assert core.state is JobState.CONFIGURING
    core.handle(Sync(2, 0.030))  # 1.6 periods
    assert core.state is JobState.FAILED and core.outcome is not None and core.outcome.code == oc.SYNC_LOST


def test_sync_count_must_increase() -> None:
    core = Coordinator(make_plan(1, 500, seed=1), StreamerSettings())
    core.handle(Sync(5, 0.0))
    with pytest.raises(ValueError, match="must increase"):
        core.handle(Sync(5, 0.01))


def test_start_position_mismatch_fails_before_anything_is_sent() -> None:
    plan = make_plan(2, 1000, seed=14)
    rig = Rig(plan)
    assert rig.drives is not None
    rig.drives[2].demand += 5
    rig.drives[2].prev_p += 5
    rig.run(50)
    outcome = rig.core.outcome
    assert outcome is not None and outcome.code == oc.START_MISMATCH and outcome.node == 2
    assert "off by 5" in outcome.message
    assert rig.sent == []  # nothing moved, nothing sent


def test_drive_not_ready() -> None:
    plan = make_plan(2, 1000, seed=15)
    rig = Rig(plan)
    assert rig.drives is not None
    rig.drives[1].op_enabled = False
    rig.run(20)
    assert rig.core.outcome is not None and rig.core.outcome.code == oc.DRIVE_NOT_READY
    assert "operation enabled" in rig.core.outcome.message
    rig = Rig(plan)
    assert rig.drives is not None
    rig.drives[2].fifo.extend(plan.records[1][:3])
    rig.run(20)
    assert rig.core.outcome is not None and rig.core.outcome.code == oc.DRIVE_NOT_READY
    assert "FIFO holds 3" in rig.core.outcome.message
    assert rig.sent == []


def test_lost_start_controlword_is_start_failed() -> None:
    def drop_start(send: Send) -> list[Send]:
        if send.cob_id == RPDO1_BASE + 2 and unpack_controlword(send.data) == CW_START_IP:
            return []
        return [send]

    rig = Rig(make_plan(3, 1000, seed=16), inject=drop_start)
    rig.run(200)
    outcome = rig.core.outcome
    assert outcome is not None and outcome.code == oc.START_FAILED and outcome.node == 2
    assert outcome.sync == rig.core.start_sync  # detected on the start SYNC's TPDO
    rig.sync()  # the quick stop (synchronous RPDO1) applies at the next SYNC
    assert rig.drives is not None and not any(d.active for d in rig.drives.values())


# ---- construction-time feasibility -------------------------------------------------------------------
def test_plan_too_dense_for_the_bus_is_bus_overload_before_anything_is_sent() -> None:
    plan = make_plan(3, 1000, seed=17, dt_choices=(2,))
    core = Coordinator(plan, StreamerSettings(bitrate=250_000))
    assert core.state is JobState.FAILED
    assert core.outcome is not None and core.outcome.code == oc.BUS_OVERLOAD
    assert core.handle(Sync(0, 0.0)).sends == []
    big = make_plan(16, 500, seed=17)
    core = Coordinator(big, StreamerSettings(bitrate=125_000))
    assert core.outcome is not None and core.outcome.code == oc.BUS_OVERLOAD


def test_plan_too_dense_for_the_fifo_is_predicted_underflow() -> None:
    plan = make_plan(1, 2000, seed=18, dt_choices=(1,))
    core = Coordinator(plan, StreamerSettings(sync_period_ms=100))
    assert core.outcome is not None and core.outcome.code == oc.BUFFER_UNDERFLOW
    assert core.outcome.detail["predicted"] is True


# ---- loss, duplicate, reorder, late ------------------------------------------------------------------
def record_dropper(node: int, which: set[int]) -> Callable[[Send], list[Send]]:
    """Drop the record frames to `node` whose 0-based send number is in `which`."""
    seen = [0]

    def inject(send: Send) -> list[Send]:
        if send.cob_id == RPDO2_BASE + node:
            k = seen[0]
            seen[0] += 1
            if k in which:
                return []
        return [send]

    return inject


def sends_of(rig: Rig, node: int, record_index: int) -> list[int]:
    """SYNC cycles in which record `record_index` of `node` was sent."""
    rec = rig.plan.records[rig.plan.node_ids.index(node)][record_index]
    return [m for m, s in rig.sent if s.cob_id == RPDO2_BASE + node and unpack(s.data) == rec]


def test_a_lost_record_is_detected_and_resent_before_it_is_due() -> None:
    plan = make_plan(3, 3000, seed=19, dt_choices=(10, 20, 30))  # <= 1 record per axis per SYNC
    rig = Rig(plan, inject=record_dropper(2, {40}))
    rig.run()
    assert rig.core.state is JobState.DONE, rig.core.outcome
    assert rig.drives is not None
    assert rig.drives[2].executed == list(plan.records[1][:-1])  # exact, in order, once
    first, again = sends_of(rig, 2, 40)
    assert again - first <= 2  # detected and resent within 2 SYNCs
    t = rig.core.telemetry()[1]
    assert (t.losses_detected, t.losses_repaired, t.resends) == (1, 1, 1)


def test_random_one_percent_loss_is_all_repaired_with_sparse_grid() -> None:
    plan = make_plan(3, 6000, seed=20, dt_choices=(10, 20, 30, 40))
    rng = random.Random(20)
    drops = [0]

    def lossy(send: Send) -> list[Send]:
        if send.cob_id & 0x780 == RPDO2_BASE and rng.random() < 0.01:
            drops[0] += 1
            return []
        return [send]

    rig = Rig(plan, inject=lossy)
    rig.run()
    assert rig.core.state is JobState.DONE, rig.core.outcome
    assert rig.drives is not None
    for axis, node in enumerate(plan.node_ids):
        assert rig.drives[node].executed == list(plan.records[axis][:-1])
    detected = sum(t.losses_detected for t in rig.core.telemetry())
    repaired = sum(t.losses_repaired for t in rig.core.telemetry())
    assert drops[0] >= 3 and detected == repaired == drops[0]


def test_priming_loss_is_repaired() -> None:
    plan = make_plan(2, 1000, seed=21)
    rig = Rig(plan, inject=record_dropper(1, {1}))
    rig.run()
    assert rig.core.state is JobState.DONE, rig.core.outcome
    assert rig.core.telemetry()[0].losses_repaired == 1


def test_partial_batch_loss_is_point_lost_before_the_gap_executes() -> None:
    plan = make_plan(3, 3000, seed=22, dt_choices=(2, 3))  # several records per axis per SYNC
    rig = Rig(plan, inject=record_dropper(2, {200}))
    rig.run()
    outcome = rig.core.outcome
    assert outcome is not None and outcome.code == oc.POINT_LOST and outcome.node == 2
    assert rig.drives is not None
    executed = rig.drives[2].executed
    assert executed == list(plan.records[1][: len(executed)])  # nothing out of order was executed
    dropped_at = sends_of(rig, 2, 200)[0]
    assert outcome.sync is not None and outcome.sync - dropped_at <= 2
    assert "which ones is unknown" in outcome.message


def test_duplicate_record_is_protocol() -> None:
    plan = make_plan(3, 2000, seed=23)
    seen = [0]

    def dup(send: Send) -> list[Send]:
        if send.cob_id == RPDO2_BASE + 3:
            seen[0] += 1
            if seen[0] == 30:
                return [send, send]
        return [send]

    rig = Rig(plan, inject=dup)
    rig.run()
    outcome = rig.core.outcome
    assert outcome is not None and outcome.code == oc.PROTOCOL and outcome.node == 3
    assert "arrived twice" in outcome.message
    assert outcome.sync is not None and outcome.sync - sends_of(rig, 3, 29)[0] <= 1


def test_late_record_is_not_resent() -> None:
    plan = make_plan(2, 2000, seed=24)
    rig = Rig(plan)
    seen = [0]

    def delay(send: Send) -> list[Send]:
        if send.cob_id == RPDO2_BASE + 1:
            seen[0] += 1
            if seen[0] == 25:
                rig.delayed.append(send)  # arrives after the next SYNC: a deficit that heals
                return []
        return [send]

    rig.inject = delay
    rig.run()
    assert rig.core.state is JobState.DONE, rig.core.outcome
    t = rig.core.telemetry()[0]
    assert (t.late_batches, t.resends, t.losses_detected) == (1, 0, 0)
    assert rig.drives is not None and rig.drives[1].executed == list(plan.records[0][:-1])


def test_record_late_beyond_the_wait_then_resent_is_a_detected_duplicate() -> None:
    plan = make_plan(2, 2000, seed=25)
    rig = Rig(plan)
    held: list[Send] = []
    seen = [0]

    def hold(send: Send) -> list[Send]:
        if send.cob_id == RPDO2_BASE + 1:
            seen[0] += 1
            if seen[0] == 25:
                held.append(send)
                return []
            if held and seen[0] == 26:  # the resend: deliver it, and the late original after it
                rig.delayed.append(held.pop())
        return [send]

    rig.inject = hold
    rig.run()
    outcome = rig.core.outcome
    assert outcome is not None and outcome.code == oc.PROTOCOL and "twice" in outcome.message


def test_swapped_records_in_one_batch_are_caught_by_the_demand_check() -> None:
    plan = make_plan(2, 3000, seed=26, dt_choices=(2, 3))
    held: list[Send] = []
    seen = [0]

    def swap(send: Send) -> list[Send]:
        if send.cob_id == RPDO2_BASE + 1:
            seen[0] += 1
            if seen[0] == 150:
                held.append(send)
                return []
            if held:
                return [send, held.pop()]
        return [send]

    rig = Rig(plan, inject=swap)
    rig.run()
    outcome = rig.core.outcome
    assert outcome is not None and outcome.code == oc.PROTOCOL and outcome.node == 1
    assert "position demand" in outcome.message


def test_burst_of_40_lost_records_on_one_axis_is_buffer_underflow_and_all_axes_stop() -> None:
    plan = make_plan(3, 4000, seed=27)
    rig = Rig(plan, inject=record_dropper(2, set(range(60, 100))))
    rig.run()
    outcome = rig.core.outcome
    # every lost batch was resent while it could still arrive in time, and lost again: the buffer does not
    # cover 40 losses, so the drive underflows (its EMCY) or the core predicts it; either way BUFFER_UNDERFLOW
    assert outcome is not None and outcome.code == oc.BUFFER_UNDERFLOW and outcome.node == 2
    assert rig.drives is not None
    t = rig.core.telemetry()[1]
    assert t.resends > 0 and t.losses_repaired < t.losses_detected
    failed_at = outcome.sync
    rig.sync()  # the quick stop (synchronous RPDO1) applies at the next SYNC
    assert all(not d.active for d in rig.drives.values())  # all stopped within 1 SYNC
    executed = {n: len(d.executed) for n, d in rig.drives.items()}
    for _ in range(50):
        rig.sync()
    assert {n: len(d.executed) for n, d in rig.drives.items()} == executed  # no automatic resume
    assert failed_at is not None


def test_lost_record_too_close_to_its_due_time_is_predicted_underflow() -> None:
    plan = make_plan(2, 3000, seed=29)
    settings = StreamerSettings(counts_per_rev=dict.fromkeys(plan.node_ids, CPR), lead_ms=100, repair_margin_ms=200)
    rig = Rig(plan, settings, inject=record_dropper(1, {40}))
    rig.run()
    outcome = rig.core.outcome
    assert outcome is not None and outcome.code == oc.BUFFER_UNDERFLOW and outcome.node == 1
    assert outcome.detail["predicted"] is True and "too soon to resend" in outcome.message
    assert rig.drives is not None and all(d.errors == 0 for d in rig.drives.values())


def test_congested_bus_waits_instead_of_resending_and_fails_bus_overload() -> None:
    plan = make_plan(2, 3000, seed=28)
    rig = running_rig(plan)
    rig.inject = record_dropper(1, set(range(10_000)))  # node 1's records stop arriving
    for _ in range(100):
        if rig.core.state in TERMINAL:
            break
        rig.feed(BusLoad(0.95, rig.t))
        rig.sync()
    outcome = rig.core.outcome
    assert outcome is not None and outcome.code == oc.BUS_OVERLOAD and outcome.node == 1
    assert rig.core.telemetry()[0].resends == 0
    assert rig.core.report().measured_bus_load_peak == pytest.approx(0.95)


def test_a_stale_answer_from_before_the_job_does_not_fail_the_start_checks() -> None:
    """A drive that answers late (within its stated latency or past it) can have its answer to a SYNC before
    the job arrive after the job's first SYNC, showing the FIFO as it was before the buffer clear. A start
    check that fails waits for an answer heard a TPDO timeout after the first SYNC (the stale one failed the
    late-answers recording test DRIVE_NOT_READY, "FIFO holds 1 records"); a check still failing then fails."""
    plan = make_plan(1, 1000, seed=16)
    node = plan.node_ids[0]
    settings = StreamerSettings(counts_per_rev={node: CPR})
    timeout = settings.tpdo_timeout_syncs

    def answer(core: Coordinator, m: int, fill: int) -> None:
        start = core._by_node[node].start_position
        core.handle(BufferStatus(node, 0x0037, 0, settings.fifo_size - fill, 0.01 * m + 0.009, sync_count=m))
        core.handle(PositionFeedback(node, start, start, 0.01 * m + 0.009, sync_count=m))

    for fresh_fill, failed in ((0, False), (1, True)):
        core = Coordinator(plan, settings)
        core.handle(Sync(0, 0.0))
        answer(core, 0, 1)  # the answer to the SYNC before the job, late: one record before the clear
        assert core.state is JobState.CONFIGURING
        for m in range(1, timeout + 1):
            core.handle(Sync(m, 0.01 * m))
            answer(core, m, fresh_fill)
        if failed:
            assert core.outcome is not None and core.outcome.code == oc.DRIVE_NOT_READY
            assert "FIFO holds 1 records" in core.outcome.message
        else:
            assert core.outcome is None and core.state is not JobState.CONFIGURING
