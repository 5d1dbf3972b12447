"""Scenario 9: bus-off (the master's controller refuses to send): the streamer stops sending, the job
fails BUS_ERROR, and a new job works after the bus recovers.

In virtual time (FaultLink, a bus-off window) and in real time on python-can's `virtual` interface
(FaultyBus around the master's bus, the simulated drives on the same channel, SYNC from the adapter's
periodic task). While the master is off the bus its quick stop cannot go out either: the drives stop
on their own, on the missing SYNC (EMCY 0x8780, fault reaction), which they report once the bus is
back. After recovery: fault reset + enable over SDO, SYNC restarted, a new job from where the axes
stand runs DONE."""

from __future__ import annotations

import dataclasses
import os
import time

import can
import pytest
from reliability_kit import Rig, cell3, demo_traj, start_positions

from bus.codec import Cia402State
from bus.faults import FaultModel, FaultyBus
from bus.network import MasterAdapter
from bus.sim.node import SimulatedCell
from bus.sim.process import DRIVES_SYNC_GAP_FACTOR  # the test suite's one margin (tests/conftest.py)
from planner.config import CellConfig
from planner.job import job_from_dict
from planner.plan import plan_job
from planner.trajectory import PvtTrajectory
from streamer.core import JobState
from streamer.core import outcome as oc
from streamer.core.coordinator import Coordinator
from streamer.runtime.realtime import RealtimeRuntime
from streamer.splice_planners import make_stop_planner

OFF_AT_S, OFF_FOR_S = 1.5, 0.5


def home_from(cell: CellConfig, positions_counts: dict[int, int], names: tuple[str, ...]) -> PvtTrajectory:
    """A move back to 0 from where the drives stand."""
    axes = [a for a in cell.axes if a.name in names]
    start = [positions_counts[a.node_id] / a.counts_per_unit for a in axes]
    job = job_from_dict({"kind": "move", "axes": list(names), "target": [0.0] * len(names)}, cell)
    return plan_job(job, cell, start=start)


def test_bus_off_in_virtual_time(faults) -> None:
    model = faults([], bus_off_windows=[(OFF_AT_S, OFF_AT_S + OFF_FOR_S)])
    rig = Rig(demo_traj(), faults=model)
    rig.run()
    core = rig.core
    outcome = core.outcome
    assert core.state is JobState.FAILED and outcome is not None
    assert outcome.code == oc.BUS_ERROR and "bus-off" in outcome.message, outcome
    assert OFF_AT_S <= outcome.t < OFF_AT_S + 0.011  # the first frame the core tried to send
    # the streamer stopped sending: one refused record frame, then the quick stop of the failing
    # reaction (refused too); the SYNC producer kept trying every period until the bus came back
    assert rig.rt.counters["send_refused"] - rig.rt.counters["sync_refused"] <= 2, rig.rt.counters
    assert rig.master_frames_after(OFF_AT_S) == []
    # the drives stopped on the missing SYNC
    for node, m in rig.vcell.models.items():
        assert m.fault_log and m.fault_log[0].code == oc.EMCY_SYNC_LOST, node
        assert not m.ip_active
    rig.idle(0.5)  # the bus is back
    names = rig.traj.axis_names
    here = {n: m.position_demand for n, m in rig.vcell.models.items()}
    again = home_from(rig.cell, here, names)
    result = rig.rt.run(again, stop_planner=make_stop_planner(rig.cell, again))
    assert result.coordinator.state is JobState.DONE, str(result.coordinator.outcome)
    assert result.settled
    for node, m in rig.vcell.models.items():
        assert m.position_demand == m.position_actual == 0 and m.state == Cia402State.OPERATION_ENABLED, node


@pytest.mark.slow
@pytest.mark.isolated  # the fault-injecting bus wraps the master's own bus: drives in this process, in real time
def test_bus_off_in_real_time_on_the_virtual_bus() -> None:
    cell = dataclasses.replace(cell3(), bus=dataclasses.replace(cell3().bus, channel=f"rel-busoff-{os.getpid()}"))
    traj = demo_traj()
    sim = SimulatedCell(cell, initial_positions=start_positions(traj),
                        sync_gap_factor=DRIVES_SYNC_GAP_FACTOR).start()
    model = FaultModel([], seed=0)
    faulty = FaultyBus(can.Bus(interface="virtual", channel=cell.bus.channel, receive_own_messages=True), model)
    adapter = MasterAdapter(None, cell, bus=faulty)
    rt = None
    try:
        adapter.configure_drives()
        rt = RealtimeRuntime(cell, adapter)
        went_off: list[float] = []

        def pull_the_plug(core: Coordinator) -> None:
            if not went_off and core.progress > 0.3:
                went_off.append(time.time())
                faulty.bus_off()

        result = rt.run(traj, stop_planner=make_stop_planner(cell, traj), on_change=pull_the_plug,
                        settle_s=0.5)
        core = result.coordinator
        outcome = core.outcome
        assert went_off, f"the job ended before 30 % of it: {core.state} {outcome}"
        assert core.state is JobState.FAILED and outcome is not None
        assert outcome.code == oc.BUS_ERROR and "bus-off" in outcome.message, outcome
        time.sleep(0.3)  # the drives notice the missing SYNC and fault
        with sim.locked() as models:
            for node, m in models.items():
                assert not m.ip_active, node
                assert m.state in (Cia402State.FAULT, Cia402State.FAULT_REACTION_ACTIVE), (node, m.state)
        assert not adapter.sync_running  # the SYNC producer saw the bus-off too and stopped
        faulty.recover()
        # SYNC back first (pvt serve keeps it running between jobs): the simulated drives' clock is
        # SYNC-locked, so their fault-reaction ramp only completes with SYNC (docs/reliability.md)
        adapter.start_sync()
        deadline = time.time() + 3.0
        while time.time() < deadline:
            with sim.locked() as models:
                if all(m.state == Cia402State.FAULT for m in models.values()):
                    break
            time.sleep(0.02)
        here = {a.node_id: adapter.read(a.node_id, 0x6062) for a in cell.axes}
        again = home_from(cell, here, traj.axis_names)
        result = rt.run(again, stop_planner=make_stop_planner(cell, again))
        assert result.coordinator.state is JobState.DONE, str(result.coordinator.outcome)
        with sim.locked() as models:
            for node, m in models.items():
                assert m.position_demand == 0, node
        sim.check()
    finally:
        if rt is not None:
            rt.close()
        adapter.close(check=False)
        faulty.shutdown()  # the adapter does not own a bus it was given
        sim.stop()
