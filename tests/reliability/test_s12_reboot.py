"""Scenario 12: a drive reboots mid-job (its boot-up frame): the job aborts (NODE_REBOOT), all axes are
stopped within 1 SYNC, and nothing resumes by itself."""

from __future__ import annotations

from reliability_kit import Rig, assert_all_stopped_within_one_sync, assert_no_motion_resumes, demo_traj

from bus.codec import Cia402State, NmtState
from streamer.core import JobState
from streamer.core import outcome as oc
from streamer.core.coordinator import Coordinator

NODE = 1


def test_drive_reboot_mid_job_aborts_and_stops_everything() -> None:
    rig = Rig(demo_traj())

    def reboot(core: Coordinator, n: int) -> None:
        s = core.start_sync
        if s is not None and n == s + 100:
            t = rig.rt.now + 0.004
            rig.rt.drive_frames(rig.vcell.model(NODE).on_frame(0, bytes([0x81, NODE]), t), t)

    rig.run(on_sync=reboot)
    core = rig.core
    outcome = core.outcome
    assert core.state is JobState.FAILED and outcome is not None
    assert outcome.code == oc.NODE_REBOOT and outcome.node == NODE, outcome
    assert core.start_sync is not None and outcome.sync == core.start_sync + 100
    assert_all_stopped_within_one_sync(rig)
    m = rig.vcell.model(NODE)
    assert m.nmt_state == NmtState.PRE_OPERATIONAL and m.state == Cia402State.SWITCH_ON_DISABLED
    assert_no_motion_resumes(rig)
