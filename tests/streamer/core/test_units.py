"""Units of the streamer core: frame bits, the fill model, plan and settings validation, dispatch tables."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from streamer_doubles import CPR, FakeTrajectory, Rig, make_plan, make_trajectory

from bus.budget import cycle_budget
from bus.cob import rpdo3_id
from bus.events import BufferStatus, Cancel, Sync
from bus.profile import SetpointSlot
from planner.encoding.record import PvtRecord
from planner.errors import EncodingRangeError
from streamer.core import (
    Coordinator,
    FeederState,
    FifoFeeder,
    InvalidTransition,
    JobOutcome,
    JobResult,
    JobState,
    StreamerSettings,
    StreamPlan,
    UnexpectedEvent,
    frame_bits,
)
from streamer.core import outcome as oc
from streamer.core.axis_state import CYCLIC_TRANSITIONS, FIFO_TRANSITIONS, FeederInput
from streamer.core.coordinator import DISPATCH, EVENT_TYPES, JOB_TRANSITIONS, TERMINAL
from streamer.core.cyclic_feeder import CyclicAxis, CyclicFeeder
from streamer.core.job_state import STATE_TRIGGERED, TRIGGERS_BY_STATE
from streamer.core.schedule import (
    FillPolicy,
    consumed_at,
    dry_run,
    priming_level,
    segment_ends,
    target_prefix,
)


# ---- frame bits / budget -----------------------------------------------------------------------------
def test_frame_bits_worst_case_stuffing() -> None:
    assert frame_bits(0) == 55  # SYNC
    assert frame_bits(1) == 65  # heartbeat
    assert frame_bits(2) == 75  # controlword
    assert frame_bits(8) == 135  # PVT record, TPDOs
    assert all(frame_bits(n + 1) > frame_bits(n) for n in range(8))
    for bad in (-1, 9):
        with pytest.raises(ValueError):
            frame_bits(bad)


def test_cycle_budget() -> None:
    b = cycle_budget(6, 10, 1_000_000, 0.7, 100)
    assert b.cycle_bits == 10_000 and b.limit_bits == pytest.approx(7000)
    # SYNC + TPDO1 (6 bytes: 115 bits) + TPDO2 (135) per node + the heartbeats a cycle may carry
    # (the average 0.6, rounded up, plus 2 for the cycles where a few coincide)
    assert b.fixed_bits == pytest.approx(55 + 6 * (115 + 135) + 3 * 65)
    assert b.record_frames_per_axis(6) == int((7000 - b.fixed_bits) // (6 * 135))


# ---- fill model --------------------------------------------------------------------------------------
POLICY = FillPolicy(
    sync_period_ms=10, underflow_watermark=4, overflow_watermark=60, lead_ms=100, repair_syncs=2
)


def test_consumption_model_matches_the_drive_semantics() -> None:
    ends = segment_ends([30, 5, 5, 20])
    assert ends == [30, 35, 40, 60, 60]  # the end record pops with the last segment
    assert [consumed_at(ends, t) for t in (0, 29, 30, 34, 35, 40, 59, 60, 1000)] == [
        0,
        0,
        1,
        1,
        2,
        3,
        3,
        5,
        5,
    ]


@given(st.lists(st.integers(1, 255), min_size=1, max_size=300))
def test_nominal_schedule_keeps_the_fifo_between_the_watermarks(grid: list[int]) -> None:
    ends = segment_ends(grid)
    total = len(ends)
    p = priming_level(ends, POLICY)
    assert 2 <= p <= min(60, total)
    shortfall = dry_run(ends, POLICY, step_per_sync=64, prefix=p, elapsed_ms=0)
    # with segments >= 1 ms and a 10 ms SYNC at most 10 records are consumed per period: always feasible
    assert shortfall is None
    e, k = 0, p
    while consumed_at(ends, e) < total:
        k = max(k, target_prefix(ends, e, e + 10, POLICY))
        assert k - consumed_at(ends, e) <= 60  # never above the overflow watermark
        e += 10
        c = consumed_at(ends, e)
        assert k - c >= min(4, total - c)


# ---- plans -------------------------------------------------------------------------------------------
def test_stream_plan_from_trajectory_appends_the_end_record() -> None:
    traj = make_trajectory(2, 300, seed=1)
    plan = StreamPlan.from_trajectory(traj)
    for axis in range(2):
        assert plan.records[axis][-1] == PvtRecord(traj.positions[axis][-1], 0, 0)
        assert len(plan.frames[axis]) == len(plan.records[axis]) == len(traj.dt_ms) + 1
    assert plan.start_positions == (traj.positions[0][0], traj.positions[1][0])
    assert plan.duration_ms == sum(traj.dt_ms)


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda t: t.velocities_rpm[0].__setitem__(-1, 5), "end at rest"),
        (lambda t: setattr(t, "node_ids", (1, 1)), "duplicate node"),
        (lambda t: setattr(t, "node_ids", (1, 200)), "outside 1..127"),
        (lambda t: t.positions[1].__setitem__(3, 2**40), "does not fit"),
    ],
)
def test_stream_plan_rejects_bad_trajectories(mutate: object, message: str) -> None:
    traj = make_trajectory(2, 300, seed=2, dt_choices=(20,))
    mutate(traj)  # type: ignore[operator]
    with pytest.raises(
        (ValueError, EncodingRangeError), match=message.replace("[", r"\[").replace("]", r"\]")
    ):
        StreamPlan.from_trajectory(traj)


@dataclass
class _Reshaped:
    """A trajectory-like whose dt_ms or positions disagree with its records."""

    base: FakeTrajectory
    dt_ms: list[int]
    positions: list[list[int]]

    @property
    def n_axes(self) -> int:
        return self.base.n_axes

    @property
    def node_ids(self) -> tuple[int, ...]:
        return self.base.node_ids

    def records(self, axis: int) -> list[PvtRecord]:
        return self.base.records(axis)


def test_stream_plan_rejects_a_grid_mismatch_and_transposed_positions() -> None:
    with pytest.raises(ValueError, match="shared grid"):
        StreamPlan.from_records([1, 2], [0, 0], [[(10, 0, 5)], [(10, 0, 6)]])
    traj = make_trajectory(2, 100, seed=3, dt_choices=(10,))
    with pytest.raises(ValueError, match="dt_ms grid"):
        StreamPlan.from_trajectory(_Reshaped(traj, [11] * len(traj.dt_ms), traj.positions))
    transposed = [list(col) for col in zip(*traj.positions, strict=True)]
    with pytest.raises(ValueError, match=r"\[axis\]\[knot\]"):
        StreamPlan.from_trajectory(_Reshaped(traj, traj.dt_ms, transposed))


def test_settings_are_validated() -> None:
    for kw in (
        {"sync_period_ms": 0},
        {"overflow_watermark": 65},
        {"underflow_watermark": 60},
        {"bus_load_limit": 1.5},
        {"counts_per_rev": {1: 0}},
        {"sync_gap_factor": 0.5},
        {"repair_margin_ms": -1},
        {"lead_ms": True},
    ):
        with pytest.raises(ValueError, match="streamer setting"):
            StreamerSettings(**kw)
    assert StreamerSettings().margin_ms == 10


def test_settings_from_the_demo_cell(demo_cell: object) -> None:
    s = StreamerSettings.from_cell(demo_cell, lead_ms=150)
    assert s.sync_period_ms == 10 and s.bitrate == 1_000_000 and s.lead_ms == 150
    assert (s.underflow_watermark, s.overflow_watermark) == (4, 60)
    assert dict(s.counts_per_rev) == dict.fromkeys(range(1, 7), 8192)
    assert s.tpdo_timeout_syncs == 3  # the default of [drive] tpdo_timeout_syncs


def test_the_cells_tpdo_timeout_reaches_the_settings() -> None:
    import tomllib

    from planner.config import cell_from_dict
    from planner.errors import PlanningError

    data = tomllib.loads((Path(__file__).resolve().parents[3] / "configs" / "demo.toml").read_text(encoding="utf-8"))
    data["drive"]["tpdo_timeout_syncs"] = 8
    assert StreamerSettings.from_cell(cell_from_dict(data)).tpdo_timeout_syncs == 8
    for bad in (0, 101, 2.5, True):
        data["drive"]["tpdo_timeout_syncs"] = bad
        with pytest.raises(PlanningError, match=r"drive\.tpdo_timeout_syncs") as e:
            cell_from_dict(data)
        assert e.value.path == "drive.tpdo_timeout_syncs"


# ---- state machines ----------------------------------------------------------------------------------
def test_every_state_has_an_entry_for_every_event_type() -> None:
    for state in JobState:
        for etype in EVENT_TYPES.values():
            assert (state, etype) in DISPATCH
    assert all(JOB_TRANSITIONS[s] == frozenset() for s in TERMINAL)


def test_the_state_triggered_table_names_moves_of_the_core() -> None:
    for trigger in STATE_TRIGGERED:
        assert trigger.state not in TERMINAL and trigger.axes_in <= set(FeederState)
        assert callable(getattr(Coordinator, trigger.move))
        assert trigger.guard is None or callable(getattr(Coordinator, trigger.guard))
        assert trigger in TRIGGERS_BY_STATE[trigger.state]
    assert sum(len(ts) for ts in TRIGGERS_BY_STATE.values()) == len(STATE_TRIGGERED)


def _core_at(state: JobState, axes: FeederState) -> Coordinator:
    core = Coordinator(make_plan(2, 300, seed=4), StreamerSettings())
    core._state = state
    for f in core._axes:
        f.state = axes
    return core


@pytest.mark.parametrize("settled", [True, False])
def test_state_triggered_transitions_run_to_a_fixed_point(settled: bool) -> None:
    # every axis finished while the job was STARTING: one call goes RUNNING, FINISHING and (once every axis is
    # in its target window) DONE
    core = _core_at(JobState.STARTING, FeederState.FINISHED)
    core._settled = lambda: settled  # type: ignore[method-assign]
    core._progress_job()
    expected = [JobState.RUNNING, JobState.FINISHING] + ([JobState.DONE] if settled else [])
    assert [c.state for c in core._changes] == expected
    core = _core_at(JobState.STARTING, FeederState.STREAMING)  # active, not all queued: RUNNING only
    core._progress_job()
    assert [c.state for c in core._changes] == [JobState.RUNNING]


def test_a_state_triggered_move_that_leaves_the_state_raises() -> None:
    core = _core_at(JobState.STARTING, FeederState.STREAMING)
    core._to_running = lambda: None  # type: ignore[method-assign]
    with pytest.raises(RuntimeError, match="_to_running left the job in STARTING"):
        core._progress_job()


def test_an_event_without_an_entry_raises() -> None:
    core = Coordinator(make_plan(1, 300, seed=4), StreamerSettings())
    with pytest.raises(UnexpectedEvent):
        core.handle("not an event")
    core.handle(Sync(0, 0.0))
    with pytest.raises(ValueError, match="before Sync"):
        core.handle(BufferStatus(1, 0x0027, 0x4000, 64, 0.0, sync_count=3))


def test_feeder_transition_table_raises_on_missing_entries() -> None:
    f = FifoFeeder(
        0, 1, 0, [], [], sync_period_ms=10, loss_confirm_syncs=1, repair_margin_ms=10, counts_per_rev=None
    )
    with pytest.raises(InvalidTransition):
        f.fire(FeederInput.START)
    assert f.fire(FeederInput.READY) is FeederState.PRIMING
    assert f.fire(FeederInput.FAULT) is FeederState.FAULTED
    with pytest.raises(InvalidTransition):
        f.fire(FeederInput.FAULT)
    assert all(nxt in FeederState for nxt in FIFO_TRANSITIONS.values())


def test_each_axis_kind_has_its_own_transition_table() -> None:
    # a cyclic axis drains once its last set point is sent: a splice extends it, a halt stops it from there;
    # a FIFO axis has neither move (its DRAINING ends only stopped or faulted)
    extra = {(FeederState.DRAINING, FeederInput.EXTENDED): FeederState.STREAMING,
             (FeederState.DRAINING, FeederInput.HALT): FeederState.HALTING}
    assert dict(CYCLIC_TRANSITIONS) == {**FIFO_TRANSITIONS, **extra}
    spec = CyclicAxis(SetpointSlot(5, rpdo3_id(5), 0, 32, 0, 4, (5,)), "linear")
    cf = CyclicFeeder(0, 5, 0, spec, 10, np.zeros(11), np.zeros(11))
    f = FifoFeeder(
        0, 1, 0, [], [], sync_period_ms=10, loss_confirm_syncs=1, repair_margin_ms=10, counts_per_rev=None
    )
    for inp in (FeederInput.READY, FeederInput.PRIMED, FeederInput.START, FeederInput.ACTIVE,
                FeederInput.END_QUEUED):
        f.fire(inp)
        cf.fire(inp)
    assert f.state is cf.state is FeederState.DRAINING
    with pytest.raises(InvalidTransition):
        f.fire(FeederInput.EXTENDED)
    with pytest.raises(InvalidTransition):
        f.fire(FeederInput.HALT)
    assert cf.fire(FeederInput.EXTENDED) is FeederState.STREAMING
    cf.fire(FeederInput.END_QUEUED)
    assert cf.fire(FeederInput.HALT) is FeederState.HALTING


def test_outcome_codes_are_checked() -> None:
    with pytest.raises(ValueError):
        JobOutcome(JobResult.FAILED, "NOPE", None, "", None, 0.0)
    with pytest.raises(ValueError):
        JobOutcome(JobResult.DONE, oc.PROTOCOL, None, "", None, 0.0)
    o = JobOutcome(JobResult.FAILED, oc.NODE_LOST, 3, "node 3: heartbeat lost", 7, 0.07, {"x": 1})
    assert o.to_dict()["code"] == "NODE_LOST" and o.to_dict()["detail"] == {"x": 1}


def test_report_and_progress() -> None:
    plan = make_plan(2, 1000, seed=5)
    rig = Rig(plan, StreamerSettings(counts_per_rev=dict.fromkeys(plan.node_ids, CPR)))
    progress: list[float] = []
    while rig.core.state not in TERMINAL:
        progress.append(rig.core.progress)
        rig.sync()
    progress.append(rig.core.progress)
    assert progress == sorted(progress) and progress[0] == 0.0 and progress[-1] == 1.0
    report = rig.core.report()
    assert report.state == "done" and report.outcome is not None
    assert report.start_sync == rig.core.start_sync and report.end_sync is not None
    assert report.points == sum(len(r) for r in plan.records)
    assert report.frames_sent == report.record_frames + report.control_frames
    assert report.control_frames == 2 * len(plan.node_ids)  # 0x000F at configure, 0x001F at the start
    assert rig.core.fifo_fills() == {1: 0, 2: 0}
    rig.feed(Cancel(rig.t))  # after the end: ignored
    assert rig.core.state is JobState.DONE


def test_the_core_imports_no_io_library() -> None:
    import ast
    from pathlib import Path

    import streamer.core

    forbidden = {"can", "canopen", "zenoh", "threading", "time", "socket", "asyncio", "logging"}
    core_dir = Path(streamer.core.__file__).parent
    for path in core_dir.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            for name in names:
                assert name.split(".")[0] not in forbidden, f"{path.name} imports {name}"
