"""Cancel: stop trajectory spliced after what is queued, halt fallback, before start, after the end."""

from __future__ import annotations

from dataclasses import replace

import pytest
from streamer_doubles import CPR, FakeTrajectory, Rig, decel_stop_planner, make_plan

from bus.cob import RPDO2_BASE
from bus.events import Cancel, Send
from planner.encoding.record import unpack
from streamer.core import JobResult, JobState, StopRequest, StreamerSettings, StreamPlan
from streamer.core.coordinator import CW_ENABLE_OPERATION, CW_HALT, TERMINAL


def cancel_at(rig: Rig, syncs_into_motion: int) -> None:
    rig.run(until=lambda r: r.core.state is JobState.RUNNING)
    for _ in range(syncs_into_motion):
        rig.sync()
    assert rig.core.state is JobState.RUNNING
    rig.feed(Cancel(rig.t))


def test_cancel_follows_the_stop_trajectory_from_the_end_of_what_is_queued() -> None:
    plan = make_plan(3, 4000, seed=30)
    requests: list[StopRequest] = []
    planner = decel_stop_planner()

    def spy(req: StopRequest) -> FakeTrajectory:
        requests.append(req)
        return planner(req)

    rig = Rig(plan, stop_planner=spy)
    queued_before = [len(rig.record_frames(n)) for n in plan.node_ids]
    cancel_at(rig, 100)
    assert rig.core.state is JobState.CANCELLING
    (req,) = requests
    k = req.knot_index
    queued = [len(rig.record_frames(n)) for n in plan.node_ids]
    assert k == max(queued) and k > max(queued_before)
    assert req.positions_counts == tuple(plan.records[a][k - 1].position for a in range(3))
    assert req.velocities_rpm == tuple(plan.records[a][k - 1].velocity for a in range(3))
    assert req.accelerations_counts_per_ms2 is not None
    assert req.time_ms == sum(plan.segment_ms[:k])
    rig.run(2000)
    assert rig.core.state is JobState.CANCELLED
    outcome = rig.core.outcome
    assert outcome is not None and outcome.result is JobResult.CANCELLED
    assert outcome.detail["stop"] == "trajectory" and outcome.detail["knot"] == k
    stop = StreamPlan.from_trajectory(planner(req))
    assert rig.drives is not None
    for axis, node in enumerate(plan.node_ids):
        drive = rig.drives[node]
        # what was queued ran, then the stop: nothing was taken back, all axes on the stop's one grid
        assert drive.executed == list(plan.records[axis][:k]) + list(stop.records[axis][:-1])
        assert not drive.active and drive.errors == 0
        assert drive.demand == stop.records[axis][-1].position
        assert rig.record_frames(node)[-1].time_ms == 0
    assert rig.core.progress == 1.0
    assert not rig.sends_after_terminal


def test_cancel_without_stop_planner_halts_all_axes() -> None:
    plan = make_plan(3, 3000, seed=31)
    rig = Rig(plan)
    cancel_at(rig, 50)
    assert rig.core.state is JobState.HALTING
    n_records = {n: len(rig.record_frames(n)) for n in plan.node_ids}
    rig.run(500)
    assert rig.core.state is JobState.CANCELLED
    outcome = rig.core.outcome
    assert outcome is not None and outcome.detail["stop"] == "halt"
    assert "no stop planner" in outcome.detail["reason"]
    for node in plan.node_ids:
        cws = [cw for _, cw in rig.controlwords(node)]
        assert cws[-2:] == [CW_HALT, CW_ENABLE_OPERATION]  # halt, then release with ip mode off
        assert len(rig.record_frames(node)) == n_records[node]  # no record after the halt
    assert rig.drives is not None and not any(d.active for d in rig.drives.values())


REASONS = {"raises": "ruckig says no", "wrong_start": "does not start", "too_dense": "in time"}


@pytest.mark.parametrize("kind", sorted(REASONS))
def test_stop_planner_trouble_falls_back_to_halt(kind: str) -> None:
    plan = make_plan(2, 3000, seed=32)
    settings = StreamerSettings(counts_per_rev=dict.fromkeys(plan.node_ids, CPR))
    if kind == "too_dense":  # at a 100 ms SYNC a stop of 1 ms segments needs 100 records per period > 60
        settings = replace(settings, sync_period_ms=100)
        plan = make_plan(2, 6000, seed=32, dt_choices=(100, 200))

    def bad(req: StopRequest) -> FakeTrajectory:
        if kind == "raises":
            raise RuntimeError("ruckig says no")
        traj = decel_stop_planner()(req)
        if kind == "wrong_start":
            traj.positions[1][0] += 1
        else:
            n = 2000
            traj.dt_ms = [1] * n
            traj.positions = [[p[0]] * (n + 1) for p in traj.positions]
            traj.velocities_rpm = [[0] * (n + 1) for _ in traj.velocities_rpm]
        return traj

    rig = Rig(plan, settings=settings, stop_planner=bad)
    cancel_at(rig, 5)
    assert rig.core.state is JobState.HALTING
    rig.run(500)
    outcome = rig.core.outcome
    assert outcome is not None and outcome.result is JobResult.CANCELLED and outcome.detail["stop"] == "halt"
    assert REASONS[kind] in outcome.detail["reason"]


def test_cancel_before_the_start_cancels_at_once_and_sends_nothing_more() -> None:
    plan = make_plan(2, 2000, seed=33)
    rig = Rig(plan, stop_planner=decel_stop_planner())
    rig.run(until=lambda r: r.core.state is JobState.PRIMING and len(r.sent) >= 4)
    n = len(rig.sent)
    rig.feed(Cancel(rig.t))
    assert rig.core.state is JobState.CANCELLED
    for _ in range(30):
        rig.sync()
    assert len(rig.sent) == n
    assert rig.drives is not None and not any(d.activated_at for d in rig.drives.values())


def test_cancel_when_the_end_is_already_queued_lets_the_plan_finish() -> None:
    plan = make_plan(2, 600, seed=34)
    rig = Rig(plan, stop_planner=decel_stop_planner())
    rig.run(until=lambda r: r.core.state is JobState.FINISHING)
    rig.feed(Cancel(rig.t))
    rig.feed(Cancel(rig.t))  # a second cancel is ignored
    rig.run(200)
    outcome = rig.core.outcome
    assert (
        outcome is not None and outcome.result is JobResult.CANCELLED and outcome.detail["stop"] == "plan_end"
    )
    assert rig.drives is not None
    for axis, node in enumerate(plan.node_ids):
        assert rig.drives[node].executed == list(plan.records[axis][:-1])


def test_cancel_while_one_axis_repairs_a_loss_keeps_all_axes_on_one_stop() -> None:
    plan = make_plan(3, 4000, seed=35)
    dropped = [False]

    def drop_once(send: Send) -> list[Send]:
        if send.cob_id == RPDO2_BASE + 2 and not dropped[0] and unpack(send.data) == plan.records[1][60]:
            dropped[0] = True
            return []
        return [send]

    planner = decel_stop_planner()
    requests: list[StopRequest] = []

    def spy(req: StopRequest) -> FakeTrajectory:
        requests.append(req)
        return planner(req)

    rig = Rig(plan, stop_planner=spy, inject=drop_once)
    rig.run(until=lambda r: dropped[0])
    rig.sync()  # the deficit is seen; node 2 now waits while the others go on
    rig.feed(Cancel(rig.t))
    rig.run(2000)
    assert rig.core.state is JobState.CANCELLED, rig.core.outcome
    k = requests[0].knot_index
    stop = StreamPlan.from_trajectory(planner(requests[0]))
    assert rig.drives is not None
    for axis, node in enumerate(plan.node_ids):
        assert rig.drives[node].executed == list(plan.records[axis][:k]) + list(stop.records[axis][:-1])
    assert rig.core.telemetry()[1].losses_repaired == 1
    assert rig.core.state in TERMINAL


def test_cancel_between_the_start_controlword_and_the_start_sync_stops_from_the_primed_records() -> None:
    plan = make_plan(2, 3000, seed=36)
    planner = decel_stop_planner()
    requests: list[StopRequest] = []

    def spy(req: StopRequest) -> FakeTrajectory:
        requests.append(req)
        return planner(req)

    rig = Rig(plan, stop_planner=spy)
    rig.run(until=lambda r: r.core.state is JobState.STARTING)
    rig.feed(Cancel(rig.t))
    rig.run(1000)
    assert rig.core.state is JobState.CANCELLED, rig.core.outcome
    k = requests[0].knot_index
    assert k == rig.core.priming_level
    stop = StreamPlan.from_trajectory(planner(requests[0]))
    assert rig.drives is not None
    for axis, node in enumerate(plan.node_ids):
        assert rig.drives[node].executed == list(plan.records[axis][:k]) + list(stop.records[axis][:-1])
