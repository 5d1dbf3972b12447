"""Scenario 10: malformed frames on the bus (wrong DLC, unknown COB-IDs): counted and logged, no crash;
the simulated drive answers a short RPDO with EMCY 0x8210 and a long one with 0x8220.

What each kind of frame does:
- unknown COB-IDs (no CANopen meaning) and frames of nodes outside the job, any DLC: counted
  (`unknown_cob_id`, `other_node`), in the candump log, no effect on the job;
- an RPDO of a job drive with the wrong length (from any sender): the drive does not process it and
  faults with EMCY 0x8210 (short) / 0x8220 (long); the job fails DRIVE_FAULT with that code, all stop;
- a TPDO/EMCY/heartbeat with a job drive's COB-ID that does not decode: counted `malformed`, turned
  into an AdapterError (never an exception), and the job fails BUS_ERROR naming the frame: the master
  cannot trust that drive's feedback any more, so it stops everything rather than guess.
"""

from __future__ import annotations

import dataclasses
import os
import random
import time

import can
import pytest
from reliability_kit import SEED, Rig, assert_all_stopped_within_one_sync, cell3, demo_traj, start_positions

from bus.cob import EMCY_BASE, RPDO1_BASE, RPDO2_BASE, TPDO1_BASE, classify
from bus.codec import Frame, decode_emcy
from bus.network import MasterAdapter
from bus.sim.node import SimulatedCell
from bus.sim.process import DRIVES_SYNC_GAP_FACTOR  # the test suite's one margin (tests/conftest.py)
from streamer.core import JobState
from streamer.core import outcome as oc
from streamer.runtime.realtime import RealtimeRuntime
from streamer.runtime.virtual import ForeignTraffic
from streamer.splice_planners import make_stop_planner

JOB_NODES = (1, 2, 3)


def garbage(seed: int, n: int, t0: float, t1: float) -> list[tuple[float, Frame]]:
    """Frames no job node may react to: unknown COB-IDs and every class of nodes 9..127, DLC 0..8."""
    rng = random.Random(seed)
    out = []
    for _ in range(n):
        if rng.random() < 0.5:
            cob_id = rng.choice([0x001, 0x050, 0x07F, 0x6E0, 0x7F0, 0x7FF])  # no CANopen meaning here
        else:
            cob_id = rng.choice([0x080, 0x180, 0x200, 0x280, 0x300, 0x580, 0x600, 0x700]) + rng.randrange(9, 128)
        data = bytes(rng.randrange(256) for _ in range(rng.randrange(9)))
        out.append((rng.uniform(t0, t1), Frame(cob_id, data)))
    return sorted(out, key=lambda x: x[0])


def test_unknown_and_foreign_malformed_frames_are_counted_and_logged_without_effect() -> None:
    frames = garbage(SEED, 2000, 0.05, 3.0)
    rig = Rig(demo_traj(), foreign=ForeignTraffic(frames))
    rig.run()
    assert rig.core.state is JobState.DONE, rig.core.outcome
    assert max(rig.ms_deviation().values()) <= rig.traj.tolerance_counts
    unknown = sum(1 for _, f in frames if classify(f.cob_id).kind == "OTHER")
    others = len(frames) - unknown
    c = rig.rt.counters
    assert c["foreign"] == len(frames)
    assert c["unknown_cob_id"] == unknown and c["other_node"] == others and c["malformed"] == 0, c
    logged = {(w.cob_id, w.data) for w in rig.wire}
    assert all((f.cob_id, f.data) in logged for _, f in frames)  # every one of them in the log
    for m in rig.vcell.models.values():
        assert m.counters.pdo_length_errors == 0 and not m.fault_log


@pytest.mark.parametrize(("cob_id", "data", "code"), [
    (RPDO2_BASE + 2, bytes(7), oc.EMCY_PDO_SHORT),  # a PVT record one byte short
    (RPDO2_BASE + 2, b"", oc.EMCY_PDO_SHORT),
    (RPDO1_BASE + 3, bytes([0x1F, 0x00, 0x00]), oc.EMCY_PDO_LONG),  # a controlword with a byte too many
])
def test_wrong_length_rpdo_is_answered_with_emcy_and_fails_the_job(cob_id: int, data: bytes, code: int) -> None:
    node = cob_id & 0x7F
    rig = Rig(demo_traj(), foreign=ForeignTraffic([(1.2345, Frame(cob_id, data))]))
    rig.run()
    emcy = [decode_emcy(w.data) for w in rig.wire if w.cob_id == EMCY_BASE + node]
    assert emcy and emcy[0].code == code, emcy
    assert rig.vcell.model(node).counters.pdo_length_errors == 1
    outcome = rig.core.outcome
    assert rig.core.state is JobState.FAILED and outcome is not None
    assert outcome.code == oc.DRIVE_FAULT and outcome.node == node and outcome.detail["emcy_code"] == code
    assert_all_stopped_within_one_sync(rig)


def test_undecodable_feedback_of_a_job_drive_is_counted_and_fails_bus_error() -> None:
    bad = Frame(TPDO1_BASE + 1, bytes(5))  # TPDO1 is 8 bytes
    rig = Rig(demo_traj(), foreign=ForeignTraffic([(1.2345, bad)]))
    rig.run()
    assert rig.rt.counters["malformed"] == 1
    outcome = rig.core.outcome
    assert rig.core.state is JobState.FAILED and outcome is not None
    assert outcome.code == oc.BUS_ERROR and "0x181" in outcome.message, outcome
    assert_all_stopped_within_one_sync(rig)


@pytest.mark.slow
@pytest.mark.isolated  # real time with the drives in this process (in the whole suite a drive fell silent)
def test_garbage_on_the_real_time_virtual_bus() -> None:
    """python-can virtual bus, real time: 1500 garbage frames from a third bus during a job."""
    cell = dataclasses.replace(cell3(), bus=dataclasses.replace(cell3().bus, channel=f"rel-garbage-{os.getpid()}"))
    traj = demo_traj()
    sim = SimulatedCell(cell, initial_positions=start_positions(traj),
                        sync_gap_factor=DRIVES_SYNC_GAP_FACTOR).start()
    adapter = MasterAdapter(None, cell)
    noise = can.Bus(interface="virtual", channel=cell.bus.channel)
    rt = None
    try:
        adapter.configure_drives()
        rt = RealtimeRuntime(cell, adapter)
        frames = garbage(SEED, 1500, 0.0, 1.0)
        sent = [0]

        def spray(core: object) -> None:  # 2 frames per event the runtime handles: spread over the job
            for _ in range(2):
                if sent[0] < len(frames):
                    f = frames[sent[0]][1]
                    noise.send(can.Message(arbitration_id=f.cob_id, data=f.data, is_extended_id=False))
                    sent[0] += 1

        result = rt.run(traj, stop_planner=make_stop_planner(cell, traj), on_change=spray)
        assert result.coordinator.state is JobState.DONE, result.coordinator.outcome
        assert sent[0] == len(frames)
        unknown = sum(1 for _, f in frames if classify(f.cob_id).kind == "OTHER")
        deadline = time.monotonic() + 2.0  # the receive thread may still be working through the last ones
        while adapter.counters["unknown_cob_id"] + adapter.counters["other_node"] < len(frames):
            assert time.monotonic() < deadline, adapter.counters
            time.sleep(0.01)
        assert adapter.counters["unknown_cob_id"] == unknown
        assert adapter.counters["other_node"] == len(frames) - unknown
        assert adapter.counters["malformed"] == 0 and adapter.failures == []
        sim.check()
        with sim.locked() as models:
            for m in models.values():
                assert m.counters.pdo_length_errors == 0 and not m.fault_log
    finally:
        if rt is not None:
            rt.close()
        noise.shutdown()
        adapter.close(check=False)
        sim.stop()
