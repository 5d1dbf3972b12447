"""Positioning state per axis (issue 15 section 3, seed 002's 9020:03) and the in-target timeout, in virtual
time on simulated drives, plus the tracker's own rules (phases, transitions)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from bus.sim.virtual import VirtualCell
from planner.config import CellConfig, load_cell
from planner.job import job_from_dict
from planner.plan import plan_job
from streamer import demo
from streamer.core import JobResult, StreamPlan
from streamer.core.coordinator import Coordinator
from streamer.core.positioning import BadTransition, PositioningState, PositioningTracker, plan_phases
from streamer.runtime.virtual import VirtualResult, VirtualRuntime
from streamer.splice_planners import make_stop_planner

ROOT = Path(__file__).resolve().parents[2]
AXES = ["j1", "j2", "j3"]
P = PositioningState


def _run(cell: CellConfig, *, disturb: float = 0.0, disturb_from_ms: int = 0, cancel_at_s: float | None = None,
         config_axes: list[str] | None = None) -> tuple[VirtualResult, list[dict[int, PositioningState]]]:
    axes = config_axes or AXES
    traj = plan_job(job_from_dict({"kind": "move", "axes": axes, "target": [1.5, -1.0, 1.2]}, cell), cell,
                    start=[0.0] * 3)
    vcell = VirtualCell(cell, initial_positions=demo.start_positions(cell, traj))
    rt = VirtualRuntime(cell, vcell=vcell)
    seen: list[dict[int, PositioningState]] = []
    node2 = vcell.models[traj.node_ids[1]]

    def on_sync(core: Coordinator, sync: int) -> None:
        seen.append(core.positioning())
        s = core.start_sync
        if disturb and s is not None and (sync - s) * cell.sync_period_ms >= disturb_from_ms:
            node2.disturbance_current_a = disturb * node2._c.i_max  # an external load, below the current limit

    result = rt.run(traj, stop_planner=make_stop_planner(cell, traj), on_sync=on_sync, cancel_at_s=cancel_at_s,
                    settle_s=0.5)
    return result, seen


def _sequence(core: Coordinator, node: int) -> list[PositioningState]:
    out = [P.IDLE]
    for c in core.positioning_changes:
        if c.node == node and c.state is not out[-1]:
            out.append(c.state)
    return out


@pytest.fixture(scope="module")
def demo_cell() -> CellConfig:
    return load_cell(ROOT / "configs" / "demo.toml")


@pytest.mark.parametrize("config", ["demo.toml", "mixed.toml"])
def test_a_move_goes_idle_start_accel_const_decel_pre_target_target(config: str) -> None:
    cell = load_cell(ROOT / "configs" / config)
    axes = AXES if config == "demo.toml" else ["j1", "j3", "j4"]
    result, seen = _run(cell, config_axes=axes)
    core = result.coordinator
    assert core.outcome is not None and core.outcome.result is JobResult.DONE, core.outcome
    assert not core.warnings
    for node in core.node_ids:
        assert _sequence(core, node) == [P.IDLE, P.START, P.ACCEL, P.CONST, P.DECEL, P.PRE_TARGET, P.TARGET], node
    # sampled per SYNC: START while priming, the last TARGET
    assert all(st is P.START for st in seen[1].values())
    assert all(st is P.TARGET for st in seen[-1].values())
    assert core.report().positioning == {n: "TARGET" for n in core.node_ids}
    # the phases follow the plan: ACCEL begins with the motion, DECEL ends where the plan ends
    changes = {(c.node, c.state): c.elapsed_ms for c in core.positioning_changes}
    end = core.stream_duration_ms
    period = cell.sync_period_ms
    for node in core.node_ids:
        assert changes[(node, P.ACCEL)] == period
        pre = changes[(node, P.PRE_TARGET)]
        assert pre is not None and end <= pre < end + period


def test_an_axis_outside_its_window_after_the_in_target_timeout_ends_the_job_done_with_a_warning(
        demo_cell: CellConfig) -> None:
    # j2: a 50 ms in-target timeout, and a load pushing it (the position loop pulls it in, slowly) from 1 s on
    cell = dataclasses.replace(demo_cell, axes=tuple(
        dataclasses.replace(a, in_target_timeout_ms=50) if a.name == "j2" else a for a in demo_cell.axes))
    result, _ = _run(cell, disturb=0.9, disturb_from_ms=1000)
    core = result.coordinator
    out = core.outcome
    assert out is not None and out.result is JobResult.DONE, out
    (w,) = core.warnings
    j2 = next(a for a in cell.axes if a.name == "j2")
    assert w.code == "not_in_target" and w.node == j2.node_id and w.timeout_ms == 50
    assert abs(w.error_counts) > w.window_counts == round(j2.target_window_user * j2.counts_per_unit)
    assert w.elapsed_ms >= core.stream_duration_ms + 50
    assert out.detail["warnings"] == [{"code": "not_in_target", "node": j2.node_id, "error_counts": w.error_counts,
                                       "window_counts": w.window_counts, "timeout_ms": 50}]
    assert f"node {j2.node_id} not in its target window" in out.message
    assert core.positioning()[j2.node_id] is P.PRE_TARGET  # never TARGET before the job ended
    assert {core.positioning()[n] for n in core.node_ids if n != j2.node_id} == {P.TARGET}


def test_without_the_timeout_the_same_load_is_pulled_in_and_the_job_waits_for_it(demo_cell: CellConfig) -> None:
    result, _ = _run(demo_cell, disturb=0.9, disturb_from_ms=1000)
    core = result.coordinator
    assert core.outcome is not None and core.outcome.result is JobResult.DONE and not core.warnings
    j2 = demo_cell.axes[1].node_id
    target_at = next(c.elapsed_ms for c in core.positioning_changes if c.node == j2 and c.state is P.TARGET)
    assert target_at is not None and target_at > core.stream_duration_ms + demo_cell.sync_period_ms


def test_a_cancel_decelerates_on_the_stop_and_ends_stopped(demo_cell: CellConfig) -> None:
    result, _ = _run(demo_cell, cancel_at_s=0.5)
    core = result.coordinator
    assert core.outcome is not None and core.outcome.result is JobResult.CANCELLED
    for node in core.node_ids:
        seq = _sequence(core, node)
        assert seq[-1] is P.STOP and P.DECEL in seq and P.TARGET not in seq and P.PRE_TARGET not in seq, seq


def test_phases_come_from_the_velocity_with_a_dead_band() -> None:
    plan = StreamPlan.from_records([1], [0], [[(10, 100, 10), (30, 300, 10), (60, 301, 10), (90, 300, 10),
                                               (110, 100, 10), (120, -100, 10), (110, 0, 10)]])
    assert plan_phases(plan, 0) == [P.ACCEL, P.ACCEL, P.CONST, P.CONST, P.DECEL, P.DECEL, P.DECEL]
    # a splice starting at cruise speed: its first segment is CONST, not ACCEL from rest
    assert plan_phases(plan, 0, start_rpm=100)[0] is P.CONST


def test_the_tracker_refuses_a_transition_the_table_does_not_have() -> None:
    plan = StreamPlan.from_records([1], [0], [[(10, 100, 10), (20, 0, 10)]])
    tracker = PositioningTracker(plan, {1: 2}, {1: 100})
    tracker.start()
    tracker.on_time(30)
    tracker.on_actual(1, 20, 30)
    assert tracker.state(1) is P.TARGET and tracker.settled()
    with pytest.raises(BadTransition):
        tracker._go(1, P.ACCEL, 40)
