"""Test doubles for the streamer core tests (NOT the product's simulated drive: bus/sim replaces these in
the lead's integration tests).

- `FakeIpDriveDouble`: a TEST DOUBLE of one drive's IP FIFO, following the semantics of
  /work/briefs/common.md exactly: 64-entry FIFO whose head is the current segment target and is
  popped when its segment completes; activation on a controlword bit 4 rising edge applied at the next
  SYNC, needing fill >= 2; underflow error when a segment completes with nothing behind it; a time-0
  head ends interpolation without error; overflow error when a record arrives at 64; warnings against
  the watermarks; on each SYNC: ticks of the period that ended, then the controlword, then TPDO1 and
  TPDO2. Position demand from planner.encoding.hermite, the same module the product uses.
- plan builders (`make_plan`, `FakeTrajectory`), a simple stop planner (`decel_stop_planner`), and
  `Rig`, which runs a Coordinator against the doubles in virtual time with fault injection hooks.
"""

from __future__ import annotations

import random
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from bus.cob import RPDO1_BASE, RPDO2_BASE, classify, unpack_controlword
from bus.events import (
    BufferStatus,
    Emcy,
    PositionFeedback,
    RecordOnWire,
    Send,
    Sync,
)
from planner.encoding.hermite import coefficients, evaluate, round_counts, rpm_to_counts_per_ms
from planner.encoding.record import PvtRecord, unpack
from streamer.core import Coordinator, JobState, StateChange, StopRequest, StreamerSettings, StreamPlan
from streamer.core.coordinator import TERMINAL

CPR = 8192


class FakeIpDriveDouble:
    """TEST DOUBLE: one EPOS-like drive's interpolated position FIFO (see module docstring)."""

    def __init__(
        self,
        node: int,
        start_position: int,
        *,
        cpr: int = CPR,
        period_ms: int = 10,
        underflow_wm: int = 4,
        overflow_wm: int = 60,
        fifo_size: int = 64,
    ) -> None:
        self.node = node
        self.cpr = cpr
        self.period_ms = period_ms
        self.underflow_wm = underflow_wm
        self.overflow_wm = overflow_wm
        self.fifo_size = fifo_size
        self.fifo: deque[PvtRecord] = deque()
        self.demand = start_position
        self.cw = 0x000F
        self.cw_pending: int | None = None
        self.reset_for_job()
        self.activated_at: list[int] = []
        self.executed: list[PvtRecord] = []
        self.received: list[PvtRecord] = []
        self.controlwords: list[int] = []
        self.max_fill_seen = 0
        self.fill_log: list[tuple[int, int, int]] = []  # (sync, fill reported at it, records executed)

    def reset_for_job(self) -> None:
        """What the runtime's SDO setup does between jobs: fault reset, enable, clear + enable the buffer."""
        self.fifo.clear()
        self.active = False
        self.op_enabled = True
        self.faulted = False
        self.halted = False
        self.halt_syncs_left = 0
        self.errors = 0
        self.cw = 0x000F
        self.cw_pending = None
        self.prev_p = self.demand
        self.prev_v = 0.0
        self.seg_tick = 0
        self._coeffs: tuple[float, float, float, float] | None = None
        self.emcys: list[Emcy] = []

    # ---- reception ---------------------------------------------------------------------------------
    def receive(self, cob_id: int, data: bytes, t: float) -> list[Emcy]:
        kind = classify(cob_id)
        assert kind.node == self.node
        if kind.kind == "RPDO1":
            self.cw_pending = unpack_controlword(data)
            self.controlwords.append(self.cw_pending)
            return []
        assert kind.kind == "RPDO2", kind
        rec = unpack(data)
        self.received.append(rec)
        if self.faulted:
            return []
        if len(self.fifo) >= self.fifo_size:
            return self._fault(0x0200, t)
        self.fifo.append(rec)
        self.max_fill_seen = max(self.max_fill_seen, len(self.fifo))
        return []

    def _fault(self, error_bit: int, t: float) -> list[Emcy]:
        self.errors |= error_bit
        self.faulted = True
        self.active = False
        bs = self.buffer_status()
        ev = Emcy(self.node, 0x8782, 0x01, bytes(3) + bs.to_bytes(2, "little") + bytes(3), t)
        self.emcys.append(ev)
        return [ev]

    # ---- SYNC ----------------------------------------------------------------------------------------
    def on_sync(self, count: int, t: float) -> list[BufferStatus | PositionFeedback | Emcy]:
        out: list[BufferStatus | PositionFeedback | Emcy] = []
        if self.halted and self.halt_syncs_left:
            self.halt_syncs_left -= 1
            self.demand += 7
        if self.active and not self.faulted:
            for _ in range(self.period_ms):
                if not self._tick(t, out):
                    break
        if self.cw_pending is not None:
            out.extend(self._apply_controlword(self.cw_pending, count, t))
            self.cw_pending = None
        fill = len(self.fifo)
        self.fill_log.append((count, fill, len(self.executed)))
        out.append(
            BufferStatus(
                self.node, self.statusword(), self.buffer_status(), self.fifo_size - fill, t, sync_count=count
            )
        )
        out.append(PositionFeedback(self.node, self.demand, self.demand, t, sync_count=count))
        return out

    def _tick(self, t: float, out: list[BufferStatus | PositionFeedback | Emcy]) -> bool:
        head = self.fifo[0]
        self.seg_tick += 1
        if self.seg_tick >= head.time_ms:
            self.demand = head.position
            self.prev_p = head.position
            self.prev_v = rpm_to_counts_per_ms(head.velocity, self.cpr)
            self.fifo.popleft()
            self.executed.append(head)
            self.seg_tick = 0
            self._coeffs = None
            if not self.fifo:
                out.extend(self._fault(0x0100, t))
                return False
            if self.fifo[0].time_ms == 0:
                self.fifo.popleft()
                self.active = False
                return False
            return True
        if self._coeffs is None:
            self._coeffs = coefficients(
                self.prev_p,
                self.prev_v,
                head.position,
                rpm_to_counts_per_ms(head.velocity, self.cpr),
                head.time_ms,
            )
        self.demand = round_counts(evaluate(self._coeffs, self.seg_tick - head.time_ms)[0])
        return True

    def _apply_controlword(self, cw: int, count: int, t: float) -> list[Emcy]:
        prev = self.cw
        self.cw = cw
        if self.faulted:
            return []
        if cw & 0x0007 == 0x0003 and not cw & 0x0004:  # quick stop (0x000B / 0x0003)
            self.active = False
            self.op_enabled = False
            return []
        if cw & 0x000F != 0x000F or not self.op_enabled:
            return []
        if cw & 0x0100:  # halt: this double creeps on for a few SYNCs (node-dependent), then stands
            self.halted = True
            self.active = False
            self.halt_syncs_left = 2 + self.node % 3
            return []
        self.halted = False
        if cw & 0x0010 and not prev & 0x0010:
            if len(self.fifo) < 2:
                return self._fault(0x0100, t)
            self.active = True
            self.activated_at.append(count)
            self.seg_tick = 0
            self.prev_p = self.demand
            self.prev_v = 0.0
            self._coeffs = None
        elif not cw & 0x0010:
            self.active = False
        return []

    # ---- registers -----------------------------------------------------------------------------------
    def statusword(self) -> int:
        if self.faulted:
            return 0x0008
        if not self.op_enabled:
            return 0x0007  # quick stop active
        sw = 0x0027
        if self.active:
            sw |= 0x1000
        elif not (self.halted and self.halt_syncs_left):
            sw |= 0x0400  # at rest: target reached (or, under halt, velocity 0)
        return sw

    def buffer_status(self) -> int:
        fill = len(self.fifo)
        bs = 0x4000 | self.errors
        if self.active:
            bs |= 0x8000
        if fill < self.underflow_wm:
            bs |= 0x0001
        if fill > self.overflow_wm:
            bs |= 0x0002
        return bs


# ---- plans -------------------------------------------------------------------------------------------
@dataclass
class FakeTrajectory:
    """A trajectory-like object (satisfies streamer.core.PvtTrajectoryLike)."""

    node_ids: tuple[int, ...]
    dt_ms: list[int]
    positions: list[list[int]]  # [axis][knot]
    velocities_rpm: list[list[int]]

    @property
    def n_axes(self) -> int:
        return len(self.node_ids)

    def records(self, axis: int) -> list[PvtRecord]:
        p, v = self.positions[axis], self.velocities_rpm[axis]
        out = [PvtRecord(p[k + 1], v[k + 1], self.dt_ms[k]) for k in range(len(self.dt_ms))]
        out.append(PvtRecord(p[-1], 0, 0))
        return out


def make_trajectory(
    n_axes: int,
    duration_ms: int,
    *,
    dt_choices: Sequence[int] = (10, 20, 30, 40),
    seed: int = 0,
    node_ids: Sequence[int] | None = None,
    starts: Sequence[int] | None = None,
    cpr: int = CPR,
) -> FakeTrajectory:
    """Rest-to-rest minimum-jerk moves of random amplitude on a random shared grid."""
    rng = random.Random(seed)
    grid: list[int] = []
    while sum(grid) < duration_ms:
        grid.append(rng.choice(list(dt_choices)))
    total = sum(grid)
    nodes = tuple(node_ids) if node_ids is not None else tuple(range(1, n_axes + 1))
    positions: list[list[int]] = []
    velocities: list[list[int]] = []
    for axis in range(n_axes):
        p0 = starts[axis] if starts is not None else rng.randint(-100_000, 100_000)
        amp = rng.choice([-1, 1]) * rng.randint(20_000, 400_000)
        ps, vs = [p0], [0]
        t = 0
        for dt in grid:
            t += dt
            u = t / total
            s = 10 * u**3 - 15 * u**4 + 6 * u**5
            ds = (30 * u**2 - 60 * u**3 + 30 * u**4) / total  # per ms
            ps.append(p0 + round(amp * s))
            vs.append(round(amp * ds * 60_000 / cpr))
        vs[-1] = 0
        ps[-1] = p0 + amp
        positions.append(ps)
        velocities.append(vs)
    return FakeTrajectory(nodes, grid, positions, velocities)


def make_plan(n_axes: int, duration_ms: int, **kw: object) -> StreamPlan:
    return StreamPlan.from_trajectory(make_trajectory(n_axes, duration_ms, **kw))  # type: ignore[arg-type]


def decel_stop_planner(
    decel_counts_per_ms2: float = 2.0, dt_ms: int = 10, cpr: int = CPR
) -> Callable[[StopRequest], FakeTrajectory]:
    """A simple (not jerk-limited) stop: constant deceleration of every axis to rest, all on one grid."""

    def plan(req: StopRequest) -> FakeTrajectory:
        v0 = [rpm_to_counts_per_ms(v, cpr) for v in req.velocities_rpm]
        t_stop = max([abs(v) / decel_counts_per_ms2 for v in v0] + [float(dt_ms)])
        n_seg = max(1, -(-int(t_stop) // dt_ms))
        t_stop = float(n_seg * dt_ms)
        positions, velocities = [], []
        for p, v in zip(req.positions_counts, v0, strict=True):
            ps, vs = [p], [0]
            for k in range(1, n_seg + 1):
                t = k * dt_ms
                ps.append(p + round(v * t - v * t * t / (2 * t_stop)))
                vs.append(round(v * (1 - t / t_stop) * 60_000 / cpr))
            vs[-1] = 0
            positions.append(ps)
            velocities.append(vs)
        return FakeTrajectory(req.node_ids, [dt_ms] * n_seg, positions, velocities)

    return plan


# ---- the rig -----------------------------------------------------------------------------------------
Injector = Callable[[Send], list[Send]]


@dataclass
class Rig:
    """A Coordinator against FakeIpDriveDouble drives in virtual time.

    `inject(send) -> frames actually delivered` (drop: [], duplicate: [s, s]); `tpdo_filter(event) -> bool`
    drops TPDOs; `delayed` frames are delivered right after the next SYNC's TPDOs.
    """

    plan: StreamPlan
    settings: StreamerSettings | None = None
    stop_planner: Callable[[StopRequest], FakeTrajectory] | None = None
    drives: dict[int, FakeIpDriveDouble] | None = None
    inject: Injector | None = None
    tpdo_filter: Callable[[object], bool] | None = None
    core: Coordinator = field(init=False)
    count: int = 0
    sent: list[tuple[int, Send]] = field(default_factory=list)
    changes: list[StateChange] = field(default_factory=list)
    sends_after_terminal: list[Send] = field(default_factory=list)
    delayed: list[Send] = field(default_factory=list)
    # feed every record frame back as it reaches the drive (`RecordOnWire`, after the newest SYNC: the rig's
    # count), as the real-time runtime does (settings.records_echoed)
    echo: bool = False

    def __post_init__(self) -> None:
        if self.settings is None:
            self.settings = StreamerSettings(counts_per_rev=dict.fromkeys(self.plan.node_ids, CPR))
        s = self.settings
        if self.drives is None:
            self.drives = {
                node: FakeIpDriveDouble(
                    node,
                    self.plan.start_positions[i],
                    period_ms=s.sync_period_ms,
                    underflow_wm=s.underflow_watermark,
                    overflow_wm=s.overflow_watermark,
                )
                for i, node in enumerate(self.plan.node_ids)
            }
        self.core = Coordinator(self.plan, s, self.stop_planner)

    @property
    def period_ms(self) -> int:
        assert self.settings is not None
        return self.settings.sync_period_ms

    @property
    def t(self) -> float:
        return self.count * self.period_ms / 1000.0

    def feed(self, event: object) -> None:
        terminal_before = self.core.state in TERMINAL
        reaction = self.core.handle(event)
        self.changes.extend(reaction.changes)
        if terminal_before:
            self.sends_after_terminal.extend(reaction.sends)
        for send in reaction.sends:
            self.sent.append((self.count, send))
            frames = self.inject(send) if self.inject is not None else [send]
            for frame in frames:
                self.deliver(frame)

    def deliver(self, frame: Send) -> None:
        assert self.drives is not None
        node = frame.cob_id & 0x7F
        drive = self.drives.get(node)
        assert drive is not None, f"frame to unknown node {node}"
        for emcy in drive.receive(frame.cob_id, frame.data, self.t):
            self.feed(emcy)
        if self.echo and frame.cob_id & 0x780 == RPDO2_BASE:
            self.feed(RecordOnWire(node, self.t, self.count))

    def sync(self) -> None:
        assert self.drives is not None
        m = self.count
        late, self.delayed = self.delayed, []  # frames held back in the last cycle arrive after this SYNC
        events: list[object] = []
        for drive in self.drives.values():
            events.extend(drive.on_sync(m, self.t))
        # bus priority: EMCY (0x08x) before TPDO1 (0x18x) before TPDO2 (0x28x)
        events.sort(key=lambda e: 0 if isinstance(e, Emcy) else 1 if isinstance(e, BufferStatus) else 2)
        self.feed(Sync(m, self.t))
        for ev in events:
            if self.tpdo_filter is None or self.tpdo_filter(ev):
                self.feed(ev)
        for frame in late:
            self.deliver(frame)
        self.count += 1

    def run(self, max_syncs: int = 100_000, until: Callable[[Rig], bool] | None = None) -> JobState:
        for _ in range(max_syncs):
            if self.core.state in TERMINAL or (until is not None and until(self)):
                break
            self.sync()
        return self.core.state

    # ---- assertions helpers --------------------------------------------------------------------------
    def record_frames(self, node: int) -> list[PvtRecord]:
        return [unpack(s.data) for _, s in self.sent if s.cob_id == RPDO2_BASE + node]

    def controlwords(self, node: int) -> list[tuple[int, int]]:
        return [(m, unpack_controlword(s.data)) for m, s in self.sent if s.cob_id == RPDO1_BASE + node]
