"""Scenario 11: 80% bus load from higher-priority frames for 30 s: either the FIFOs stay above the
underflow watermark, or the job fails BUS_OVERLOAD before any drive underflows.

The foreign traffic is 8-byte frames on COB-ID 0x050 (above every CANopen object but NMT in priority,
SYNC included), evenly released so that their worst-case bits fill 80% of the 1 Mbit/s bus. The
virtual bus arbitrates by COB-ID, so every frame of the job waits for gaps in that traffic. 3 axes
(the scenario): the job's own ~13% fits in the 20% left; the core sees the measured load (BusLoad,
~95%) above its 70% limit, treats missing records as late rather than lost, and the FIFOs never go
below the watermark. 6 axes (the other branch): the job's traffic (~25%) does not fit; the core fails
BUS_OVERLOAD when a FIFO drops below the watermark, before any drive runs dry."""

from __future__ import annotations

from reliability_kit import Rig, assert_all_stopped_within_one_sync, long_traj

from streamer import demo
from streamer.core import JobState
from streamer.core import outcome as oc
from streamer.runtime.virtual import ForeignTraffic, periodic_load

LOAD, LOAD_S = 0.80, 30.0
OVERLOAD = 0.82


def test_80_percent_higher_priority_load_for_30s_keeps_the_fifos_above_the_watermark() -> None:
    traj = long_traj()
    foreign = ForeignTraffic(periodic_load(LOAD, 1_000_000, cob_id=0x050, start_s=0.0, duration_s=LOAD_S))
    rig = Rig(traj, foreign=foreign)
    result = rig.run()
    core = result.coordinator
    assert foreign.sent >= LOAD * LOAD_S * 1_000_000 / 135 - 1  # the load was really there
    assert core.state is JobState.DONE, core.outcome
    assert max(rig.ms_deviation().values()) <= traj.tolerance_counts
    low = rig.cell.drive.underflow_warning
    start = core.start_sync
    assert start is not None
    knot_ms = traj.knot_times_ms
    under_load = 0
    for ax in result.trace.axes.values():
        for s, fill in zip(ax.fill_sync, ax.fill, strict=True):
            elapsed = (s - start) * rig.cell.sync_period_ms
            if s < start or elapsed >= traj.duration_ms:
                continue
            left = int((knot_ms > elapsed).sum()) + 1
            assert fill >= min(low, left), (ax.name, s, fill)
            under_load += result.trace.sync_times[s] < LOAD_S
    assert under_load > 3 * 2500
    peak = core.report().measured_bus_load_peak
    assert peak is not None and peak > 0.9
    for m in rig.vcell.models.values():
        assert not m.fault_log
    print(f"[scenario 11] 3 axes, {LOAD:.0%} foreign load for {LOAD_S:.0f} s: DONE, measured bus load peak "
          f"{peak:.1%}, min FIFO {[t.min_fifo for t in core.telemetry()]} (watermark {low}), late batches "
          f"{[t.late_batches for t in core.telemetry()]}")


def test_when_the_job_does_not_fit_beside_the_load_it_fails_bus_overload_before_any_underflow() -> None:
    # 6 axes beside 82 % of higher-priority load (80 % leaves them just enough since TPDO1 carries 6 bytes)
    cell, _, traj = demo.prepare(axes=6)
    foreign = ForeignTraffic(periodic_load(OVERLOAD, cell.bus.bitrate, cob_id=0x050, duration_s=LOAD_S))
    rig = Rig(traj, cell=cell, foreign=foreign)
    rig.run()
    outcome = rig.core.outcome
    assert rig.core.state is JobState.FAILED and outcome is not None
    assert outcome.code == oc.BUS_OVERLOAD, outcome
    assert outcome.detail["fill"] >= 1  # decided while the drive still had records
    for m in rig.vcell.models.values():
        underflows = [f for f in m.fault_log if f.code == oc.EMCY_IP_BUFFER]
        assert underflows == [], (m.node_id, m.fault_log)
    assert_all_stopped_within_one_sync(rig)
    print(f"[scenario 11] 6 axes, {OVERLOAD:.0%} foreign load: {outcome.code} at SYNC {outcome.sync} "
          f"({outcome.message}); no drive underflowed")
