"""The planned emergency stop (issue 15 section 2, seed 002's "Emergency deceleration"), in virtual time on
simulated drives: spliced after what is queued like the cancel's stop, at each axis' emergency deceleration,
and the drives' quick stop only when no plan is possible."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bus.events import Cancel
from bus.sim.virtual import VirtualCell
from planner.config import CellConfig, load_cell
from planner.job import job_from_dict
from planner.plan import plan_job
from planner.trajectory import PvtTrajectory
from streamer import demo
from streamer.core import JobResult
from streamer.core.coordinator import Coordinator
from streamer.core.plan_source import EmergencyStop, StopPlanner, StopRequest
from streamer.core.positioning import PositioningState
from streamer.runtime.virtual import VirtualRuntime
from streamer.splice_planners import make_emergency_planner, make_stop_planner

ROOT = Path(__file__).resolve().parents[2]
AXES = ["j1", "j2", "j3"]
AT_MS = 800  # in the cruise of the move below


@dataclass
class Stopped:
    core: Coordinator
    demand: np.ndarray  # (SYNCs from the start SYNC, axes), user units
    cut: int  # the SYNC index (from the start SYNC) where the stop begins
    models: dict[int, Any]  # node -> the simulated drive


@pytest.fixture(scope="module")
def cell() -> CellConfig:
    return load_cell(ROOT / "configs" / "demo.toml")


@pytest.fixture(scope="module")
def traj(cell: CellConfig) -> PvtTrajectory:
    job = job_from_dict({"kind": "move", "axes": AXES, "target": [2.8, -1.8, 2.3]}, cell)
    return plan_job(job, cell, start=[-2.8, 1.8, -2.3])


def _stop(cell: CellConfig, traj: PvtTrajectory, how: str, planner: StopPlanner | None = None) -> Stopped:
    vcell = VirtualCell(cell, initial_positions=demo.start_positions(cell, traj))
    rt = VirtualRuntime(cell, vcell=vcell)
    demand: list[list[int]] = []
    fed: list[int] = []

    def on_sync(core: Coordinator, sync: int) -> None:
        if core.start_sync is not None and sync >= core.start_sync:
            demand.append([vcell.models[n].position_demand for n in traj.node_ids])

    def feed(core: Coordinator, sync: int, t: float) -> list[object]:
        s = core.start_sync
        if fed or s is None or (sync - s) * cell.sync_period_ms < AT_MS:
            return []
        fed.append(sync)
        return [Cancel(t)] if how == "stop" else [EmergencyStop(t, planner)]

    result = rt.run(traj, stop_planner=make_stop_planner(cell, traj), on_sync=on_sync, feed=feed)
    cpu = np.array([next(a for a in cell.axes if a.name == n).counts_per_unit for n in AXES])
    core = result.coordinator
    cut_ms = core.report().cancel.get("time_ms", AT_MS)
    return Stopped(core, np.asarray(demand, dtype=np.float64) / cpu, int(cut_ms) // cell.sync_period_ms,
                   dict(vcell.models))


def _peak_deceleration(run: Stopped, period_s: float) -> np.ndarray:
    """Per axis, the largest |acceleration| of the drives' demand (per-SYNC second differences) after the cut."""
    acc = np.diff(run.demand[run.cut - 1:], 2, axis=0) / period_s**2
    return np.asarray(np.abs(acc).max(axis=0))


def test_the_emergency_stop_decelerates_at_the_emergency_deceleration_and_stops_sooner_than_a_stop(
        cell: CellConfig, traj: PvtTrajectory) -> None:
    period_s = cell.sync_period_s
    cfg = [next(a for a in cell.axes if a.name == n) for n in AXES]
    emergency_decel = np.array([a.emergency_stop_deceleration for a in cfg])
    normal_decel = np.array([a.acceleration for a in cfg])
    assert np.all(emergency_decel > 1.2 * normal_decel)  # the comparison below means something

    emcy = _stop(cell, traj, "emergency", make_emergency_planner(cell, traj))
    core = emcy.core
    out = core.outcome
    assert out is not None and out.result is JobResult.CANCELLED, out
    info = core.emergency
    assert info is not None and info["method"] == "emergency_trajectory", info
    assert core.report().cancel["stop"] == "emergency_trajectory" and core.report().cancel["emergency"] is True
    # spliced after what was queued at the request (the cruise), like the cancel's stop
    assert info["time_ms"] >= AT_MS and core.pieces[-1][0] == info["time_ms"]
    peak = _peak_deceleration(emcy, period_s)
    # time-synchronised: the axis that needs longest brakes at its emergency deceleration, none beyond it (the
    # encoder's tolerance and the SYNC sampling: a few %)
    assert np.all(peak <= 1.05 * emergency_decel), (peak, emergency_decel)
    assert 0.9 <= float(np.max(peak / emergency_decel)) <= 1.05, (peak, emergency_decel)
    for node in core.node_ids:
        states = [c.state for c in core.positioning_changes if c.node == node]
        assert states[-2:] == [PositioningState.EMCY, PositioningState.STOP], states

    normal = _stop(cell, traj, "stop")
    assert normal.core.outcome is not None and normal.core.outcome.result is JobResult.CANCELLED
    assert normal.cut == emcy.cut  # the same state at the end of the queue: the same comparison
    normal_peak = _peak_deceleration(normal, period_s)
    assert float(np.max(normal_peak / normal_decel)) <= 1.05
    # stopping time and distance from the same state: the emergency stop is shorter on every axis
    emcy_ms = int(info["stop_duration_ms"])
    normal_ms = int(normal.core.report().cancel["stop_duration_ms"])
    assert emcy_ms < 0.7 * normal_ms, (emcy_ms, normal_ms)
    emcy_dist = np.abs(emcy.demand[-1] - emcy.demand[emcy.cut])
    normal_dist = np.abs(normal.demand[-1] - normal.demand[normal.cut])
    assert np.all(emcy_dist < 0.8 * normal_dist), (emcy_dist, normal_dist)


@pytest.mark.parametrize("why", ["no planner", "planner raises"])
def test_without_a_plan_the_emergency_stop_quick_stops_every_drive(cell: CellConfig, traj: PvtTrajectory,
                                                                   why: str) -> None:
    def broken(request: StopRequest) -> PvtTrajectory:
        raise RuntimeError("no plan today")

    run = _stop(cell, traj, "emergency", None if why == "no planner" else broken)
    core = run.core
    out = core.outcome
    assert out is not None and out.result is JobResult.FAILED and out.code == "EMERGENCY_STOP", out
    info = core.emergency
    assert info is not None and info["method"] == "quick_stop"
    assert ("no emergency stop planner" if why == "no planner" else "no plan today") in info["reason"]
    assert out.detail["method"] == "quick_stop"
    assert set(core.positioning().values()) == {PositioningState.EMCY}
    for node in core.node_ids:  # every drive got the quick stop: it ramped down and is disabled
        model = run.models[node]
        assert model.state.name in ("SWITCH_ON_DISABLED", "QUICK_STOP_ACTIVE"), model.state
