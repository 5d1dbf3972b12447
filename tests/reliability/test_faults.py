"""The fault injector itself (bus/faults.py): the seeded model, its virtual-time link and the python-can
wrapper, including late frames in the virtual runtime."""

from __future__ import annotations

import time

import can
import pytest
from reliability_kit import Rig, demo_traj

from bus.codec import Frame
from bus.faults import (
    TO_DRIVES,
    TO_MASTER,
    FaultLink,
    FaultModel,
    FaultRule,
    FaultyBus,
    corrupt,
    delay,
    drop,
    duplicate,
    reorder,
)
from streamer.core import JobState

REC = Frame(0x302, bytes(8))


def decisions(model: FaultModel, n: int = 2000) -> list[int]:
    return [len(model.apply(Frame(0x300 + 1 + i % 3, bytes([i % 256]) * 8), i * 1e-3, TO_DRIVES)) for i in range(n)]


def test_same_seed_same_decisions_and_the_rate_is_the_probability() -> None:
    a = decisions(FaultModel([drop("RPDO2", 0.05), duplicate("RPDO2", 0.05)], seed=3))
    b = decisions(FaultModel([drop("RPDO2", 0.05), duplicate("RPDO2", 0.05)], seed=3))
    c = decisions(FaultModel([drop("RPDO2", 0.05), duplicate("RPDO2", 0.05)], seed=4))
    assert a == b and a != c
    assert 60 <= a.count(0) <= 140 and 50 <= a.count(2) <= 140  # ~100 of 2000 each


def test_rules_select_by_class_node_direction_and_window() -> None:
    m = FaultModel([drop("RPDO2", 1.0, nodes=2, direction=TO_DRIVES, start_s=1.0, end_s=2.0)])
    assert m.apply(REC, 1.5, TO_DRIVES) == []
    assert len(m.apply(REC, 0.5, TO_DRIVES)) == 1  # before the window
    assert len(m.apply(REC, 2.0, TO_DRIVES)) == 1  # after it
    assert len(m.apply(REC, 1.5, TO_MASTER)) == 1  # other direction
    assert len(m.apply(Frame(0x303, bytes(8)), 1.5, TO_DRIVES)) == 1  # other node
    assert len(m.apply(Frame(0x182, bytes(8)), 1.5, TO_DRIVES)) == 1  # other class
    assert m.stats[("drop", "RPDO2")] == 1 and "seed 0" in m.describe()
    with pytest.raises(ValueError, match="COB-ID classes"):
        FaultRule("drop", frozenset({"RPDO9"}))
    with pytest.raises(ValueError, match="action"):
        FaultRule("explode")


def test_burst_after_n_frames_and_stop_rule() -> None:
    rule = drop("RPDO2", burst=3, start_after=2)
    m = FaultModel([rule])
    got = [len(m.apply(REC, 0.0, TO_DRIVES)) for _ in range(8)]
    assert got == [1, 1, 0, 0, 0, 1, 1, 1]
    m2 = FaultModel([drop("RPDO2", 1.0)])
    assert m2.apply(REC, 0.0, TO_DRIVES) == []
    m2.stop_rule(m2.rules[0])
    assert len(m2.apply(REC, 0.0, TO_DRIVES)) == 1


def test_reorder_swaps_with_the_next_frame_of_the_same_cob_id_or_releases_late() -> None:
    a, b = Frame(0x302, b"A" * 8), Frame(0x302, b"B" * 8)
    m = FaultModel([reorder("RPDO2", burst=1, start_after=0, max_hold_s=0.005)])
    assert m.apply(a, 0.0, TO_DRIVES) == []
    assert [d.frame for d in m.apply(b, 0.001, TO_DRIVES)] == [b, a]
    m = FaultModel([reorder("RPDO2", burst=1, start_after=0, max_hold_s=0.005)])
    assert m.apply(a, 0.0, TO_DRIVES) == [] and m.release(0.004) == []
    assert [d.frame for d in m.release(0.005)] == [a]


def test_delay_and_corruptions() -> None:
    m = FaultModel([delay("RPDO2", 1.0, 0.02)])
    (d,) = m.apply(REC, 1.0, TO_DRIVES)
    assert d.frame == REC and d.delay_s == 0.02
    assert FaultLink(FaultModel([delay("RPDO2", 1.0, 0.02)])).to_drives(REC, 1.0) == [(REC, 1.02)]
    for how, check in (("short", lambda f: len(f.data) == 7), ("long", lambda f: len(f.data) == 8),
                       ("flip", lambda f: len(f.data) == 8 and f.data != REC.data),
                       ("dlc", lambda f: len(f.data) != 8)):
        (d,) = FaultModel([corrupt("RPDO2", 1.0, how)], seed=1).apply(REC, 0.0, TO_DRIVES)
        assert check(d.frame), (how, d)
    (d,) = FaultModel([corrupt("RPDO1", 1.0, "long")]).apply(Frame(0x201, b"\x1f\x00"), 0.0, TO_DRIVES)
    assert len(d.frame.data) == 3


def test_bus_off_refuses_sends_and_loses_what_would_be_received() -> None:
    m = FaultModel([], bus_off_windows=[(1.0, 2.0)])
    assert m.refuse(REC, 0.5) is None and m.refuse(REC, 1.5) == "bus-off"
    assert m.apply(Frame(0x182, bytes(8)), 1.5, TO_MASTER) == []
    m.set_bus_off("controller error passive")
    assert m.refuse(REC, 5.0) == "controller error passive"
    m.recover()
    assert m.refuse(REC, 5.0) is None


def _recv_all(bus: can.BusABC, wait_s: float) -> list[can.Message]:
    out = []
    deadline = time.monotonic() + wait_s
    while (left := deadline - time.monotonic()) > 0:
        msg = bus.recv(timeout=left)
        if msg is not None:
            out.append(msg)
    return out


def test_faulty_bus_on_the_virtual_interface() -> None:
    channel = f"rel-faulty-{time.monotonic_ns()}"
    model = FaultModel([drop(probability=1.0, nodes=1, direction=TO_DRIVES),
                        duplicate(probability=1.0, nodes=2, direction=TO_DRIVES),
                        delay(probability=1.0, delay_s=0.05, nodes=3, direction=TO_DRIVES),
                        drop("TPDO1", 1.0, direction=TO_MASTER)])
    master = FaultyBus(can.Bus(interface="virtual", channel=channel, receive_own_messages=True), model)
    drives = can.Bus(interface="virtual", channel=channel)
    try:
        t0 = time.monotonic()
        for node in (1, 2, 3, 4):
            master.send(can.Message(arbitration_id=0x300 + node, data=bytes(8), is_extended_id=False))
        got = _recv_all(drives, 0.2)
        ids = [m.arbitration_id for m in got]
        assert ids.count(0x301) == 0 and ids.count(0x302) == 2 and ids.count(0x304) == 1
        assert ids.count(0x303) == 1 and got[ids.index(0x303)].timestamp - t0 >= 0.045  # delayed
        # the master's own echo passes untouched; a drive's TPDO1 to the master is dropped, TPDO2 not
        own = _recv_all(master, 0.1)
        assert {m.arbitration_id for m in own} >= {0x302, 0x304}
        drives.send(can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False))
        drives.send(can.Message(arbitration_id=0x281, data=bytes(8), is_extended_id=False))
        assert [m.arbitration_id for m in _recv_all(master, 0.1)] == [0x281]
        master.bus_off()
        with pytest.raises(can.CanOperationError, match="bus-off"):
            master.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
        master.recover()
        master.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
        assert [m.arbitration_id for m in _recv_all(drives, 0.1)] == [0x080]
        assert master.errors == []
    finally:
        master.shutdown()
        drives.shutdown()


def test_late_records_in_virtual_time_are_waited_for_not_resent(faults) -> None:
    """Records delayed past the next SYNC (15 ms): the fill shows them missing, the core waits one SYNC,
    they arrive, nothing is resent (a resend would make them arrive twice)."""
    model = faults([delay("RPDO2", 0.03, 0.015, direction=TO_DRIVES)])
    rig = Rig(demo_traj(), faults=model)
    rig.run()
    assert model.injected("delay"), model.describe()
    assert rig.core.state is JobState.DONE, (rig.core.outcome, model.describe())
    tel = rig.core.telemetry()
    assert sum(t.late_batches for t in tel) >= 1 and sum(t.resends for t in tel) == 0
    for i, node in enumerate(rig.traj.node_ids):
        assert rig.entered[node] == rig.traj.records(i)
