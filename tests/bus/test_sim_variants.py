"""The simulated drive's readings of the points the manuals leave open (issue 11 section 1), one test
per variant, in virtual time: each option changes exactly the behaviour docs/drive-model.md says."""

from __future__ import annotations

import pytest
from bus_testkit import CPR, VDrive, make_axis

from bus import cob, codec
from bus.codec import Cia402State as S
from bus.profile import FeedbackSchedule
from bus.sim import od as odm
from bus.sim.od import SdoAbort
from planner.errors import PlanningError
from planner.readings import DriveReadings, SimDriveOptions


def drive(**options: object) -> VDrive:
    d = VDrive(options=SimDriveOptions(**options))  # type: ignore[arg-type]
    d.enable()
    return d


def tpdo1_after(d: VDrive, before: int) -> list[codec.Tpdo1]:
    return [codec.decode_tpdo1(f.data) for f in d.frames[before:] if f.cob_id == cob.tpdo1_id(d.node)]


DWELL = [(0, 0, 25), (0, 0, 25), (0, 0, 0)]  # zero motion, 50 ms


# ---- 1. TPDO sampling -----------------------------------------------------------------------------------
@pytest.mark.parametrize(("sampling", "active_at_start"), [("after_rpdo", True), ("before_rpdo", False)])
def test_tpdo_of_the_enabling_sync(sampling: str, active_at_start: bool) -> None:
    d = drive(tpdo_sampling=sampling)
    for r in DWELL:
        d.record(*r)
    d.cw(0x001F)
    n = len(d.frames)
    d.sync()  # the enabling SYNC: the controlword applies here
    (t1,) = tpdo1_after(d, n)
    assert bool(t1.buffer_status & codec.BS_IP_ACTIVE) is active_at_start
    assert d.model.ip_active  # the drive itself is active either way
    n = len(d.frames)
    d.sync()
    assert tpdo1_after(d, n)[0].buffer_status & codec.BS_IP_ACTIVE


# ---- 2. FIFO accounting ------------------------------------------------------------------------------------
@pytest.mark.parametrize(("count", "during_first"), [("until_segment_end", 3), ("until_segment_start", 2)])
def test_fifo_count_of_the_record_being_interpolated_towards(count: str, during_first: int) -> None:
    d = drive(fifo_count=count)
    for r in DWELL:
        d.record(*r)
    assert d.model.fifo_fill == 3
    d.cw(0x001F)
    d.sync()
    assert d.model.fifo_fill == during_first
    assert d.model.sdo_read(0x60C4, 2) == 64 - during_first
    d.sync(3)  # 30 ms: the first segment (25 ms) ended, the second runs
    assert d.model.fifo_fill == during_first - 1
    d.sync(3)
    assert not d.model.ip_active and d.model.fifo_fill == 0 and not d.emcys()


# ---- 3. the first record after enabling -------------------------------------------------------------------------
def test_first_record_ends_a_segment_or_is_the_point_at_time_zero() -> None:
    moves = [(0, 0, 20), (100, 0, 20), (100, 0, 0)]
    a = drive(first_record="segment_end")
    b = drive(first_record="time_zero")
    for d in (a, b):
        for r in moves:
            d.record(*r)
        d.cw(0x001F)
        d.sync()
        d.sync()  # 10 ms in
    assert a.model.position_demand == 0  # dwelling on the first record's 20 ms segment
    assert b.model.position_demand == 50  # halfway from the origin record to the second
    b.sync()
    assert b.model.position_demand == 100
    a.sync(3)
    assert a.model.position_demand == 100
    assert not b.model.ip_active and not a.model.ip_active
    assert a.model.counters.segments_completed == 2 and b.model.counters.segments_completed == 1


# ---- 4. rounding ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize(("rounding", "expected"), [("nearest", 1), ("toward_zero", 0)])
def test_demand_rounding(rounding: str, expected: int) -> None:
    d = drive(rounding=rounding)
    for r in [(1, 0, 15), (1, 0, 20), (1, 0, 0)]:
        d.record(*r)
    d.cw(0x001F)
    d.sync()
    d.sync()  # tick 10 of 15: smoothstep 0.741 of one count
    assert d.model.position_demand == expected
    neg = drive(rounding=rounding)
    neg.model._demand = -5
    for r in [(-6, 0, 15), (-6, 0, 20), (-6, 0, 0)]:
        neg.record(*r)
    neg.cw(0x001F)
    neg.sync(2)
    assert neg.model.position_demand == (-6 if rounding == "nearest" else -5)


# ---- 5. optional objects absent ------------------------------------------------------------------------------------
def test_absent_objects_abort_and_configuration_goes_on() -> None:
    d = VDrive(options=SimDriveOptions(absent=("0x1006", "0x6085", "0x60C2", "0x6081", "0x6083")))
    for index in (0x1006, 0x6085, 0x60C2, 0x6081, 0x6083):
        with pytest.raises(SdoAbort) as e:
            d.model.sdo_read(index, 1 if index == 0x60C2 else 0)
        assert e.value.code == odm.ABORT_NO_OBJECT
        assert not d.model.has_object(index)
    assert d.model.sdo_read(0x6084, 0) > 0  # configured (essential)
    d.enable()
    # quick stop ramps with the profile deceleration 0x6084 instead of the missing 0x6085
    assert d.model._qs_dec_key == (0x6084, 0)
    with pytest.raises(SdoAbort) as e:
        d.sdo(0x1A01, 1, (0x6081 << 16) | 32)  # an absent object cannot be mapped either
    assert e.value.code in (odm.ABORT_CANNOT_MAP, odm.ABORT_PARAMETER_INCOMPATIBLE)


def test_essential_object_missing_fails_configuration() -> None:
    with pytest.raises(PlanningError):
        SimDriveOptions(absent=("0x20C1",))  # not optional: a drive without it is not an IPM drive


# ---- 6. queue underflow check ------------------------------------------------------------------------------------
@pytest.mark.parametrize(("check", "fault_after_ms"), [("segment_end", 40), ("every_tick", 20)])
def test_underflow_checked_at_segment_end_or_every_tick(check: str, fault_after_ms: int) -> None:
    d = drive(underflow_check=check)
    for r in [(0, 0, 20), (0, 0, 20)]:  # no end record: the FIFO runs dry
        d.record(*r)
    d.cw(0x001F)
    d.sync()
    ms = 0
    for ms in range(10, 60, 10):  # noqa: B007 - the loop variable is the answer
        d.sync()
        if d.emcys():
            break
    assert ms == fault_after_ms
    (e,) = d.emcys()
    assert e.code == codec.EMCY_IP_BUFFER and e.buffer_status & codec.BS_UNDERFLOW_ERROR


def test_every_tick_with_start_counting_needs_two_records_behind_the_target() -> None:
    d = drive(underflow_check="every_tick", fifo_count="until_segment_start")
    for r in [(0, 0, 20), (0, 0, 0)]:
        d.record(*r)
    d.cw(0x001F)
    d.sync()
    assert d.emcys() and d.model.state in (S.FAULT_REACTION_ACTIVE, S.FAULT)
    ok = drive(underflow_check="every_tick", fifo_count="until_segment_start")
    for r in [(0, 0, 20), (0, 0, 0), (0, 0, 0)]:  # a second end record keeps two behind the target
        ok.record(*r)
    ok.cw(0x001F)
    ok.sync(4)
    assert not ok.emcys() and not ok.model.ip_active and ok.model.fifo_fill == 1


# ---- 7. the drive's clock ---------------------------------------------------------------------------------------
def long_move(d: VDrive, ms: int) -> None:
    for r in [(0, 0, 5), (0, 0, 255)] + [(0, 0, 250)] * (ms // 250) + [(0, 0, 0)]:
        d.record(*r)


@pytest.mark.parametrize("ppm", [1000.0, -1000.0])
def test_own_clock_drifts_against_sync(ppm: float) -> None:
    d = drive(clock="own", clock_drift_ppm=ppm)
    long_move(d, 1000)
    d.cw(0x001F)
    d.sync()
    ticks0 = d.model.counters.ticks
    d.sync(100)  # 1 s of SYNC
    assert d.model.counters.ticks - ticks0 == (1001 if ppm > 0 else 999)
    locked = drive()
    long_move(locked, 1000)
    locked.cw(0x001F)
    locked.sync()
    t0 = locked.model.counters.ticks
    locked.sync(100)
    assert locked.model.counters.ticks - t0 == 1000


def test_time_stamps_correct_the_own_clock() -> None:
    d = VDrive(options=SimDriveOptions(clock="own", clock_drift_ppm=200.0))
    d.sdo(0x1012, 0, 0x80000100)  # consume time stamps
    d.enable()
    long_move(d, 20_000)
    d.cw(0x001F)
    stamps = 0

    def sync_with_stamp() -> None:
        nonlocal stamps
        d.sync()
        d.frame(cob.TIME_STAMP_COB_ID, int(round(d.t * 1e6) % (1 << 32)).to_bytes(4, "little"))
        stamps += 1

    sync_with_stamp()
    start_ticks = d.model.counters.ticks
    for _ in range(1000):  # 10 s
        sync_with_stamp()
    run = d.model.counters.ticks - start_ticks
    assert abs(run - 10_000) <= 1  # uncorrected it would be 10_002
    assert d.model.clock is not None and d.model.clock.stamps == stamps


# ---- 8. TPDO latency --------------------------------------------------------------------------------------------
def test_tpdo_latency_holds_the_tpdos_up_to_the_stated_time() -> None:
    d = VDrive(options=SimDriveOptions(tpdo_latency_ms=9.0, seed=3))
    d.enable()
    d.t += 0.0095
    d.model.advance(d.t)  # what the enable sequence's SYNCs still held
    delays = []
    for _ in range(50):
        d.t += 0.010
        d.model.advance(d.t)  # heartbeats due by now (the TPDOs of the last SYNC already went)
        now = d.model.on_sync(d.t)
        assert all(f.cob_id not in (cob.tpdo1_id(1), cob.tpdo2_id(1)) for f in now)
        out: list[codec.Frame] = []
        while not out:
            due = d.model.next_deadline()
            assert due is not None and d.t <= due <= d.t + 0.009 + 1e-12
            out = [f for f in d.model.advance(due) if f.cob_id != 0x701]  # not the heartbeat
        assert [f.cob_id for f in out] == [cob.tpdo1_id(1), cob.tpdo2_id(1)]
        delays.append(due - d.t)
    assert max(delays) > 0.007 and min(delays) < 0.002  # spread over the stated range


def test_tpdo_jitter_sends_some_answers_after_the_next_sync_in_order() -> None:
    """tpdo_jitter_ms: up to that much after the latency draw, so some answers come after the next SYNC;
    a SYNC's answers never overtake the previous SYNC's (a drive answers in order)."""
    d = VDrive(options=SimDriveOptions(tpdo_latency_ms=9.0, tpdo_jitter_ms=6.0, seed=3))
    d.enable()
    d.t += 0.0095
    d.model.advance(d.t + 0.02)  # what the enable sequence's SYNCs still held
    d.t += 0.02
    syncs: list[float] = []
    arrivals: list[float] = []
    for _ in range(200):
        d.t += 0.010
        syncs.append(d.t)
        for f in d.model.on_sync(d.t):
            if f.cob_id == cob.tpdo1_id(1):
                arrivals.append(d.t)
        while (due := d.model.next_deadline()) is not None and due < d.t + 0.010:
            arrivals += [due for f in d.model.advance(due) if f.cob_id == cob.tpdo1_id(1)]
    delays = [a - s for s, a in zip(syncs, arrivals, strict=False)]
    assert len(arrivals) >= 190 and arrivals == sorted(arrivals)
    assert sum(1 for x in delays if x > 0.010) >= 10 and max(delays) <= 0.015 + 1e-9


# ---- CiA 301: SYNC counter and TPDO start value ---------------------------------------------------------------------
def test_tpdo2_every_nth_sync_from_its_start_value() -> None:
    fb = FeedbackSchedule.staggered([1, 2, 3, 4, 5], 4)
    assert [fb.start_value(n) for n in (1, 2, 3, 4, 5)] == [1, 2, 3, 4, 1]
    assert fb.counter_overflow == 240
    d = VDrive(make_axis(2), configure=False)
    d.frames += d.model.configure(10, t=0.0, feedback=fb)
    assert d.model.sdo_read(0x1019, 0) == 240 and d.model.sdo_read(0x1801, 2) == 4
    assert d.model.sdo_read(0x1801, 6) == 2
    carried = []
    for counter in range(1, 14):
        n = len(d.frames)
        d.t += 0.01
        d.frames += d.model.on_sync(d.t, bytes([counter]))
        if any(f.cob_id == cob.tpdo2_id(2) for f in d.frames[n:]):
            carried.append(counter)
        assert fb.carries(2, counter) == (counter in carried)
    assert carried == [2, 6, 10]


# ---- the config surface -------------------------------------------------------------------------------------------
def test_options_and_readings_name_bad_keys() -> None:
    with pytest.raises(PlanningError, match=r"sim\.fifo_count must be one of"):
        SimDriveOptions(fifo_count="sometimes")
    with pytest.raises(PlanningError, match=r"needs sim\.clock"):
        SimDriveOptions(clock_drift_ppm=10.0)
    assert SimDriveOptions(fifo_count="until_segment_start").describe() == "fifo_count='until_segment_start'"
    r = DriveReadings(fifo_count="until_segment_start")
    assert r.unknown() == ("tpdo_sampling", "first_record", "rounding", "underflow_check", "clock")
    assert r.merged(DriveReadings(clock="own", fifo_count="until_segment_end")).fifo_count == "until_segment_start"
    assert DriveReadings.of_sim(SimDriveOptions(clock="own", clock_drift_ppm=5.0)).clock == "own"
    assert CPR == 8192
