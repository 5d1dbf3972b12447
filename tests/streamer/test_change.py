"""Changing a running motion (issue 15, section 2), in virtual time on simulated drives: a new target
spliced after what is queued (buffer "aborting"), a move appended at the plan's end ("buffered"), and a
change that is refused (COMMAND_REJECTED upstream) leaving the running job exactly as planned."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from bus.sim.virtual import VirtualCell
from planner.config import CellConfig, load_cell
from planner.job import job_from_dict
from planner.plan import plan_job
from planner.trajectory import PvtTrajectory
from streamer import demo
from streamer.core import JobResult, StreamPlan
from streamer.core.coordinator import Coordinator
from streamer.core.plan_source import Change, ChangeResult
from streamer.runtime.virtual import VirtualRuntime
from streamer.splice_planners import ChangePlanner, make_stop_planner

ROOT = Path(__file__).resolve().parents[2]
AXES = ["j1", "j2", "j3"]
# three axes of each cell: EPOS only; EPOS and an XtrapulsPac (mixed); XtrapulsPac only, two in one multiplexed frame
CELL_AXES = {"demo.toml": AXES, "mixed.toml": ["j1", "j3", "j4"], "xtrapuls.toml": AXES}


@dataclass
class Run:
    cell: CellConfig
    traj: PvtTrajectory
    core: Coordinator
    demands: dict[int, list[int]]  # node -> position demand after every SYNC of the job
    syncs: list[int]
    planners: list[ChangePlanner] = field(default_factory=list)
    axes: list[str] = field(default_factory=lambda: list(AXES))

    @property
    def results(self) -> tuple[ChangeResult, ...]:
        return self.core.change_results


def run_with_change(config: str, target: Sequence[float], at_ms: int, *, mode: str = "aborting",
                    first: Sequence[float] = (1.5, -1.0, 1.2), start: Sequence[float] = (0.0, 0.0, 0.0)) -> Run:
    cell = load_cell(ROOT / "configs" / config)
    axes = CELL_AXES[config]
    job = job_from_dict({"kind": "move", "axes": axes, "target": list(first)}, cell)
    traj = plan_job(job, cell, start=list(start))
    vcell = VirtualCell(cell, initial_positions=demo.start_positions(cell, traj))
    rt = VirtualRuntime(cell, vcell=vcell)
    demands: dict[int, list[int]] = {n: [] for n in traj.node_ids}
    syncs: list[int] = []
    planners: list[ChangePlanner] = []

    def on_sync(core: Coordinator, sync: int) -> None:
        if core.start_sync is not None and sync >= core.start_sync:
            syncs.append(sync)
            for n in traj.node_ids:
                demands[n].append(vcell.models[n].position_demand)

    def feed(core: Coordinator, sync: int, t: float) -> list[object]:
        s = core.start_sync
        if planners or s is None or (sync - s) * cell.sync_period_ms < at_ms:
            return []
        planner = ChangePlanner(cell, traj, dict(zip(axes, target, strict=True)))
        planners.append(planner)
        return [Change(t, planner, mode=mode, tag="B")]

    result = rt.run(traj, stop_planner=make_stop_planner(cell, traj), on_sync=on_sync, feed=feed)
    return Run(cell, traj, result.coordinator, demands, syncs, planners, axes)


def counts(cell: CellConfig, name: str, x: float) -> int:
    a = next(a for a in cell.axes if a.name == name)
    return round(x * a.counts_per_unit)


def check_continuous(run: Run) -> None:
    """The demand through the change: velocity continuous (no step in the per-SYNC differences larger than the
    axis' acceleration allows, with a margin), and no standstill of every axis at once before the end."""
    period_s = run.cell.sync_period_ms / 1000.0
    moving_until = max(
        max(i for i, d in enumerate(run.demands[n]) if d != run.demands[n][-1]) for n in run.traj.node_ids)
    for n, name in zip(run.traj.node_ids, run.axes, strict=True):
        a = next(a for a in run.cell.axes if a.name == name)
        d = np.asarray(run.demands[n], dtype=np.float64) / a.counts_per_unit
        acc = np.abs(np.diff(d, 2)) / period_s**2  # a velocity step of v in one SYNC shows as v / period here
        assert acc.max() <= 1.2 * a.acceleration, (name, float(acc.max()), a.acceleration)
    speed = np.zeros(moving_until)
    for n in run.traj.node_ids:
        speed += np.abs(np.diff(np.asarray(run.demands[n][: moving_until + 1], dtype=np.float64)))
    stood = [i for i in range(1, moving_until) if speed[i] == 0.0]
    assert not stood, f"every axis stood still at SYNC(s) {stood[:5]} between the start and the arrival"


@pytest.mark.parametrize("config", ["demo.toml", "mixed.toml", "xtrapuls.toml"])
def test_a_change_mid_motion_is_continuous_and_every_axis_arrives_at_the_new_target_together(config: str) -> None:
    target = (-0.5, 0.6, -0.8)  # every axis reverses: the change brakes and comes back
    run = run_with_change(config, target, at_ms=400)
    (res,) = run.results
    assert res.accepted, res.reason
    assert res.knot is not None and res.time_ms is not None and res.duration_ms is not None
    outcome = run.core.outcome
    assert outcome is not None and outcome.result is JobResult.DONE, outcome
    # what ran: the job's plan up to the change's knot, then the change (nothing taken back)
    planned = run.planners[0].planned
    assert planned is not None
    change = StreamPlan.from_trajectory(planned.trajectory)
    assert run.core.pieces[-1] == (res.time_ms, change)
    # every axis ends exactly at the new target, all at the same SYNC
    arrive = []
    for n, name, x in zip(run.traj.node_ids, run.axes, target, strict=True):
        d = run.demands[n]
        assert d[-1] == counts(run.cell, name, x), name
        arrive.append(max(i for i, v in enumerate(d) if v != d[-1]) + 1)
    assert max(arrive) - min(arrive) <= 1, arrive
    end_ms = res.time_ms + res.duration_ms
    assert abs(max(arrive) * run.cell.sync_period_ms - end_ms) <= run.cell.sync_period_ms
    check_continuous(run)
    # the running job was cut at the change: it never reached its own target
    for n, name, x in zip(run.traj.node_ids, run.axes, (1.5, -1.0, 1.2), strict=True):
        assert max(abs(v - counts(run.cell, name, x)) for v in run.demands[n]) > 0


def test_a_change_that_passes_its_target_reports_the_overrun() -> None:
    # the axes head for (1.5, -1, 1.2) at speed; the new targets lie just ahead: it brakes past it and comes back
    run = run_with_change("demo.toml", (0.9, -0.6, 0.75), at_ms=500)
    (res,) = run.results
    assert res.accepted, res.reason
    planned = run.planners[0].planned
    assert planned is not None and planned.overrun_axes, "no overrun reported"
    for name, past in zip(planned.overrun_axes, planned.overrun_counts, strict=True):
        n = run.traj.node_ids[AXES.index(name)]
        goal = run.demands[n][-1]
        sign = 1 if goal > run.demands[n][0] else -1
        # (sampled once per SYNC: the peak may fall between two samples)
        assert max((v - goal) * sign for v in run.demands[n]) >= 0.98 * past  # the drive went that far past it


def test_a_refused_change_leaves_the_running_job_exactly_as_planned() -> None:
    cell = load_cell(ROOT / "configs" / "demo.toml")
    limit = next(a for a in cell.axes if a.name == "j1").position_max
    run = run_with_change("demo.toml", (limit + 0.5, 0.0, 0.0), at_ms=300)  # outside the software limits
    (res,) = run.results
    assert not res.accepted and "software position limits" in res.reason
    assert run.core.outcome is not None and run.core.outcome.result is JobResult.DONE
    assert run.core.pieces == ((0, StreamPlan.from_trajectory(run.traj)),)
    for i, n in enumerate(run.traj.node_ids):
        assert run.demands[n][-1] == int(run.traj.positions[i, -1])
    plain = run_with_change("demo.toml", (0.0, 0.0, 0.0), at_ms=10**9)  # the same job, never changed
    assert plain.results == ()
    assert run.demands == plain.demands  # every SYNC's demand exactly as without the request


def test_a_change_too_late_is_refused_with_the_reason() -> None:
    run = run_with_change("demo.toml", (0.0, 0.0, 0.0), at_ms=1000)  # the plan (1.1 s) has its end queued by then
    (res,) = run.results
    assert not res.accepted and "already queued" in res.reason


def test_a_buffered_move_runs_on_from_the_plan_end_without_a_new_start() -> None:
    target = (0.2, 0.3, -0.4)
    run = run_with_change("demo.toml", target, at_ms=200, mode="buffered")
    (res,) = run.results
    assert res.accepted, res.reason
    assert res.time_ms == run.traj.duration_ms  # appended at the plan's end
    assert run.core.outcome is not None and run.core.outcome.result is JobResult.DONE
    for n, name, x in zip(run.traj.node_ids, AXES, target, strict=True):
        assert run.demands[n][-1] == counts(run.cell, name, x)
        assert counts(run.cell, name, (1.5, -1.0, 1.2)[AXES.index(name)]) in run.demands[n]  # first target reached
