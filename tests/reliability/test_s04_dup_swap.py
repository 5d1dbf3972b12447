"""Scenario 4: 0.5% duplicated and 0.5% swapped record frames: no record enters a FIFO twice or out of
order undetected.

A duplicate is seen at the next SYNC (the drive's fill is one more than sent and not consumed:
PROTOCOL) before it is executed. A swap of two records of one axis is invisible in the fill; it is
caught when executed, by the position-demand check of the next TPDO2 (PROTOCOL). A frame held past
the next SYNC looks lost, is resent, and then arrives twice (PROTOCOL). A FIFO holds no delete, so a
record that entered twice or out of order cannot be repaired: the job fails and every axis stops.
Runs at the 10 ms SYNC (one record per batch: swaps can only be with a later cycle's record) and at a
20 ms SYNC (batches of 2: swaps inside a batch)."""

from __future__ import annotations

import pytest
from reliability_kit import (
    SEED,
    Rig,
    assert_all_stopped_within_one_sync,
    batch_index,
    long_traj,
    slow_sync_cell,
)

from bus.faults import TO_DRIVES, duplicate, reorder
from planner.encoding.record import PvtRecord
from streamer.core import JobState
from streamer.core import outcome as oc

RUNS = 8


def first_anomaly(entered: list[PvtRecord], planned: list[PvtRecord]) -> int | None:
    for j, rec in enumerate(entered):
        if j >= len(planned) or rec != planned[j]:
            return j
    return None


@pytest.mark.parametrize("sync_ms", [10, 20])
def test_duplicates_and_swaps_never_enter_a_fifo_undetected(faults, sync_ms: int, variant: dict) -> None:
    cell = slow_sync_cell(sync_ms) if sync_ms != 10 else None
    tally = {"done": 0, "dup_detected": 0, "swap_detected": 0, "swap_drive_limit": 0, "late_resend_dup": 0}
    for k in range(RUNS):
        model = faults([duplicate("RPDO2", 0.005, direction=TO_DRIVES),
                        reorder("RPDO2", 0.005, direction=TO_DRIVES)], seed=SEED + k)
        rig = Rig(long_traj(), faults=model, variant=variant, **({"cell": cell} if cell is not None else {}))
        rig.run()
        core, traj = rig.core, rig.traj
        anomalies = {node: first_anomaly(rig.entered[node], rig.stream(i))
                     for i, node in enumerate(traj.node_ids)}
        bad = {n: j for n, j in anomalies.items() if j is not None}
        if not bad:
            # whatever the wire did was harmless: the plan ran exactly
            assert core.state is JobState.DONE, (core.outcome, model.describe())
            assert max(rig.ms_deviation().values()) <= traj.tolerance_counts
            tally["done"] += 1
            continue
        outcome = core.outcome
        assert core.state is JobState.FAILED and outcome is not None, model.describe()
        # PROTOCOL from the core, or the drive's own limit check on the swapped segment (EMCY 0xFF10 /
        # 0xFF11, velocity / acceleration error) when it trips within the same period
        assert outcome.code == oc.PROTOCOL or (
            outcome.code == oc.DRIVE_FAULT
            and outcome.detail.get("emcy_code") in (oc.EMCY_IP_VELOCITY, oc.EMCY_IP_ACCELERATION)
        ), (outcome, model.describe())
        assert outcome.node in bad, (outcome, bad)
        m = assert_all_stopped_within_one_sync(rig)
        start = core.start_sync
        assert start is not None
        # detected in time: the drives followed the plan until the period that ended at the deciding
        # SYNC (a swapped record executed shows in the next TPDO2; the stop ramp after it is no plan)
        first_dev = rig.first_deviation_ms(traj.tolerance_counts)
        assert first_dev is None or first_dev > (m - start - 1) * rig.cell.sync_period_ms, (m, start, first_dev)
        node_cob = 0x300 + int(outcome.node or 0)
        if outcome.code == oc.DRIVE_FAULT:
            tally["swap_drive_limit"] += 1
        elif "twice" in outcome.message:
            dup = [d for d in model.injected("duplicate") if d.cob_id == node_cob and d.t <= outcome.t]
            tally["dup_detected" if dup else "late_resend_dup"] += 1
        else:
            assert "out of order" in outcome.message, outcome
            tally["swap_detected"] += 1
    print(f"[scenario 4] {sync_ms} ms SYNC, {RUNS} runs of the 60 s job: {tally}")
    assert sum(tally.values()) == RUNS


def test_a_swap_inside_a_batch_is_caught_when_executed(faults, variant: dict) -> None:
    """20 ms SYNC, the first record of a 2-record batch held until its follower passed: the fill is
    right, the drive executes them swapped, the next TPDO2 (or the drive's limit check) fails the job."""
    cell = slow_sync_cell(20)
    nominal = Rig(long_traj(), cell=cell, variant=variant)
    nominal.run()
    k = batch_index(nominal, 1, 2)
    model = faults([reorder("RPDO2", nodes=1, start_after=k, direction=TO_DRIVES, max_hold_s=0.005)])
    rig = Rig(long_traj(), faults=model, cell=cell, variant=variant)
    rig.run()
    planned = rig.traj.records(0)
    assert rig.entered[1][k] == planned[k + 1] and rig.entered[1][k + 1] == planned[k]  # swapped in the FIFO
    outcome = rig.core.outcome
    assert rig.core.state is JobState.FAILED and outcome is not None and outcome.node == 1, outcome
    assert outcome.code in (oc.PROTOCOL, oc.DRIVE_FAULT), outcome
    m = assert_all_stopped_within_one_sync(rig)
    start = rig.core.start_sync
    assert start is not None
    first_dev = rig.first_deviation_ms(rig.traj.tolerance_counts)
    assert first_dev is not None and first_dev > (m - start - 1) * cell.sync_period_ms
    print(f"[scenario 4] swap inside a batch: {outcome.code} at SYNC {m}, {outcome.message}")
