"""`run_homing` in real time (issue 14): the master's homing sequence over SDO on a python-can virtual bus while
its periodic SYNC runs, against simulated drives in this process (bus/sim/node.py `SimulatedCell`), through
the port the job service's runtime uses (streamer/runtime/bus_backend.py). Two axes search switches in opposite
directions at once; both end attained at their switch edges, back in their streaming mode and enabled."""

from __future__ import annotations

import dataclasses
import math
import uuid

import pytest

from bus.codec import Cia402State, state_from_statusword
from bus.network import MasterAdapter
from bus.sim.node import SimulatedCell
from bus.sim.process import DRIVES_SYNC_GAP_FACTOR  # the test suite's one margin (tests/conftest.py)
from planner.config import BusConfig, CellConfig
from planner.job import job_from_dict
from streamer.runtime.bus_backend import _RealtimePort
from streamer.runtime.homing import SW_HOMING_ATTAINED, run_homing

INF = math.inf


def _cell(demo_cell: CellConfig) -> CellConfig:
    """j1 (the shipped home switch, active above 0.05 rad) and j2 with a switch active below -0.05 rad, on a
    virtual channel of their own."""
    j1, j2 = demo_cell.axes[:2]
    j2 = dataclasses.replace(j2, sim=dataclasses.replace(j2.sim, home_switch=(-INF, -0.05)))
    bus = BusConfig(interface="virtual", channel=f"pvt-homing-{uuid.uuid4().hex[:8]}", bitrate=demo_cell.bus.bitrate)
    return dataclasses.replace(demo_cell, axes=(j1, j2), bus=bus)


def test_run_homing_in_real_time_on_simulated_drives(demo_cell: CellConfig) -> None:
    cell = _cell(demo_cell)
    assert cell.axes[0].sim.home_switch == (0.05, INF)
    job = job_from_dict({"kind": "home", "axes": ["j1", "j2"], "method": [19, 21], "search_speed": 0.2,
                         "zero_speed": 0.02, "acceleration": 2.0, "offset": [0.0, 0.01], "timeout_s": 30.0}, cell)
    sim = SimulatedCell(cell, sync_gap_factor=DRIVES_SYNC_GAP_FACTOR).start()
    adapter = None
    try:
        adapter = MasterAdapter(None, cell)
        adapter.configure_drives()
        adapter.enable_drives()
        adapter.start_sync()
        port = _RealtimePort(adapter)
        t0 = adapter.now()
        report = run_homing(cell, job, port)
        elapsed = adapter.now() - t0
        assert report["result"] == "done", report
        assert [(r["name"], r["result"]) for r in report["axes"]] == [("j1", "attained"), ("j2", "attained")]
        # real time: at least the search to the switch at the search speed (0.05 rad at 0.2 rad/s) passed
        assert 0.25 <= report["duration_s"] <= elapsed
        for axis, edge, offset in ((cell.axes[0], 0.05, 0.0), (cell.axes[1], -0.05, 0.01)):
            model = sim.model(axis.node_id)
            assert model.referenced
            # the home position is the switch edge of the machine, and there the drive now reports the offset
            assert model.machine_position / axis.counts_per_unit == pytest.approx(edge, abs=1e-3)
            here = port.read(axis.node_id, 0x6064, 0) / axis.counts_per_unit
            assert here == pytest.approx(offset, abs=1e-3)
            # back in the streaming mode, enabled, controlword bit 4 low (so "homing attained" is reset)
            assert model.mode == model.interpolation_mode and model.ready_for_job
            sw = port.read(axis.node_id, 0x6041, 0)
            assert state_from_statusword(sw) == Cia402State.OPERATION_ENABLED and not sw & SW_HOMING_ATTAINED
        assert adapter.sync_running  # SYNC ran throughout (the drives moved on it)
        sim.check()
    finally:
        if adapter is not None:
            adapter.close(check=False)
        sim.stop()
