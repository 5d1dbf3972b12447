"""The pure EposDrive in virtual time: every behaviour of issue 3 section 3, deterministic.

The same behaviours are driven in real time by the stock canopen RemoteNode in
test_sim_faithfulness.py; here each timing branch is exact (time is an argument).
"""

from __future__ import annotations

import itertools

import pytest
from bus_testkit import CPR, VDrive, make_axis, make_cell, ramp_records

from bus import cob, codec
from bus.codec import Cia402State as S
from bus.codec import NmtState
from bus.sim import od as odm
from bus.sim.epos import EposDrive
from bus.sim.od import SdoAbort
from bus.sim.virtual import VirtualCell
from planner.config import DriveSettings


def emcy_codes(d: VDrive) -> list[int]:
    return [e.code for e in d.emcys()]


# ---- NMT, heartbeat, boot ----------------------------------------------------------------------------
def test_boot_sends_bootup_and_enters_pre_operational() -> None:
    m = EposDrive(5, make_axis(5))
    assert m.on_sync(0.0) == []  # not powered: deaf
    frames = m.power_on(0.0)
    assert frames == [codec.Frame(0x705, b"\x00")]
    assert m.nmt_state == NmtState.PRE_OPERATIONAL
    assert m.state == S.SWITCH_ON_DISABLED
    assert m.statusword & 0x6F == 0x40


def test_heartbeat_producer_follows_0x1017_and_nmt_state() -> None:
    d = VDrive(configure=False)
    d.sdo(0x1017, 0, 100)
    assert d.model.next_deadline() == pytest.approx(0.1)
    assert d.model.advance(0.05) == []
    assert d.model.advance(0.1) == [codec.Frame(0x701, b"\x7f")]
    d.t = 0.1
    d.frame(0, bytes((codec.NmtCommand.START, 1)))
    assert d.model.advance(0.2001) == [codec.Frame(0x701, b"\x05")]
    d.frame(0, bytes((codec.NmtCommand.STOP, 0)))  # broadcast
    assert d.model.advance(0.3001) == [codec.Frame(0x701, b"\x04")]
    d.sdo(0x1017, 0, 0)
    assert d.model.advance(10.0) == []


def test_pdos_only_in_operational_and_nmt_addressing() -> None:
    d = VDrive(configure=False)
    for w in d.model.profile.configuration(d.axis, DriveSettings(), 10):
        d.sdo(w.index, w.sub, w.value)
    assert all(f.cob_id != cob.tpdo1_id(1) for f in d.sync())  # pre-operational: no TPDO
    d.frame(0, bytes((codec.NmtCommand.START, 2)))  # another node
    assert d.model.nmt_state == NmtState.PRE_OPERATIONAL
    d.frame(0, bytes((codec.NmtCommand.START, 1)))
    ids = [f.cob_id for f in d.sync()]
    assert ids == [cob.tpdo1_id(1), cob.tpdo2_id(1)]  # TPDO1 then TPDO2


def test_inhibit_time_spaces_a_changing_event_tpdo_exactly() -> None:
    """CiA 301 0x18xx:03 in the model's own time: never two within the inhibit time, and a change made
    inside it goes out when it ends (test_sim_cia301.py drives the same through canopen in real time)."""
    d = VDrive(configure=False)
    tpdo3 = 0x380 + d.node
    for index, sub, value in [(0x1802, 1, 0x8000_0000 | tpdo3), (0x1802, 2, 255), (0x1802, 3, 1000),
                              (0x1802, 5, 0), (0x1A02, 0, 0), (0x1A02, 1, 0x6041_0010), (0x1A02, 0, 1),
                              (0x1802, 1, tpdo3)]:  # statusword, event driven, 100 ms inhibit, no timer
        d.sdo(index, sub, value)
    d.frame(0, bytes((codec.NmtCommand.START, d.node)))
    sent: list[tuple[float, bytes]] = []
    flip = False
    for ms in range(1, 800):
        d.t = ms / 1000.0
        out = d.model.advance(d.t)
        if ms % 10 == 0 and ms <= 600:  # shutdown / disable voltage back and forth every 10 ms
            out += d.sdo(0x6040, 0, 0x0006 if flip else 0x0000)
            flip = not flip
        sent += [(d.t, f.data) for f in out if f.cob_id == tpdo3]
    times = [t for t, _ in sent]
    gaps = [b - a for a, b in itertools.pairwise(times)]
    assert len(times) >= 6 and min(gaps) >= 0.1 - 1e-9, times
    assert all(g <= 0.1 + 1e-9 for g in gaps[1:]), gaps  # every later change waited exactly its end
    assert sent[-1][1] == d.model.statusword.to_bytes(2, "little")  # the last change went out


def test_reset_node_restores_defaults_and_boots_again() -> None:
    d = VDrive()
    d.sdo(0x20C4, 2, 7)
    out = d.frame(0, bytes((codec.NmtCommand.RESET_NODE, 1)))
    assert codec.Frame(0x701, b"\x00") in out
    assert d.model.sdo_read(0x20C4, 2) == 4
    assert d.model.sdo_read(0x1A00, 1) == 0x60410010  # factory TPDO1 mapping again
    assert d.model.nmt_state == NmtState.PRE_OPERATIONAL


# ---- CiA 402 --------------------------------------------------------------------------------------------
def test_power_state_machine_via_sdo() -> None:
    d = VDrive()
    m = d.model
    d.sdo(0x6040, 0, 0x000F)  # no transition from switch on disabled: ignored
    assert m.state == S.SWITCH_ON_DISABLED and m.counters.ignored_commands == 1
    d.sdo(0x6040, 0, 0x0006)
    assert m.state == S.READY_TO_SWITCH_ON and m.statusword & 0x6F == 0x21
    d.sdo(0x6040, 0, 0x0007)
    assert m.state == S.SWITCHED_ON and m.statusword & 0x6F == 0x23
    d.sdo(0x6040, 0, 0x000F)
    assert m.state == S.OPERATION_ENABLED and m.statusword & 0x6F == 0x27
    assert m.statusword & codec.SW_VOLTAGE_ENABLED
    d.sdo(0x6040, 0, 0x0007)  # disable operation
    assert m.state == S.SWITCHED_ON
    d.sdo(0x6040, 0, 0x0000)  # disable voltage
    assert m.state == S.SWITCH_ON_DISABLED


def test_controlword_in_synchronous_rpdo_applies_at_next_sync() -> None:
    d = VDrive()
    d.cw(0x0006)
    assert d.model.state == S.SWITCH_ON_DISABLED
    frames = d.sync()
    assert d.model.state == S.READY_TO_SWITCH_ON
    sw = codec.decode_tpdo1(next(f.data for f in frames if f.cob_id == cob.tpdo1_id(1))).statusword
    assert codec.state_from_statusword(sw) == S.READY_TO_SWITCH_ON  # TPDO after the controlword


def test_quick_stop_ramps_down_then_switch_on_disabled() -> None:
    d = VDrive()
    d.enable()
    pending = d.start(ramp_records(60_000, cruise_rpm=1200), prime=10)
    d.run(pending, until=lambda m: m.velocity_actual_rpm > 500)
    d.sdo(0x6040, 0, 0x000B)  # quick stop (seed 000 6.3: 0x000B)
    assert d.model.state == S.QUICK_STOP_ACTIVE and not d.model.ip_active
    assert d.model.statusword & 0x6F == 0x07
    d.sync(30)
    assert d.model.state == S.SWITCH_ON_DISABLED  # option code 2 (default): ramp, then disabled
    assert emcy_codes(d) == []


def test_quick_stop_option_6_stays_in_quick_stop_and_can_resume() -> None:
    d = VDrive()
    d.sdo(0x605A, 0, 6)
    d.enable()
    d.sdo(0x6040, 0, 0x000B)
    d.sync(2)
    assert d.model.state == S.QUICK_STOP_ACTIVE and d.model.statusword & codec.SW_TARGET_REACHED
    d.sdo(0x6040, 0, 0x000F)  # transition 16
    assert d.model.state == S.OPERATION_ENABLED
    with pytest.raises(SdoAbort) as e:
        d.sdo(0x605A, 0, 3)
    assert e.value.code == odm.ABORT_INVALID_VALUE


# ---- modes --------------------------------------------------------------------------------------------
def test_modes_of_operation_and_mode_selection_clears_the_buffer() -> None:
    d = VDrive(configure=False)
    assert d.model.sdo_read(0x6061, 0) == 0
    with pytest.raises(SdoAbort) as e:
        d.sdo(0x6060, 0, 1)  # profile position: not supported by this drive
    assert e.value.code == odm.ABORT_INVALID_VALUE
    d.sdo(0x60C4, 6, 1)
    d.sdo(0x20C1, 0, 0x0A00000000000010)
    assert d.model.fifo_fill == 1
    d.sdo(0x6060, 0, 7)  # table 4-26 transition I: ip mode selected -> clear the buffer
    assert d.model.fifo_fill == 0 and d.model.sdo_read(0x6061, 0) == 7
    assert d.model.sdo_read(0x6502, 0) & 0x40


# ---- IPM: nominal sequence, FIFO, end record -------------------------------------------------------------
def test_nominal_ipm_sequence_ends_on_time_zero_record_without_error() -> None:
    d = VDrive()
    d.enable()
    records = ramp_records(20_000)
    pending = d.start(records, prime=4)
    assert d.model.ip_active and d.model.statusword & codec.SW_IP_ACTIVE
    d.run(pending, keep=6)
    m = d.model
    assert not m.ip_active and m.state == S.OPERATION_ENABLED
    assert m.position_demand == 20_000 and m.fifo_fill == 0
    assert emcy_codes(d) == [] and m.counters.faults == 0
    d.sync(40)
    assert abs(m.position_actual - 20_000) <= 20
    assert m.statusword & codec.SW_TARGET_REACHED
    assert m.counters.segments_completed == len(records) - 1
    assert m.counters.underflow_warnings >= 1  # the tail of every trajectory runs below the watermark


def test_free_size_and_buffer_position_report_the_fill() -> None:
    d = VDrive()
    d.enable()
    for k in range(5):
        d.record(100 * k, 0, 10)
    assert d.model.sdo_read(0x60C4, 2) == 59 and d.model.sdo_read(0x60C4, 4) == 5
    d.sdo(0x60C4, 4, 0)  # "writing to this object has no effect"
    assert d.model.sdo_read(0x60C4, 4) == 5
    tp = d.tpdo1()
    d.sync()
    assert d.tpdo1()[len(tp)].free_size == 59
    bs = codec.decode_buffer_status(d.model.buffer_status)
    assert bs.buffer_enabled and not bs.underflow_warning and not bs.ip_active


def test_watermark_warnings_follow_0x20c4_levels() -> None:
    d = VDrive()
    d.enable()
    d.sdo(0x20C4, 2, 3)
    d.sdo(0x20C4, 3, 5)
    assert d.model.buffer_status & codec.BS_UNDERFLOW_WARNING  # fill 0 < 3
    for k in range(3):
        d.record(k, 0, 10)
    assert not d.model.buffer_status & (codec.BS_UNDERFLOW_WARNING | codec.BS_OVERFLOW_WARNING)
    for k in range(3):
        d.record(k, 0, 10)
    assert d.model.buffer_status & codec.BS_OVERFLOW_WARNING  # fill 6 > 5
    d.sync()
    assert d.model.counters.overflow_warnings == 1


def test_activation_with_fewer_than_two_records_is_an_underflow_error() -> None:
    d = VDrive()
    d.enable()
    d.record(100, 0, 10)
    d.cw(0x001F)
    d.sync()
    assert d.model.state == S.FAULT
    (e,) = d.emcys()
    assert e.code == codec.EMCY_IP_BUFFER and e.buffer_status & codec.BS_UNDERFLOW_ERROR


def test_underflow_during_motion_emcy_fault_and_fault_reset() -> None:
    d = VDrive()
    d.enable()
    records = ramp_records(40_000, cruise_rpm=900)
    d.start(records[:6])  # the rest never comes
    for _ in range(20):
        d.sync()
        if d.model.state != S.OPERATION_ENABLED:
            break
    m = d.model
    assert m.state in (S.FAULT_REACTION_ACTIVE, S.FAULT)
    (e,) = d.emcys()
    assert e.code == 0x8782 and e.buffer_status & codec.BS_UNDERFLOW_ERROR and not e.buffer_status & 0x0200
    assert e.register & codec.ER_GENERIC
    assert m.error_code == 0x8782 and m.sdo_read(0x603F, 0) == 0x8782
    assert m.buffer_status & codec.BS_UNDERFLOW_ERROR and not m.ip_active
    d.sync(30)  # fault reaction: quick-stop ramp, then Fault with the power stage off
    assert m.state == S.FAULT and m.statusword & codec.SW_FAULT
    assert m.fault_log[0].code == 0x8782
    d.cw(0x000F)  # nothing but a fault reset leaves Fault
    d.sync()
    assert m.state == S.FAULT
    d.cw(0x0080)
    d.sync()
    assert m.state == S.SWITCH_ON_DISABLED
    assert d.emcys()[-1].code == codec.EMCY_ERROR_RESET and d.emcys()[-1].is_error_reset
    assert m.buffer_status & codec.BS_ERRORS == 0 and m.error_code == 0
    d.cw(0x0080)  # held high: no second edge
    d.sync()
    assert len(d.emcys()) == 2


def test_overflow_error_when_a_record_arrives_at_a_full_fifo() -> None:
    d = VDrive()
    d.enable()
    for k in range(64):
        d.record(k, 0, 10)
    assert d.model.free_size == 0 and emcy_codes(d) == []
    d.record(64, 0, 10)
    (e,) = d.emcys()
    assert e.code == 0x8782 and e.buffer_status & codec.BS_OVERFLOW_ERROR
    assert d.model.fifo_fill == 64 and d.model.state == S.FAULT
    assert d.model.counters.records_rejected == 1


def test_records_are_refused_while_the_buffer_is_disabled() -> None:
    d = VDrive()
    d.record(1, 0, 10)  # over PDO: dropped
    assert d.model.fifo_fill == 0 and d.model.counters.records_rejected == 1
    with pytest.raises(SdoAbort) as e:
        d.sdo(0x20C1, 0, 1)
    assert e.value.code == odm.ABORT_DEVICE_STATE


def test_controlword_bit4_falling_edge_stops_interpolation_and_keeps_the_fifo() -> None:
    d = VDrive()
    d.enable()
    pending = d.start(ramp_records(20_000), prime=8)
    d.sync(3)
    demand = d.model.position_demand
    d.cw(0x000F)
    d.sync()
    held = d.model.position_demand
    assert not d.model.ip_active and d.model.fifo_fill > 0 and held >= demand
    d.sync(3)
    assert d.model.position_demand == held
    assert pending and emcy_codes(d) == []


def test_synchronous_start_moves_exactly_one_period_by_the_next_sync() -> None:
    d = VDrive(sync_period_ms=4)
    d.enable()
    records = ramp_records(2_000, cruise_rpm=100, seg_ms=4)
    for r in records[:5]:
        d.record(*r)
    d.cw(0x001F)
    frames = d.sync()
    t1 = codec.decode_tpdo1(next(f.data for f in frames if f.cob_id == cob.tpdo1_id(1)))
    t2 = codec.decode_tpdo2(next(f.data for f in frames if f.cob_id == cob.tpdo2_id(1)))
    assert t1.buffer_status & codec.BS_IP_ACTIVE and t1.statusword & codec.SW_IP_ACTIVE
    assert t2.position_demand == 0  # activated at this SYNC: not moved yet
    ticks = d.model.counters.ticks
    d.sync()
    assert d.model.counters.ticks - ticks == 4
    assert d.model.position_demand == records[0][0]  # one 4 ms segment done in one 4 ms period


# ---- limits ------------------------------------------------------------------------------------------------
def test_velocity_warning_and_velocity_error_abort() -> None:
    d = VDrive()
    d.enable()
    d.sdo(0x6081, 0, 300)  # profile velocity: warning only
    pending = d.start(ramp_records(20_000, cruise_rpm=600), prime=6)
    d.run(pending)
    assert d.model.buffer_status & codec.BS_VELOCITY_WARNING and d.model.counters.velocity_warnings >= 1
    assert emcy_codes(d) == []
    d.sdo(0x607F, 0, 400)  # max profile velocity: trajectory abort
    pending = d.start(ramp_records(20_000, cruise_rpm=600, start=20_000), prime=6)
    assert not d.model.buffer_status & codec.BS_VELOCITY_WARNING  # cleared on activation
    d.run(pending, max_syncs=200, until=lambda m: m.state == S.FAULT)
    (e,) = d.emcys()
    assert e.code == codec.EMCY_IP_VELOCITY and e.buffer_status & codec.BS_VELOCITY_ERROR
    assert d.model.state == S.FAULT


def test_acceleration_warning_and_error() -> None:
    d = VDrive()
    d.enable()
    d.sdo(0x6083, 0, 2000)
    pending = d.start(ramp_records(20_000, cruise_rpm=600), prime=6)
    d.run(pending)
    assert d.model.buffer_status & codec.BS_ACCELERATION_WARNING and emcy_codes(d) == []
    d.sdo(0x60C5, 0, 2000)
    d.start(ramp_records(20_000, cruise_rpm=600, start=20_000), prime=8)
    d.sync(10)
    (e,) = d.emcys()
    assert e.code == codec.EMCY_IP_ACCELERATION and e.buffer_status & codec.BS_ACCELERATION_ERROR


def test_halt_decelerates_with_profile_deceleration_and_reports_target_reached() -> None:
    d = VDrive()
    d.enable()
    d.sdo(0x6084, 0, 6000)  # rpm/s
    pending = d.start(ramp_records(100_000, cruise_rpm=1200), prime=10)
    d.run(pending, until=lambda m: m.demand_velocity_rpm > 1000)
    d.cw(0x011F)
    d.sync()
    m = d.model
    v0 = m.demand_velocity_rpm  # the ramp starts after this SYNC's ticks, from this velocity
    assert v0 > 1000
    assert not m.ip_active and not m.statusword & codec.SW_TARGET_REACHED
    syncs = 0
    while not m.statusword & codec.SW_TARGET_REACHED:
        d.sync()
        syncs += 1
        assert syncs < 100
    # v0 / (6000 rpm/s), counted in 10 ms SYNCs
    assert syncs == pytest.approx(v0 / 6000 * 100, abs=1.0)
    assert m.state == S.OPERATION_ENABLED and emcy_codes(d) == [] and m.fifo_fill > 0
    p = m.position_demand
    d.sync(5)
    assert m.position_demand == p


# ---- following error and motor model -----------------------------------------------------------------------
def test_actual_position_lags_the_demand_realistically() -> None:
    d = VDrive()
    d.enable()
    pending = d.start(ramp_records(50_000, cruise_rpm=1200), prime=6)
    lags = []
    for _ in range(200):
        while pending and d.model.fifo_fill < 6:
            d.record(*pending.pop(0))
        d.sync()
        lags.append(abs(d.model.following_error))
        if not d.model.ip_active:
            break
    assert 5 < max(lags) < 2000  # a real loop lags; a broken one diverges
    d.sync(50)
    assert abs(d.model.position_actual - 50_000) <= 20
    assert abs(d.model.velocity_actual_rpm) < 5


def test_following_error_window_faults_with_8611() -> None:
    d = VDrive()
    d.enable()
    d.sdo(0x6065, 0, 50)
    pending = d.start(ramp_records(50_000, cruise_rpm=1200), prime=6)
    d.run(pending, max_syncs=100, until=lambda m: m.state == S.FAULT)
    (e,) = d.emcys()
    assert e.code == codec.EMCY_FOLLOWING_ERROR and e.register & codec.ER_DEVICE_PROFILE
    assert d.model.state == S.FAULT


def test_blocked_axis_trips_the_following_error() -> None:
    d = VDrive()
    d.enable()
    d.model.disturbance_current_a = 50.0  # far above the current limit: the motor cannot follow
    pending = d.start(ramp_records(50_000, cruise_rpm=1200), prime=6)
    d.run(pending, max_syncs=100, until=lambda m: m.state == S.FAULT)
    assert emcy_codes(d) == [codec.EMCY_FOLLOWING_ERROR]


# ---- PDO length, SYNC, heartbeat consumer ------------------------------------------------------------------
@pytest.mark.parametrize(("data", "code"), [(b"\x01\x02\x03", 0x8210), (b"\x0f\x00\x00", 0x8220)])
def test_rpdo_of_the_wrong_length(data: bytes, code: int) -> None:
    d = VDrive()
    d.enable()
    cob_id = cob.rpdo2_id(1) if code == 0x8210 else cob.rpdo1_id(1)
    d.frame(cob_id, data)
    assert emcy_codes(d) == [code]
    assert d.model.counters.pdo_length_errors == 1 and d.model.state == S.FAULT


def test_late_sync_while_ip_active_is_a_sync_error() -> None:
    d = VDrive()
    d.enable()
    pending = d.start(ramp_records(20_000), prime=8)
    d.sync(2)
    d.sync(dt_s=0.014)  # 1.4 periods: fine
    assert emcy_codes(d) == []
    d.model.on_sync(d.t + 0.016)  # 1.6 periods after the previous SYNC
    d.frames += d.model.on_sync(d.t + 0.026)
    assert d.model.counters.sync_gaps == 1
    assert pending


def test_missing_sync_is_detected_by_the_timer() -> None:
    d = VDrive()
    d.enable()
    d.start(ramp_records(20_000), prime=8)
    d.sdo(0x1017, 0, 0)
    deadline = d.model.next_deadline()
    assert deadline == pytest.approx(d.t + 0.015)
    assert d.model.advance(d.t + 0.0149) == []
    frames = d.model.advance(d.t + 0.0151)
    assert [codec.decode_emcy(f.data).code for f in frames] == [codec.EMCY_SYNC_LOST]
    assert d.model.state in (S.FAULT_REACTION_ACTIVE, S.FAULT)


def test_no_sync_monitoring_while_ip_inactive() -> None:
    d = VDrive()
    d.enable()
    assert all(f.cob_id != cob.emcy_id(1) for f in d.model.advance(d.t + 10.0))
    d.sync(dt_s=1.0)
    assert d.model.counters.sync_gaps == 0


def test_heartbeat_consumer_timeout_faults_with_8130() -> None:
    d = VDrive()
    d.enable()
    d.sdo(0x1017, 0, 0)  # no heartbeat production in the way
    d.sdo(0x1016, 1, (0x7F << 16) | 50)  # watch node 127, 50 ms
    assert d.model.next_deadline() is None  # armed by the first heartbeat
    d.frame(0x77F, b"\x05")
    d.sync()
    d.frame(0x77F, b"\x05")
    assert d.model.next_deadline() == pytest.approx(d.t + 0.05)
    assert d.model.advance(d.t + 0.04) == []
    frames = d.model.advance(d.t + 0.06)
    assert [codec.decode_emcy(f.data).code for f in frames] == [codec.EMCY_HEARTBEAT]


def test_drive_clock_without_configured_period_uses_the_measured_interval() -> None:
    d = VDrive(configure=False)
    d.sync(dt_s=0.007)  # first SYNC: no reference yet
    assert d.model.counters.ticks == 0
    d.sync(dt_s=0.0025)
    d.sync(dt_s=0.0025)
    assert d.model.counters.ticks == 5


# ---- SDO server semantics ---------------------------------------------------------------------------------
def test_sdo_access_and_range_checks() -> None:
    m = VDrive(configure=False).model
    cases = [
        (lambda: m.sdo_write(0x6041, 0, 1), odm.ABORT_READ_ONLY),
        (lambda: m.sdo_read(0x20C1, 0), odm.ABORT_WRITE_ONLY),
        (lambda: m.sdo_read(0x60C4, 6), odm.ABORT_WRITE_ONLY),
        (lambda: m.sdo_read(0x2345, 0), odm.ABORT_NO_OBJECT),
        (lambda: m.sdo_read(0x60C4, 9), odm.ABORT_NO_SUBINDEX),
        (lambda: m.sdo_write(0x20C4, 2, 64), odm.ABORT_VALUE_TOO_HIGH),
        (lambda: m.sdo_write(0x20C4, 3, 0), odm.ABORT_VALUE_TOO_LOW),
        (lambda: m.sdo_write(0x60C0, 0, 0), odm.ABORT_VALUE_TOO_HIGH),
        (lambda: m.sdo_write(0x60C4, 5, 9), odm.ABORT_VALUE_TOO_HIGH),
        (lambda: m.sdo_write(0x6040, 0, 0x10000), odm.ABORT_VALUE_TOO_HIGH),
    ]
    for call, code in cases:
        with pytest.raises(SdoAbort) as e:
            call()
        assert e.value.code == code
    assert m.sdo_read(0x60C4, 1) == 64 and m.sdo_read(0x60C0, 0) == -1
    assert m.sdo_read(0x60C2, 1) == 1 and m.sdo_read(0x60C2, 2) == -3


def test_pdo_mapping_rules() -> None:
    m = VDrive(configure=False).model
    with pytest.raises(SdoAbort) as e:
        m.sdo_write(0x1A00, 0, 0)  # TPDO1 valid: mapping locked
    assert e.value.code == odm.ABORT_PARAMETER_INCOMPATIBLE
    m.sdo_write(0x1800, 1, 0x80000181)
    m.sdo_write(0x1A00, 0, 0)
    with pytest.raises(SdoAbort) as e:
        m.sdo_write(0x1A00, 1, 0x10000020)  # device type is not mappable
    assert e.value.code == odm.ABORT_CANNOT_MAP
    with pytest.raises(SdoAbort) as e:
        m.sdo_write(0x1A00, 1, 0x20C10040)  # write-only record in a TPDO
    assert e.value.code == odm.ABORT_CANNOT_MAP
    for k, word in enumerate((0x60640020, 0x60620020, 0x60410010), start=1):
        m.sdo_write(0x1A00, k, word)
    with pytest.raises(SdoAbort) as e:
        m.sdo_write(0x1A00, 0, 3)  # 80 bits
    assert e.value.code == odm.ABORT_PDO_LENGTH
    with pytest.raises(SdoAbort) as e:
        m.sdo_write(0x1800, 2, 253)  # RTR-only transmission is not supported
    assert e.value.code == odm.ABORT_INVALID_VALUE
    m.sdo_write(0x1800, 1, 0x181)
    with pytest.raises(SdoAbort) as e:
        m.sdo_write(0x1800, 1, 0x1C1)  # another COB-ID while valid
    assert e.value.code == odm.ABORT_INVALID_VALUE


def test_configuration_reads_back() -> None:
    d = VDrive()
    for w in d.model.profile.configuration(d.axis, DriveSettings(), 10):
        if w.verify:
            assert d.model.sdo_read(w.index, w.sub) == w.value, w
    assert d.model.rx_cob_ids() == {0, 0x80, cob.rpdo1_id(1), cob.rpdo2_id(1)}
    assert d.model.sdo_read(0x1006, 0) == 10_000
    assert d.model.sdo_read(0x607F, 0) == 3000
    assert d.model.sdo_read(0x6081, 0) == 1200
    assert d.model.sdo_read(0x60C5, 0) == 400 * 60  # 400 rev/s^2 = 24000 rpm/s
    assert d.model.counts_per_rev == CPR


def test_virtual_cell_routes_frames_and_enables_like_the_master() -> None:
    vc = VirtualCell(make_cell(3))
    assert [f.cob_id for f in vc.boot_frames if f.data == b"\x00"] == [0x701, 0x702, 0x703]
    vc.enable_drives(0.0)
    assert all(m.state == S.OPERATION_ENABLED and m.buffer_enabled for m in vc.models.values())
    vc.deliver(cob.rpdo2_id(2), bytes(8), 0.0)
    assert [m.fifo_fill for m in vc.models.values()] == [0, 1, 0]
    frames = vc.sync(0.01)
    assert [f.cob_id for f in frames] == [0x181, 0x281, 0x182, 0x282, 0x183, 0x283]
    vc.sdo_write(3, 0x1801, 1, 0x80000283)  # TPDO2 of node 3 off
    assert len(vc.sync(0.02)) == 5
    vc.models[1].sdo_write(0x1400, 1, 0x80000201)
    vc.deliver(cob.rpdo1_id(1), b"\x06\x00", 0.02)  # RPDO1 of node 1 disabled: not routed
    assert vc.models[1].state == S.OPERATION_ENABLED
    # heartbeats configured like the master: one drive after another (2 ms apart, the last at t0), 100 ms
    # + node id mod 11, so they do not land in one SYNC cycle
    assert vc.next_deadline() == pytest.approx(-0.004 + 0.101)
    assert [f.cob_id for f in vc.advance(0.0975)] == [0x701]
    assert [f.cob_id for f in vc.advance(0.1035)] == [0x702, 0x703]
