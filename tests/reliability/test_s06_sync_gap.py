"""Scenario 6: a SYNC gap over 1.5 periods in motion: every drive reports it (EMCY 0x8780, its SYNC
monitoring: no SYNC within 1.5 x 0x1006), the job fails SYNC_LOST and all axes stop."""

from __future__ import annotations

import pytest
from reliability_kit import Rig, assert_all_stopped_within_one_sync, assert_no_motion_resumes, demo_traj

from streamer.core import JobState
from streamer.core import outcome as oc


@pytest.mark.parametrize("gap", [1.6, 3.0])
def test_sync_gap_over_one_and_a_half_periods_is_sync_lost(gap: float, variant: dict) -> None:
    period_s = 0.01
    gap_cycle = 150

    def sync_time(n: int) -> float:
        return n * period_s + ((gap - 1.0) * period_s if n >= gap_cycle else 0.0)

    rig = Rig(demo_traj(), sync_time=sync_time, variant=variant)
    rig.run()
    core = rig.core
    outcome = core.outcome
    assert core.state is JobState.FAILED and outcome is not None
    assert core.start_sync is not None and core.start_sync < gap_cycle - 10  # the gap came in motion
    assert outcome.code == oc.SYNC_LOST, outcome
    assert outcome.detail.get("emcy_code") == oc.EMCY_SYNC_LOST and outcome.node in rig.traj.node_ids
    # every drive detected it itself, 1.5 periods after the last SYNC (before the late SYNC came)
    last_sync_t = sync_time(gap_cycle - 1)
    for node, m in rig.vcell.models.items():
        codes = [(f.code, f.t) for f in m.fault_log]
        assert codes and codes[0][0] == oc.EMCY_SYNC_LOST, (node, codes)
        assert abs(codes[0][1] - (last_sync_t + 1.5 * period_s)) < 1e-4, (node, codes)  # + one SYNC frame
    assert outcome.t < sync_time(gap_cycle)  # the job failed before the late SYNC
    assert_all_stopped_within_one_sync(rig)
    assert_no_motion_resumes(rig)
