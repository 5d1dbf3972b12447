"""Scenario 7: one drive's heartbeat stops (its heartbeat frames never reach the master, the drive
itself keeps running): within the consumer timeout + 1 SYNC the job fails NODE_LOST, every axis gets
the quick stop, and the drive's later boot-up does not resume motion."""

from __future__ import annotations

from reliability_kit import Rig, assert_all_stopped_within_one_sync, assert_no_motion_resumes, demo_traj

from bus.cob import HEARTBEAT_BASE
from bus.faults import TO_MASTER, drop
from streamer.core import JobState
from streamer.core import outcome as oc
from streamer.core.coordinator import Coordinator

NODE = 2
SILENT_FROM_S = 1.5


def test_heartbeat_loss_is_node_lost_and_a_later_bootup_does_not_resume(faults, variant: dict) -> None:
    silence = drop("HEARTBEAT", 1.0, nodes=NODE, direction=TO_MASTER, start_s=SILENT_FROM_S)
    model = faults([silence])
    rig = Rig(demo_traj(), faults=model, variant=variant)
    cell = rig.cell
    rebooted: list[float] = []

    def reboot_later(core: Coordinator, n: int) -> None:
        t = rig.rt.now
        if core.state is JobState.FAILED and not rebooted:
            model.stop_rule(silence)  # the drive's frames reach the master again
            rebooted.append(t)  # the drive reboots (NMT reset node seen by it alone): boot-up
            rig.rt.drive_frames(rig.vcell.model(NODE).on_frame(0, bytes([0x81, NODE]), t), t)

    rig.run(on_sync=reboot_later)
    core = rig.core
    outcome = core.outcome
    assert core.state is JobState.FAILED and outcome is not None
    assert outcome.code == oc.NODE_LOST and outcome.node == NODE, outcome
    last_hb = max(w.t for w in rig.wire if w.cob_id == HEARTBEAT_BASE + NODE and w.t < SILENT_FROM_S)
    timeout_s = cell.drive.heartbeat_timeout_ms / 1000.0
    # the last heartbeat ended ~65 us after it started; detection within the timeout + 1 SYNC
    assert timeout_s < outcome.t - last_hb <= timeout_s + cell.sync_period_s + 1e-3, (last_hb, outcome.t)
    assert_all_stopped_within_one_sync(rig)
    assert rebooted, "the drive's boot-up was not injected"
    assert any(w.cob_id == HEARTBEAT_BASE + NODE and w.data == b"\x00" and w.t >= rebooted[0] for w in rig.wire)
    assert_no_motion_resumes(rig)
    print(f"[scenario 7] NODE_LOST {outcome.t - last_hb:.3f} s after node {NODE}'s last heartbeat "
          f"(timeout {timeout_s} s)")
