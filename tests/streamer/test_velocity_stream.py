"""Velocity jobs streamed (issue 15 follow-up C), in virtual time on simulated drives: an open-ended plan is
extended chunk by chunk (streamer/core/open_stream.py) on FIFO and cyclic axes; the demand is
continuous through every chunk boundary and the cruise lies on its exact integer line; the job ends only by a
change (to a target, or another velocity), a stop, a closed chunk before the position limits, or, when no chunk
comes, a stop from the end of the queue (EXTENSION_FAILED)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from bus.events import Cancel
from bus.sim.virtual import VirtualCell
from planner.config import CellConfig, load_cell
from planner.job import job_from_dict
from planner.motion.travel import CruiseState, extend_velocity
from planner.plan import plan_job
from planner.trajectory import PvtTrajectory
from streamer import demo
from streamer.core import JobResult
from streamer.core.coordinator import Coordinator
from streamer.core.plan_source import Change, PvtTrajectoryLike
from streamer.runtime.extension import VelocityChangePlanner
from streamer.runtime.virtual import VirtualRuntime
from streamer.splice_planners import ChangePlanner, make_stop_planner

ROOT = Path(__file__).resolve().parents[2]
# three axes of each cell: EPOS only; EPOS and an XtrapulsPac (mixed); XtrapulsPac only
CELL_AXES = {"demo.toml": ["j1", "j2", "j3"], "mixed.toml": ["j1", "j3", "j4"], "xtrapuls.toml": ["j1", "j2", "j3"]}
VELOCITY = (0.1, -0.08, 0.09)  # user units/s: 10 s stay well inside the limits


@dataclass
class Run:
    cell: CellConfig
    axes: list[str]
    traj: PvtTrajectory
    core: Coordinator
    demands: dict[int, list[int]]  # node -> position demand at every SYNC from the start SYNC
    chunks: list[PvtTrajectory]  # every chunk the extender handed out, in order


Event = Callable[[CellConfig, PvtTrajectory, float], object]


def run_velocity(config: str, *, event_at_ms: int = 10_000, event: Event | None = None,
                 later: Sequence[tuple[int, Event]] = (), velocity: Sequence[float] = VELOCITY,
                 extender: Callable[[PvtTrajectoryLike], PvtTrajectoryLike | None] | None = None) -> Run:
    cell = load_cell(ROOT / "configs" / config)
    axes = CELL_AXES[config]
    job = job_from_dict({"kind": "move", "axes": axes, "mode": "velocity", "velocity": list(velocity)}, cell)
    traj = plan_job(job, cell, start=[0.0] * len(axes))
    assert traj.open_ended
    vcell = VirtualCell(cell, initial_positions=demo.start_positions(cell, traj))
    rt = VirtualRuntime(cell, vcell=vcell)
    demands: dict[int, list[int]] = {n: [] for n in traj.node_ids}
    chunks: list[PvtTrajectory] = []
    pending = sorted(([(event_at_ms, event)] if event is not None else []) + list(later), key=lambda x: x[0])

    def extend(t: PvtTrajectoryLike) -> PvtTrajectoryLike | None:
        out = extender(t) if extender is not None else extend_velocity(t)  # type: ignore[arg-type]
        if out is not None:
            chunks.append(out)  # type: ignore[arg-type]
        return out

    def on_sync(core: Coordinator, sync: int) -> None:
        if core.start_sync is not None and sync >= core.start_sync:
            for n in traj.node_ids:
                demands[n].append(vcell.models[n].position_demand)

    def feed(core: Coordinator, sync: int, t: float) -> list[object]:
        s = core.start_sync
        if not pending or s is None or (sync - s) * cell.sync_period_ms < pending[0][0]:
            return []
        return [pending.pop(0)[1](cell, traj, t)]

    result = rt.run(traj, stop_planner=make_stop_planner(cell, traj), on_sync=on_sync, feed=feed, extender=extend)
    return Run(cell, axes, traj, result.coordinator, demands, chunks)


def stop(cell: CellConfig, traj: PvtTrajectory, t: float) -> object:
    return Cancel(t)


def counts(cell: CellConfig, name: str, x: float) -> int:
    return round(x * cell.axis(name).counts_per_unit)


def check_smooth(run: Run, until: int | None = None) -> None:
    """Position and velocity continuous at every SYNC (so through every chunk boundary): the per-SYNC step
    changes by no more than the axis' acceleration allows (a velocity step of v shows as v / period)."""
    period_s = run.cell.sync_period_ms / 1000.0
    for n, name in zip(run.traj.node_ids, run.axes, strict=True):
        a = run.cell.axis(name)
        d = np.asarray(run.demands[n][:until], dtype=np.float64) / a.counts_per_unit
        acc = np.abs(np.diff(d, 2)) / period_s**2
        assert acc.max() <= 1.2 * a.acceleration, (name, float(acc.max()), a.acceleration)


@pytest.mark.parametrize("config", ["demo.toml", "mixed.toml", "xtrapuls.toml"])
def test_ten_seconds_of_velocity_stream_in_chunks_on_the_exact_cruise_and_a_stop_ends_at_rest(config: str) -> None:
    run = run_velocity(config, event=stop)
    core = run.core
    outcome = core.outcome
    assert outcome is not None and outcome.result is JobResult.CANCELLED, outcome
    assert core.extensions >= 4 and len(run.chunks) == core.extensions  # 10 s = several 2 s chunks
    # every chunk starts exactly where the one before it ended (count and rpm), with no end record between
    prev = run.traj
    for chunk in run.chunks:
        assert list(chunk.positions[:, 0]) == list(prev.positions[:, -1])
        assert list(chunk.velocities[:, 0]) == list(prev.velocities[:, -1])
        prev = chunk
    # the cruise is exact: knots on position(e) = anchor + round(v_rpm * cpr * e / 60000) from one anchor, and
    # the drive's demand between them within a count of that line
    cruise = run.traj.open_end
    assert isinstance(cruise, CruiseState)
    period = run.cell.sync_period_ms
    t1 = run.traj.duration_ms  # the anchor: the end of the first chunk
    stop_at = int(core.report().cancel["time_ms"])
    for chunk in run.chunks:
        st = chunk.open_end
        assert st is not None and st.anchor_counts == cruise.anchor_counts and st.velocity_rpm == cruise.velocity_rpm
        e0 = st.elapsed_ms - chunk.duration_ms
        for k, t in enumerate(chunk.knot_times_ms):
            assert list(chunk.positions[:, k]) == cruise.position_at(e0 + int(t))
    for i, n in enumerate(run.traj.node_ids):
        d = run.demands[n]
        for j in range(-(-t1 // period), stop_at // period):
            assert abs(d[j] - cruise.position_at(j * period - t1)[i]) <= 1, (n, j)
    check_smooth(run)
    # a stop ends at rest, from the end of what was queued
    for n in run.traj.node_ids:
        tail = run.demands[n][-20:]
        assert len(set(tail)) == 1, (n, tail)
    fifo = [a for a in core.telemetry() if a.min_fifo is not None]
    assert all(a.min_fifo >= 4 for a in fifo), [a.min_fifo for a in fifo]  # never below the watermark


@pytest.mark.parametrize("config", ["demo.toml", "mixed.toml"])
def test_a_change_to_an_absolute_target_ends_the_velocity_job_exactly_there(config: str) -> None:
    target = (0.3, -1.2, 0.4)
    planners: list[ChangePlanner] = []

    def change(cell: CellConfig, traj: PvtTrajectory, t: float) -> object:
        planners.append(ChangePlanner(cell, traj, dict(zip(CELL_AXES[config], target, strict=True))))
        return Change(t, planners[-1], mode="aborting", tag="B")

    run = run_velocity(config, event=change)
    (res,) = run.core.change_results
    assert res.accepted, res.reason
    assert run.core.outcome is not None and run.core.outcome.result is JobResult.DONE, run.core.outcome
    assert not run.core.open_ended
    assert run.core.extensions >= 4
    for n, name, x in zip(run.traj.node_ids, run.axes, target, strict=True):
        assert run.demands[n][-1] == counts(run.cell, name, x), name
    check_smooth(run)


def test_a_change_to_another_velocity_goes_on_extending_at_the_new_cruise() -> None:
    config = "mixed.toml"
    new = (-0.05, 0.06, 0.02)
    planners: list[VelocityChangePlanner] = []

    def change(cell: CellConfig, traj: PvtTrajectory, t: float) -> object:
        job = job_from_dict({"kind": "move", "axes": CELL_AXES[config], "mode": "velocity", "velocity": list(new)},
                            cell)
        planners.append(VelocityChangePlanner(cell, job, tuple(traj.node_ids)))
        return Change(t, planners[-1], mode="aborting", tag="V")

    run = run_velocity(config, event_at_ms=3_000, event=change, later=[(9_000, stop)])
    (res,) = run.core.change_results
    assert res.accepted, res.reason
    planned = planners[0].planned
    assert planned is not None and planned.trajectory.open_end is not None
    new_rpm = planned.trajectory.open_end.velocity_rpm
    after = [c for c in run.chunks if c.open_end is not None and c.open_end.velocity_rpm == new_rpm]
    assert len(after) >= 2, "the new velocity was not extended"
    first = after[0].open_end
    assert first is not None and first.anchor_counts == planned.trajectory.open_end.anchor_counts
    assert run.core.outcome is not None and run.core.outcome.result is JobResult.CANCELLED
    check_smooth(run)
    # between the change's ramp and the stop every axis moves at the new cruise (counts per SYNC)
    period = run.cell.sync_period_ms
    t_cruise = (res.time_ms or 0) + planned.trajectory.duration_ms
    for n, name, v in zip(run.traj.node_ids, run.axes, new, strict=True):
        d = np.diff(np.asarray(run.demands[n][t_cruise // period + 1: 8_500 // period], dtype=np.float64))
        per_sync = v * run.cell.axis(name).counts_per_unit * period / 1000.0
        assert np.abs(d - per_sync).max() <= 2.0, (name, float(np.abs(d - per_sync).max()))


def test_a_buffered_change_of_a_velocity_job_is_refused() -> None:
    def change(cell: CellConfig, traj: PvtTrajectory, t: float) -> object:
        return Change(t, ChangePlanner(cell, traj, {"j1": 0.0, "j2": 0.0, "j3": 0.0}), mode="buffered", tag="B")

    run = run_velocity("demo.toml", event_at_ms=1_000, event=change)
    (res,) = run.core.change_results
    assert not res.accepted and "no end" in res.reason


def test_near_the_position_limit_the_chunk_brakes_by_itself_and_the_job_ends_at_rest() -> None:
    run = run_velocity("demo.toml", velocity=(1.0, 0.0, 0.0))  # j1 reaches its limit of 3 within seconds
    assert run.core.outcome is not None and run.core.outcome.result is JobResult.DONE, run.core.outcome
    last = run.chunks[-1]
    assert last.open_end is None and last.info.get("position_limit_stop") == 1.0
    j1 = run.cell.axis("j1")
    end = run.demands[run.traj.node_ids[0]][-1]
    assert end <= j1.position_max * j1.counts_per_unit and end > (j1.position_max - 0.2) * j1.counts_per_unit
    check_smooth(run)


@pytest.mark.parametrize("config", ["demo.toml", "xtrapuls.toml"])
def test_no_next_chunk_stops_the_motion_from_the_queue_end_and_fails_extension_failed(config: str) -> None:
    calls = {"n": 0}

    def failing(t: PvtTrajectoryLike) -> PvtTrajectoryLike | None:
        calls["n"] += 1
        if calls["n"] <= 2:
            return extend_velocity(t)  # type: ignore[arg-type]
        raise RuntimeError("planner gone")

    run = run_velocity(config, extender=failing)
    outcome = run.core.outcome
    assert outcome is not None and outcome.result is JobResult.FAILED and outcome.code == "EXTENSION_FAILED"
    assert "planner gone" in outcome.message
    for n in run.traj.node_ids:  # at rest, by the stop trajectory (no quick stop: the demand is smooth)
        assert len(set(run.demands[n][-20:])) == 1
    check_smooth(run)


def test_an_extender_that_is_not_ready_is_asked_again_at_the_next_sync() -> None:
    asked = {"n": 0}

    def slow(t: PvtTrajectoryLike) -> PvtTrajectoryLike | None:
        asked["n"] += 1
        return None if asked["n"] % 5 else extend_velocity(t)  # type: ignore[arg-type]

    run = run_velocity("demo.toml", event=stop, extender=slow)
    assert run.core.outcome is not None and run.core.outcome.result is JobResult.CANCELLED, run.core.outcome
    assert run.core.extensions >= 4 and asked["n"] >= 5 * run.core.extensions
    check_smooth(run)
