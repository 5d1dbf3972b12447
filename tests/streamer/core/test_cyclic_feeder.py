"""The coordinator's cyclic feeder: one set point per SYNC (XtrapulsPac IP, CSP), alone and next to EPOS FIFOs.

`CyclicDriveDouble` is a TEST DOUBLE of one set-point-per-SYNC drive, reduced to what the streamer's
contract with such a drive is (streamer/core/cyclic_feeder.py, planner/encoding/cyclic.py): at each SYNC the demand
reaches the set point latched at the previous SYNC, the controlword (RPDO1 type 1) applies, a drive with
ip mode active that got no set point since the last SYNC faults (EMCY 0x8782, XtrapulsPac error 50; a CSP
drive, which follows its target without bit 4, holds the last one), the
new set point is latched, then TPDO1 (statusword) and TPDO2 (actual = demand) answer. The product's
simulated drives (bus/sim/xtrapuls.py, csp.py) are tested against the seed in tests/bus.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest
from streamer_doubles import CPR, FakeIpDriveDouble, FakeTrajectory, Rig, decel_stop_planner, make_plan, make_trajectory

from bus import cob
from bus.events import Cancel, Emcy, PositionFeedback, Send, StatusWord, Sync
from bus.profile import SetpointSlot
from streamer.core import JobResult, JobState, StopRequest, StreamerSettings, StreamPlan
from streamer.core import outcome as oc
from streamer.core.coordinator import CW_ENABLE_OPERATION, CW_QUICK_STOP, CW_START_IP
from streamer.core.cyclic_feeder import CyclicAxis


class CyclicDriveDouble:
    """TEST DOUBLE: one drive fed one set point per SYNC (see the module docstring)."""

    def __init__(self, node: int, start: int, slot: SetpointSlot, *, bit4: bool = True,
                 lock_after_syncs: int = 0) -> None:
        self.node = node
        self.slot = slot
        self.bit4 = bit4
        self.lock_after = lock_after_syncs
        self.demand = self.target = self.last_sp = start
        self.cw = 0x000F
        self.cw_pending: int | None = None
        self.pending: int | None = None
        self.active = not bit4
        self.op_enabled = True
        self.faulted = False
        self.syncs = 0
        self.latched: list[tuple[int, int]] = []  # (SYNC, set point latched there)
        self.demands: dict[int, int] = {}  # SYNC -> demand there
        self.activated_at: list[int] = []
        self.emcys: list[Emcy] = []
        self.frames: list[tuple[int, bytes]] = []

    def receive(self, cob_id: int, data: bytes, t: float) -> list[Emcy]:
        self.frames.append((cob_id, data))
        if cob_id == cob.rpdo1_id(self.node):
            self.cw_pending = int.from_bytes(data, "little")
            return []
        assert cob_id == self.slot.cob_id and len(data) == self.slot.frame_bytes
        o = self.slot.offset
        if self.slot.position_bits == 32:
            value = int.from_bytes(data[o:o + 4], "little", signed=True)
        else:  # rebuild the upper word nearest the previous set point
            low = int.from_bytes(data[o:o + 2], "little")
            value = self.last_sp + ((low - self.last_sp + 0x8000) & 0xFFFF) - 0x8000
        self.pending = self.last_sp = value
        return []

    def on_sync(self, m: int, t: float) -> list[object]:
        self.syncs += 1
        out: list[object] = []
        if self.active and not self.faulted:
            self.demand = self.target
        if self.cw_pending is not None:
            cw, self.cw_pending = self.cw_pending, None
            self.cw = cw
            if cw & 0x0004 == 0 and cw & 0x0002:  # quick stop
                self.op_enabled = False
                self.active = False
            elif self.bit4 and not cw & 0x0010:
                self.active = False
        # bit 4 high: ip mode active once the drive's SYNC lock is there (the XtrapulsPac's 180 ms)
        if self.bit4 and self.cw & 0x0010 and self.op_enabled and not self.faulted and self.syncs > self.lock_after:
            self.active = True
        if self.active and self.bit4 and not self.activated_at:
            self.activated_at.append(m)
        if self.active and self.bit4 and not self.faulted and self.pending is None:  # a CSP drive holds
            self.faulted = True
            self.active = False
            ev = Emcy(self.node, 0x8782, 0x01, bytes(5), t)
            self.emcys.append(ev)
            out.append(ev)
        if self.pending is not None and not self.faulted:
            self.target = self.pending
            self.latched.append((m, self.pending))
        self.pending = None
        self.demands[m] = self.demand
        out.append(StatusWord(self.node, self.statusword(), t, sync_count=m))
        out.append(PositionFeedback(self.node, self.demand, self.demand, t, sync_count=m))
        return out

    def statusword(self) -> int:
        if self.faulted:
            return 0x0008
        if not self.op_enabled:
            return 0x0040  # switch on disabled after the quick stop ramp
        return 0x0027 | (0x1000 if self.active else 0)


def slot(node: int, *, members: tuple[int, ...] | None = None, pv: bool = False) -> SetpointSlot:
    if members is None:
        return SetpointSlot(node, cob.rpdo3_id(node), 0, 32, 32 if pv else 0, 8 if pv else 4, (node,))
    k = members.index(node)
    return SetpointSlot(node, cob.rpdo3_id(members[0]), 2 * k, 16, 0, 2 * len(members), members)


@dataclass
class CyclicRig(Rig):
    """`Rig` with some axes fed one set point per SYNC (`cyclic`: node -> its CyclicAxis)."""

    cyclic: dict[int, CyclicAxis] = field(default_factory=dict)
    lock_after: int = 0
    # set points and bit 4 sent in reaction to anything but a SYNC (a TPDO can come at any time in the cycle,
    # a set point must precede its SYNC by 100 us: seed 003, error 50)
    off_sync: list[Send] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.settings is None:
            self.settings = StreamerSettings(counts_per_rev=dict.fromkeys(self.plan.node_ids, CPR), cyclic=self.cyclic)
        s = self.settings
        self.drives = {}
        for i, node in enumerate(self.plan.node_ids):
            start = self.plan.start_positions[i]
            if node in s.cyclic:
                c = s.cyclic[node]
                self.drives[node] = CyclicDriveDouble(node, start, c.slot, bit4=c.starts_with_bit4,  # type: ignore[assignment]
                                                      lock_after_syncs=self.lock_after)
            else:
                self.drives[node] = FakeIpDriveDouble(node, start, period_ms=s.sync_period_ms,
                                                      underflow_wm=s.underflow_watermark,
                                                      overflow_wm=s.overflow_watermark)
        super().__post_init__()

    def deliver(self, frame: Send) -> None:
        assert self.drives is not None and self.settings is not None
        targets = [n for n, c in self.settings.cyclic.items() if c.slot.cob_id == frame.cob_id]
        if not targets:
            targets = [frame.cob_id & 0x7F]
        for node in targets:
            for emcy in self.drives[node].receive(frame.cob_id, frame.data, self.t):
                self.feed(emcy)

    def feed(self, event: object) -> None:
        before = len(self.sent)
        super().feed(event)
        if not isinstance(event, Sync):
            slots = {c.slot.cob_id for c in self.cyclic.values()}
            self.off_sync.extend(s for _, s in self.sent[before:] if s.cob_id in slots
                                 or (s.cob_id == cob.rpdo1_id(s.cob_id & 0x7F) and s.data[0] & 0x10))

    def setpoint_frames(self, cob_id: int) -> list[tuple[int, bytes]]:
        return [(m, s.data) for m, s in self.sent if s.cob_id == cob_id]


def cyc(drive: object) -> CyclicDriveDouble:
    assert isinstance(drive, CyclicDriveDouble)
    return drive


def test_a_cyclic_job_sends_one_set_point_per_sync_a_period_ahead_and_ends_with_ip_mode_off() -> None:
    plan = make_plan(3, 3000, seed=4)
    nodes = plan.node_ids
    rig = CyclicRig(plan, cyclic={nodes[0]: CyclicAxis(slot(nodes[0], members=nodes[:2]), "p3"),
                                  nodes[1]: CyclicAxis(slot(nodes[1], members=nodes[:2]), "p3"),
                                  nodes[2]: CyclicAxis(slot(nodes[2]), "linear")})
    assert rig.run(2000) is JobState.DONE, rig.core.outcome
    s = rig.core.start_sync
    assert s is not None
    for node in nodes:
        d = cyc(rig.drives[node])  # type: ignore[index]
        sp = rig.core.setpoints(node)
        assert sp is not None and d.emcys == []
        x = [int(v) for v in sp.positions]
        # the drive was ip-active on the hold before the start, and every SYNC from then had a set point
        assert d.activated_at and d.activated_at[0] < s
        latched = dict(d.latched)
        assert all(latched[m] == x[0] for m in range(d.activated_at[0], s))
        # set point j latched at SYNC S + j - 1 and reached at S + j: the demand at S + j is x_j
        for j in range(1, len(x)):
            assert latched[s + j - 1] == x[j]
            assert d.demands[s + j] == x[j]
        assert d.demand == x[-1] == plan.records[nodes.index(node)][-1].position
        assert d.cw & 0x0010 == 0 and not d.active  # ip mode off at the end
    # the two axes of the multiplexed group travel in one frame per SYNC, 16 bits each
    frames = rig.setpoint_frames(cob.rpdo3_id(nodes[0]))
    per_sync: dict[int, int] = {}
    for m, data in frames:
        assert len(data) == 4
        per_sync[m] = per_sync.get(m, 0) + 1
    assert max(per_sync.values()) == 1
    assert rig.off_sync == []  # also at READY: set points and bit 4 go out in a SYNC's reaction only
    report = rig.core.report()
    assert report.outcome is not None and report.outcome.result is JobResult.DONE


def test_epos_and_cyclic_axes_start_on_the_same_sync_and_follow_one_timeline() -> None:
    plan = make_plan(4, 2500, seed=11, dt_choices=(10, 20))
    nodes = plan.node_ids
    rig = CyclicRig(plan, cyclic={nodes[2]: CyclicAxis(slot(nodes[2], pv=True), "pv"),
                                  nodes[3]: CyclicAxis(slot(nodes[3]), "linear", starts_with_bit4=False)})
    assert rig.run(2000) is JobState.DONE, rig.core.outcome
    s = rig.core.start_sync
    assert s is not None
    epos = rig.drives[nodes[0]]  # type: ignore[index]
    assert isinstance(epos, FakeIpDriveDouble) and epos.activated_at == [s]
    for node in nodes[2:]:
        d = cyc(rig.drives[node])  # type: ignore[index]
        latched = dict(d.latched)
        sp = rig.core.setpoints(node)
        assert sp is not None
        # set point 1 (the plan at one period) is latched at S, when the EPOS drives start interpolating,
        # after holds of the start, and set point j at S + j - 1
        assert latched[s - 1] == sp.positions[0] and latched[s] == sp.positions[1]
        assert all(latched[s + j - 1] == sp.positions[j] for j in range(1, sp.n + 1))
    # the same plan, two families: at every SYNC their demands agree with the plan there (cyclic: the set
    # point is the plan at jP rounded; EPOS: the Hermite through the same knots), on every grid knot
    ends = [sum(plan.segment_ms[:k + 1]) for k in range(len(plan.segment_ms))]
    for node in nodes[2:]:
        a = nodes.index(node)
        d = cyc(rig.drives[node])  # type: ignore[index]
        for k, t in enumerate(ends):
            if t % 10 == 0:
                assert d.demands[s + t // 10] == plan.records[a][k].position


def test_cancel_of_a_cyclic_job_acts_with_the_next_set_point() -> None:
    plan = make_plan(2, 4000, seed=7)
    nodes = plan.node_ids
    requests: list[StopRequest] = []
    stopper = decel_stop_planner(decel_counts_per_ms2=0.5)

    def spy(req: StopRequest) -> FakeTrajectory:
        requests.append(req)
        return stopper(req)

    rig = CyclicRig(plan, stop_planner=spy, cyclic={n: CyclicAxis(slot(n), "linear") for n in nodes})
    rig.run(until=lambda r: r.core.state is JobState.RUNNING)
    for _ in range(100):
        rig.sync()
    before = {n: rig.core.setpoints(n).positions.copy() for n in nodes}  # type: ignore[union-attr]
    m = rig.count - 1  # the last SYNC fed: the set point for m + 1 is out already
    s = rig.core.start_sync
    assert s is not None
    rig.feed(Cancel(rig.t))
    assert rig.core.state is JobState.CANCELLING
    (req,) = requests
    sent = m + 2 - s  # index of the last set point sent
    assert req.time_ms == sent * 10
    for node in nodes:
        after = rig.core.setpoints(node)
        assert after is not None
        # everything sent stays; the next set point (after the next SYNC) is the stop's first
        assert list(after.positions[:sent + 1]) == list(before[node][:sent + 1])
        assert after.positions[sent + 1] != before[node][sent + 1]
    assert rig.run(2000) is JobState.CANCELLED
    for node in nodes:
        d = cyc(rig.drives[node])  # type: ignore[index]
        assert d.emcys == [] and not d.active
        stop = StreamPlan.from_trajectory(stopper(req))
        assert d.demand == stop.records[nodes.index(node)][-1].position


def test_cancel_in_a_mixed_cell_starts_the_stop_at_the_end_of_the_epos_queue() -> None:
    plan = make_plan(3, 4000, seed=8)
    nodes = plan.node_ids
    requests: list[StopRequest] = []
    stopper = decel_stop_planner()

    def spy(req: StopRequest) -> FakeTrajectory:
        requests.append(req)
        return stopper(req)

    rig = CyclicRig(plan, stop_planner=spy, cyclic={nodes[2]: CyclicAxis(slot(nodes[2]), "p3")})
    rig.run(until=lambda r: r.core.state is JobState.RUNNING)
    for _ in range(80):
        rig.sync()
    rig.feed(Cancel(rig.t))
    (req,) = requests
    k = req.knot_index
    t0 = sum(plan.segment_ms[:k])
    assert req.time_ms == t0 and k > 0
    assert req.positions_counts[:2] == tuple(plan.records[a][k - 1].position for a in range(2))
    assert rig.run(3000) is JobState.CANCELLED
    d = cyc(rig.drives[nodes[2]])  # type: ignore[index]
    stop = StreamPlan.from_trajectory(stopper(req))
    assert d.emcys == [] and d.demand == stop.records[2][-1].position


def test_a_16_bit_step_too_large_is_refused_before_anything_is_sent() -> None:
    traj = make_trajectory(2, 400, seed=1, dt_choices=(10,))
    traj.positions[1] = [p * 200 for p in traj.positions[1]]  # a big, fast move on the grouped axis
    traj.velocities_rpm[1] = [v * 200 for v in traj.velocities_rpm[1]]
    plan = StreamPlan.from_trajectory(traj)  # type: ignore[arg-type]
    nodes = plan.node_ids
    rig = CyclicRig(plan, cyclic={n: CyclicAxis(slot(n, members=nodes), "linear") for n in nodes})
    assert rig.core.state is JobState.FAILED
    out = rig.core.outcome
    assert out is not None and out.code == oc.SETPOINT_RANGE and out.node == nodes[1]
    assert "32767" in out.message and rig.sent == []


def test_a_job_must_include_every_axis_of_a_multiplexed_group() -> None:
    plan = make_plan(1, 400, seed=2, node_ids=[5])
    rig = CyclicRig(plan, cyclic={5: CyclicAxis(slot(5, members=(5, 6)), "linear")})
    out = rig.core.outcome
    assert out is not None and out.code == oc.SETPOINT_RANGE and "[6]" in out.message


def test_a_missed_set_point_fails_setpoint_late_and_quick_stops_every_axis() -> None:
    plan = make_plan(3, 3000, seed=5)
    nodes = plan.node_ids
    dropped: list[Send] = []

    def drop_one(send: Send) -> list[Send]:
        if send.cob_id == cob.rpdo3_id(nodes[1]) and rig.core.state is JobState.RUNNING and not dropped:
            dropped.append(send)
            return []
        return [send]

    rig = CyclicRig(plan, cyclic={n: CyclicAxis(slot(n), "pv" if n != nodes[0] else "linear")
                                  for n in nodes[1:]}, inject=drop_one)
    assert rig.run(2000) is JobState.FAILED
    out = rig.core.outcome
    assert out is not None and out.code == oc.SETPOINT_LATE and out.node == nodes[1]
    for node in nodes:
        assert (rig.count - 1, CW_QUICK_STOP) in rig.controlwords(node) or any(
            cw == CW_QUICK_STOP for _, cw in rig.controlwords(node))


def test_a_drive_that_never_activates_fails_start_failed() -> None:
    plan = make_plan(1, 400, seed=3)
    node = plan.node_ids[0]
    settings = StreamerSettings(counts_per_rev={node: CPR}, cyclic={node: CyclicAxis(slot(node), "linear")},
                                activate_timeout_ms=300)
    rig = CyclicRig(plan, settings=settings, lock_after=10_000)
    assert rig.run(200) is JobState.FAILED
    out = rig.core.outcome
    assert out is not None and out.code == oc.START_FAILED and "SYNC had run" in out.message
    assert (CW_START_IP in [cw for _, cw in rig.controlwords(node)])


def test_bit4_waits_until_sync_has_run_as_long_as_the_drive_needs() -> None:
    """An XtrapulsPac refuses bit 4 before 180 ms of SYNC (seed 003): the core sends it only once SYNC has run
    that long at the SYNC before the one that applies it, counted from its own first Sync when the runtime
    does not say when the run began."""
    plan = make_plan(1, 400, seed=3)
    node = plan.node_ids[0]
    rig = CyclicRig(plan, cyclic={node: CyclicAxis(slot(node), "linear", True, 180)})
    assert rig.run(400) is JobState.DONE, rig.core.outcome
    first_bit4 = next(m for m, cw in rig.controlwords(node) if cw == CW_START_IP)
    assert first_bit4 == 180 // rig.period_ms  # SYNC 18 (t = 180 ms): applied at SYNC 19, 190 ms into the run
    # bit 4 once, and set points (holds) from the configuration on, long before it
    assert [cw for _, cw in rig.controlwords(node)].count(CW_START_IP) == 1
    assert rig.setpoint_frames(slot(node).cob_id)[0][0] < first_bit4


@dataclass
class RunningSyncRig(CyclicRig):
    """The runtime's SYNC has run since `since` (before the job): every Sync says so."""

    since: float = -1.0

    def feed(self, event: object) -> None:
        if isinstance(event, Sync):
            event = Sync(event.count, event.t, event.counter, since=self.since)
        super().feed(event)


def test_bit4_goes_out_with_the_first_sync_when_the_runtime_says_sync_ran_long_enough() -> None:
    plan = make_plan(1, 400, seed=3)
    node = plan.node_ids[0]
    rig = RunningSyncRig(plan, cyclic={node: CyclicAxis(slot(node), "linear", True, 180)}, since=-0.2)
    assert rig.run(400) is JobState.DONE, rig.core.outcome
    # the start checks pass on the answers to SYNC 0; bit 4 goes in SYNC 1's reaction, with its set point
    assert next(m for m, cw in rig.controlwords(node) if cw == CW_START_IP) == 1
    late = RunningSyncRig(plan, cyclic={node: CyclicAxis(slot(node), "linear", True, 180)}, since=-0.1)
    assert late.run(400) is JobState.DONE, late.core.outcome
    assert next(m for m, cw in late.controlwords(node) if cw == CW_START_IP) == 8  # 100 ms before + 80 ms


def test_a_slow_lock_delays_the_start_but_not_the_alignment() -> None:
    plan = make_plan(2, 1500, seed=9)
    nodes = plan.node_ids
    rig = CyclicRig(plan, cyclic={nodes[1]: CyclicAxis(slot(nodes[1]), "p3")}, lock_after=20)
    assert rig.run(2000) is JobState.DONE, rig.core.outcome
    d = cyc(rig.drives[nodes[1]])  # type: ignore[index]
    s = rig.core.start_sync
    assert s is not None and d.activated_at[0] >= 20 and s >= d.activated_at[0] + 2


def test_cancel_before_the_start_switches_ip_mode_off_with_a_last_hold() -> None:
    plan = make_plan(2, 1500, seed=9)
    nodes = plan.node_ids
    rig = CyclicRig(plan, cyclic={nodes[1]: CyclicAxis(slot(nodes[1]), "p3")}, lock_after=3)
    rig.run(until=lambda r: r.core.state is JobState.PRIMING)
    for _ in range(6):
        rig.sync()
    d = cyc(rig.drives[nodes[1]])  # type: ignore[index]
    assert rig.core.state is JobState.PRIMING and d.active  # the EPOS FIFO is still priming
    sent = len(rig.sent)
    rig.feed(Cancel(rig.t))
    # the cancel comes at any time in the cycle: the last hold and bit 4 off go out right after the next SYNC
    assert rig.core.state is JobState.PRIMING and len(rig.sent) == sent
    rig.sync()
    assert rig.core.state is JobState.CANCELLED
    assert rig.core.report().cancel["stop"] == "before_start"
    rig.sync()
    assert not d.active and d.emcys == [] and d.cw == CW_ENABLE_OPERATION
    assert rig.off_sync == []


def test_the_budget_counts_the_set_point_frames() -> None:
    plan = make_plan(30, 400, seed=1, dt_choices=(10,))
    nodes = plan.node_ids
    # 30 axes of PV set points (8 bytes) + their feedback at 1 ms SYNC: far over 70 % of 1 Mbit/s
    settings = StreamerSettings(sync_period_ms=1, counts_per_rev=dict.fromkeys(nodes, CPR),
                                cyclic={n: CyclicAxis(slot(n, pv=True), "pv") for n in nodes})
    rig = CyclicRig(plan, settings=settings)
    out = rig.core.outcome
    assert out is not None and out.code == oc.BUS_OVERLOAD and rig.sent == []


@pytest.mark.parametrize("interp", ["linear", "pv", "p3"])
def test_set_points_are_the_plan_at_each_sync_rounded(interp: str) -> None:
    plan = make_plan(1, 2000, seed=21, dt_choices=(10, 20, 30))
    node = plan.node_ids[0]
    rig = CyclicRig(plan, cyclic={node: CyclicAxis(slot(node, pv=interp == "pv"), interp)})
    sp = rig.core.setpoints(node)
    assert sp is not None
    t = 0
    for rec in plan.records[0][:-1]:
        t += rec.time_ms
        if t % 10 == 0:
            assert sp.positions[t // 10] == rec.position  # the plan's knots are hit to the count
    assert sp.positions[-1] == plan.records[0][-1].position and sp.velocities[-1] == 0
    if interp != "pv":
        assert not sp.velocities.any()
