"""Stateful fuzzing of the streamer core against the FIFO drive double (issue 4 s.1, issue 7 s.3).

Rules: sync, drop (the next record frame), duplicate (the next record frame), emcy, heartbeat loss,
submit (a new job once the current one ended), cancel. Invariants: nothing is sent after a job ended
(in particular after a fault); every modelled FIFO fill stays within [0, 64]; frames go only to the
job's axes; a job nobody disturbed ends DONE with every drive having executed exactly its plan.
"""

from __future__ import annotations

from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, precondition, rule
from streamer_doubles import FakeIpDriveDouble, Rig, decel_stop_planner, make_plan

from bus.cob import RPDO1_BASE, RPDO2_BASE
from bus.events import Cancel, Emcy, HeartbeatLost, Send
from streamer.core import JobResult, JobState
from streamer.core.coordinator import TERMINAL

NODES = (3, 7, 12)


class StreamerCoreMachine(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        self.drives: dict[int, FakeIpDriveDouble] = {}
        self.rig: Rig | None = None
        self.disturbed = False
        self.pending_drop = 0
        self.pending_dup = 0
        self.marks: dict[int, int] = {}
        self.jobs = 0

    # ---- jobs ----------------------------------------------------------------------------------------
    def _inject(self, send: Send) -> list[Send]:
        if send.cob_id & 0x780 == RPDO2_BASE:
            if self.pending_drop:
                self.pending_drop -= 1
                self.disturbed = True
                return []
            if self.pending_dup:
                self.pending_dup -= 1
                self.disturbed = True
                return [send, send]
        return [send]

    def _submit(self, seed: int, duration_ms: int, dense: bool, with_stop_planner: bool) -> None:
        nodes = sorted(self.drives)
        for drive in self.drives.values():
            drive.reset_for_job()  # the runtime's SDO setup between jobs
        self.marks = {n: len(d.executed) for n, d in self.drives.items()}
        plan = make_plan(
            len(nodes),
            duration_ms,
            seed=seed,
            node_ids=nodes,
            starts=[self.drives[n].demand for n in nodes],
            dt_choices=(2, 3, 5) if dense else (10, 20, 40),
        )
        self.rig = Rig(
            plan,
            drives=self.drives,
            inject=self._inject,
            stop_planner=decel_stop_planner() if with_stop_planner else None,
        )
        self.disturbed = False
        self.pending_drop = self.pending_dup = 0
        self.jobs += 1

    @initialize(
        n_axes=st.integers(1, 3),
        seed=st.integers(0, 10_000),
        duration_ms=st.integers(100, 1500),
        dense=st.booleans(),
        with_stop_planner=st.booleans(),
    )
    def setup(self, n_axes: int, seed: int, duration_ms: int, dense: bool, with_stop_planner: bool) -> None:
        self.drives = {n: FakeIpDriveDouble(n, 1000 * n) for n in NODES[:n_axes]}
        self._submit(seed, duration_ms, dense, with_stop_planner)

    @property
    def job(self) -> Rig:
        assert self.rig is not None
        return self.rig

    # ---- rules -----------------------------------------------------------------------------------------
    @rule(n=st.integers(1, 60))
    def sync(self, n: int) -> None:
        for _ in range(n):
            self.job.sync()
            self.check_fifo_bounds()

    @rule()
    def drop(self) -> None:
        self.pending_drop += 1

    @rule()
    def duplicate(self) -> None:
        self.pending_dup += 1

    # the job-ending rules act on 1 draw in 4 (`go`), so that many jobs also run to their end
    @rule(
        pick=st.integers(0, 2), code=st.sampled_from([0x8611, 0x8782, 0x8780, 0x5530]), go=st.integers(0, 3)
    )
    def emcy(self, pick: int, code: int, go: int) -> None:
        if go:
            return
        node = sorted(self.drives)[pick % len(self.drives)]
        self.disturbed = True
        self.job.feed(Emcy(node, code, 0x01, bytes(8), self.job.t))
        assert self.job.core.state in TERMINAL

    @rule(pick=st.integers(0, 2), go=st.integers(0, 3))
    def heartbeat_loss(self, pick: int, go: int) -> None:
        if go:
            return
        node = sorted(self.drives)[pick % len(self.drives)]
        self.disturbed = True
        self.job.feed(HeartbeatLost(node, self.job.t))
        assert self.job.core.state in TERMINAL

    @rule(go=st.integers(0, 3))
    def cancel(self, go: int) -> None:
        if go:
            return
        self.disturbed = True
        self.job.feed(Cancel(self.job.t))

    @precondition(lambda self: self.rig is not None and self.rig.core.state in TERMINAL)
    @rule(
        seed=st.integers(0, 10_000),
        duration_ms=st.integers(100, 1500),
        dense=st.booleans(),
        with_stop_planner=st.booleans(),
    )
    def submit(self, seed: int, duration_ms: int, dense: bool, with_stop_planner: bool) -> None:
        self._submit(seed, duration_ms, dense, with_stop_planner)

    # ---- invariants ------------------------------------------------------------------------------------
    def check_fifo_bounds(self) -> None:
        for drive in self.drives.values():
            assert 0 <= len(drive.fifo) <= 64

    @invariant()
    def nothing_sent_after_the_job_ended(self) -> None:
        if self.rig is not None:
            assert self.rig.sends_after_terminal == []

    @invariant()
    def fifo_fill_within_0_64(self) -> None:
        self.check_fifo_bounds()
        for drive in self.drives.values():
            assert drive.max_fill_seen <= 64

    @invariant()
    def frames_only_to_enabled_axes(self) -> None:
        if self.rig is None:
            return
        allowed = {base + n for n in self.rig.plan.node_ids for base in (RPDO1_BASE, RPDO2_BASE)}
        assert {s.cob_id for _, s in self.rig.sent} <= allowed

    @invariant()
    def undisturbed_jobs_stream_cleanly(self) -> None:
        if self.rig is None or self.disturbed:
            return
        core = self.rig.core
        assert core.state is not JobState.FAILED, core.outcome
        for drive in self.drives.values():
            assert drive.errors == 0 and not drive.faulted
        if core.state is JobState.DONE:
            assert core.outcome is not None and core.outcome.result is JobResult.DONE
            for axis, node in enumerate(self.rig.plan.node_ids):
                executed = self.drives[node].executed[self.marks[node] :]
                assert executed == list(self.rig.plan.records[axis][:-1])


TestStreamerCoreStateful = StreamerCoreMachine.TestCase
TestStreamerCoreStateful.settings = settings(max_examples=60, stateful_step_count=80, deadline=None)
