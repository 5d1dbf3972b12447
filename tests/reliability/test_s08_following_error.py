"""Scenario 8: a drive raises EMCY 0x8611 (following error) mid-motion: the job fails within 1 SYNC with
the node and the code in the error that reaches the API."""

from __future__ import annotations

from reliability_kit import Rig, assert_all_stopped_within_one_sync, assert_no_motion_resumes, demo_traj

from bus.cob import EMCY_BASE
from bus.codec import decode_emcy
from streamer.core import JobState
from streamer.core import outcome as oc
from streamer.core.coordinator import Coordinator

NODE = 3


def test_following_error_fails_the_job_within_one_sync_with_node_and_code(variant: dict) -> None:
    rig = Rig(demo_traj(), variant=variant)

    def block_axis(core: Coordinator, n: int) -> None:
        s = core.start_sync
        if s is not None and n == s + 60:
            rig.vcell.model(NODE).disturbance_current_a = 25.0  # a load the motor cannot hold: it is dragged
        if core.state is JobState.FAILED:
            rig.vcell.model(NODE).disturbance_current_a = 0.0  # the load lets go (else it drags the axis on)

    rig.run(on_sync=block_axis)
    core = rig.core
    outcome = core.outcome
    assert core.state is JobState.FAILED and outcome is not None
    emcy = [w for w in rig.wire if w.cob_id == EMCY_BASE + NODE and decode_emcy(w.data).code == 0x8611]
    assert emcy, "the drive did not raise EMCY 0x8611"
    assert outcome.code == oc.FOLLOWING_ERROR and outcome.node == NODE, outcome
    assert outcome.sync is not None and outcome.sync - rig.sync_at(emcy[0].t) <= 1
    api_error = outcome.to_dict()  # what the runtime backend puts in the report's "error"
    assert api_error["code"] == "FOLLOWING_ERROR" and api_error["node"] == NODE
    assert api_error["detail"]["emcy_code"] == 0x8611
    assert f"node {NODE}" in api_error["message"] and "0x8611" in api_error["message"]
    assert_all_stopped_within_one_sync(rig)
    assert_no_motion_resumes(rig)
