"""Nominal streaming: priming, synchronous start, watermarks, time-0 end, 60 s of motion, budget."""

from __future__ import annotations

import time

import pytest
from streamer_doubles import CPR, Rig, make_plan, make_trajectory

from bus.cob import RPDO1_BASE, RPDO2_BASE
from streamer.core import Coordinator, JobResult, JobState, StreamerSettings, StreamPlan
from streamer.core.coordinator import CW_ENABLE_OPERATION, CW_START_IP


def _settings(plan: StreamPlan, **kw: object) -> StreamerSettings:
    return StreamerSettings(counts_per_rev=dict.fromkeys(plan.node_ids, CPR), **kw)  # type: ignore[arg-type]


def assert_clean_run(rig: Rig) -> None:
    """DONE, every drive executed exactly its plan records, same start SYNC, FIFO within watermarks."""
    plan, core = rig.plan, rig.core
    assert core.state is JobState.DONE, core.outcome
    assert core.outcome is not None and core.outcome.result is JobResult.DONE
    s = core.start_sync
    assert s is not None
    settings = rig.settings
    assert settings is not None and rig.drives is not None
    u, o = settings.underflow_watermark, settings.overflow_watermark
    for axis, node in enumerate(plan.node_ids):
        drive = rig.drives[node]
        assert drive.activated_at == [s], (node, drive.activated_at, s)
        assert drive.executed == list(plan.records[axis][:-1])
        assert drive.demand == plan.records[axis][-1].position
        assert drive.errors == 0 and not drive.faulted
        assert drive.max_fill_seen <= o
        # sent exactly the plan's records, in order, once each, ending with the time-0 record
        assert rig.record_frames(node) == list(plan.records[axis])
        # after priming the FIFO stays within the watermarks, as long as >= U records are left to run
        total = len(plan.records[axis])
        executed_before = drive.fill_log[0][2]
        checked = 0
        for sync, fill, executed in drive.fill_log:
            if sync >= s and total - (executed - executed_before) >= u:
                assert u <= fill <= o, (node, sync, fill)
                checked += 1
        assert checked > 0
        telemetry = core.telemetry()[axis]
        assert telemetry.start_sync == s
        assert telemetry.underflow_warnings == 0 and telemetry.overflow_warnings == 0
        assert telemetry.min_fifo is not None and telemetry.min_fifo >= u
        assert telemetry.max_fifo is not None and telemetry.max_fifo <= o
        assert telemetry.max_demand_error_counts == 0
    assert not rig.sends_after_terminal
    # the records of all axes for one grid index went out in the same SYNC cycle
    cycles: dict[int, list[int]] = {}
    for m, send in rig.sent:
        if send.cob_id & 0x780 == RPDO2_BASE:
            cycles.setdefault(send.cob_id, []).append(m)
    per_index = list(zip(*cycles.values(), strict=True))
    assert all(len(set(ms)) == 1 for ms in per_index)


@pytest.mark.parametrize("n_axes", [1, 3, 6, 16])
def test_all_axes_start_on_the_same_sync(n_axes: int) -> None:
    plan = make_plan(n_axes, 2000, seed=n_axes, dt_choices=(10, 20, 30))
    rig = Rig(plan)
    rig.run(1000)
    assert_clean_run(rig)
    s = rig.core.start_sync
    assert s is not None
    # one start controlword per axis, all sent in the cycle of SYNC s - 1 (applied at SYNC s)
    starts = [(m, node) for node in plan.node_ids for m, cw in rig.controlwords(node) if cw == CW_START_IP]
    assert sorted(n for _, n in starts) == sorted(plan.node_ids)
    assert {m for m, _ in starts} == {s - 1}
    report = rig.core.report()
    assert {a.start_sync for a in report.axes} == {s}
    assert report.bus_load_peak <= 0.7


def test_priming_fills_every_fifo_to_the_priming_level_before_the_start() -> None:
    plan = make_plan(3, 1500, seed=3)
    rig = Rig(plan)
    p = rig.core.priming_level
    assert 2 <= p <= 60
    rig.run(until=lambda r: r.core.state is JobState.STARTING)
    assert rig.drives is not None
    for node in plan.node_ids:
        assert len(rig.drives[node].fifo) == p
        # bit 4 was first cleared (0x000F), so the start is a rising edge
        assert rig.controlwords(node)[0][1] == CW_ENABLE_OPERATION
    # priming goes one record per axis per SYNC, each batch confirmed before the next
    rig.run()
    assert_clean_run(rig)


def test_priming_level_respects_lead_time_and_overflow_watermark() -> None:
    dense = make_plan(2, 3000, seed=4, dt_choices=(2, 3))
    c = Coordinator(dense, _settings(dense, lead_ms=400))
    assert c.priming_level == 60  # the lead wants more; the overflow watermark caps it
    sparse = make_plan(2, 3000, seed=4, dt_choices=(100,))
    c = Coordinator(sparse, _settings(sparse))
    assert c.priming_level >= 2
    tiny = StreamPlan.from_records([1], [0], [[(10, 0, 5)]])
    assert Coordinator(tiny, _settings(tiny)).priming_level == 2  # one segment + the end record


def test_dense_plan_several_records_per_sync() -> None:
    plan = make_plan(4, 2000, seed=5, dt_choices=(2, 3, 5))
    rig = Rig(plan)
    rig.run(1000)
    assert_clean_run(rig)


def test_time0_record_ends_the_stream_and_done_waits_for_target_reached() -> None:
    plan = make_plan(2, 1000, seed=6)
    rig = Rig(plan)
    rig.run()
    assert_clean_run(rig)
    s = rig.core.start_sync
    assert s is not None
    for axis, node in enumerate(plan.node_ids):
        frames = rig.record_frames(node)
        assert frames[-1].time_ms == 0 and frames[-1].position == plan.records[axis][-2].position
    done = rig.changes[-1]
    assert done.state is JobState.DONE and done.sync is not None
    assert (done.sync - s) * 10 >= plan.duration_ms  # not before the plan's end
    finishing = next(c for c in rig.changes if c.state is JobState.FINISHING)
    assert finishing.sync is not None and finishing.sync < done.sync


def test_sixty_seconds_of_motion_in_well_under_a_few_seconds() -> None:
    plan = make_plan(6, 60_000, seed=7, dt_choices=(5, 10, 20, 40))
    rig = Rig(plan)
    t0 = time.perf_counter()
    rig.run(10_000)
    elapsed = time.perf_counter() - t0
    assert_clean_run(rig)
    report = rig.core.report()
    assert report.syncs >= 6000
    assert report.frames_per_point <= 1.05
    assert elapsed < 20.0  # virtual time: 60 s of motion, 6 axes, drive doubles included


def test_trajectory_protocol_and_sync_count_attribution_without_sync_count() -> None:
    traj = make_trajectory(2, 800, seed=8)
    plan = StreamPlan.from_trajectory(traj)
    rig = Rig(plan)

    # an adapter that does not fill sync_count: the core attributes TPDOs to the last Sync fed
    def strip(ev: object) -> bool:
        if hasattr(ev, "sync_count") and getattr(ev, "sync_count", None) is not None:
            object.__setattr__(ev, "sync_count", None)
        return True

    rig.tpdo_filter = strip
    rig.run()
    assert_clean_run(rig)


def test_budget_limits_records_per_sync_and_bus_load_stays_under_limit() -> None:
    plan = make_plan(6, 2000, seed=9, dt_choices=(5, 10))
    settings = _settings(plan, bitrate=500_000)
    rig = Rig(plan, settings)
    rig.run(2000)
    assert_clean_run(rig)
    assert rig.core.report().bus_load_peak <= 0.7 + 1e-9
    # records per SYNC cycle never exceed the budget's per-axis step times the axes (plus resends: none)
    per_cycle: dict[int, int] = {}
    for m, send in rig.sent:
        if send.cob_id & 0x780 == RPDO2_BASE:
            per_cycle[m] = per_cycle.get(m, 0) + 1
    step = rig.core._step
    assert step == 2  # (0.7 * 5000 - SYNC - 12 TPDOs - heartbeats) // (6 * 135)
    assert max(per_cycle.values()) <= step * len(plan.node_ids)


def test_frames_go_only_to_job_nodes() -> None:
    plan = make_plan(3, 800, seed=10, node_ids=[5, 9, 17])
    rig = Rig(plan)
    rig.run()
    assert_clean_run(rig)
    allowed = {base + n for n in (5, 9, 17) for base in (RPDO1_BASE, RPDO2_BASE)}
    assert {s.cob_id for _, s in rig.sent} <= allowed
