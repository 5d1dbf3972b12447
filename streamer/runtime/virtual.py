"""The virtual-time runtime: the streamer core and the simulated drives, frame by frame, no threads.

A discrete-event simulation of one CAN bus: frames are queued with their release time and transmitted one
at a time, lowest COB-ID first, each lasting its worst-case bit length; a frame takes effect when its
transmission ends, and the master's side tags and decodes exactly as `bus.network.MasterAdapter`. The
same core, drives and decoding as on a real bus, so a minute of motion runs in under a second, every
timing branch is reachable from a test, and a candump of a run is byte-identical. Fault hooks (the
reliability tests): `link` (what arrives instead of each frame; `accept`, `release`), `sync_time(n)`,
`foreign` traffic, `drive_frames`; `counters` tallies what happened.
"""

from __future__ import annotations

import heapq
import math
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from typing import Any, NamedTuple, Protocol

from bus.cob import SYNC_COB_ID, TIME_STAMP_COB_ID, classify
from bus.codec import Frame, frame_bits
from bus.errors import PROBE, BusError, ProtocolError
from bus.events import (
    AdapterError,
    BufferStatus,
    BusLoad,
    Cancel,
    Emcy,
    Event,
    HeartbeatLost,
    PositionFeedback,
    Send,
    SendFailed,
    Sync,
)
from bus.families import EPOS_IPM, PROFILES
from bus.probe import AUTO_EXPERIMENTS, AbsentObject, Phase, ProbeError, ProbeResult, StandstillProbe, WriteOnly
from bus.profile import DriveProfile, frame_to_event
from bus.sim.od import ABORT_NO_OBJECT, ABORT_NO_SUBINDEX, ABORT_UNSUPPORTED_ACCESS, ABORT_WRITE_ONLY, SdoAbort
from bus.sim.virtual import VirtualCell
from planner.config import CellConfig
from planner.job import Job
from planner.readings import DriveReadings
from streamer.core.coordinator import Coordinator, JobState, Reaction
from streamer.core.plan_source import Extender, PvtTrajectoryLike, StopPlanner
from streamer.core.settings import StreamerSettings
from streamer.runtime.spill import temp_store
from streamer.runtime.trace import JobTrace, answered

TERMINAL = frozenset({JobState.DONE, JobState.CANCELLED, JobState.FAILED})

Arrival = Frame | tuple[Frame, float]  # a frame that arrives now, or (frame, arrival time)


class FrameLog(Protocol):
    def __call__(self, t: float, cob_id: int, data: bytes) -> None: ...


class Link(Protocol):
    """What the wire does to a frame between master and drives. Returns what arrives (none, one, several;
    `(frame, t)` arrives at time t). Optional methods, used when present: `accept(frame, t) -> str | None`
    (a reason = the master's controller refuses to send it: bus-off), `release(t) -> (to_drives,
    to_master)` (frames held back, due by t)."""

    def to_drives(self, frame: Frame, t: float) -> Sequence[Arrival]: ...

    def to_master(self, frame: Frame, t: float) -> Sequence[Arrival]: ...


class ForeignTraffic:
    """Frames other devices send: a merge of time-ordered `(release time, frame)` sources."""

    def __init__(self, *sources: Iterable[tuple[float, Frame]]):
        self._it: Iterator[tuple[float, Frame]] = heapq.merge(*sources, key=lambda x: x[0])
        self._next: tuple[float, Frame] | None = next(self._it, None)
        self.sent = 0

    def peek(self) -> tuple[float, Frame] | None:
        return self._next

    def pop(self) -> tuple[float, Frame]:
        item = self._next
        assert item is not None
        self._next = next(self._it, None)
        self.sent += 1
        return item


def periodic_load(load: float, bitrate: int, *, cob_id: int = 0x050, dlc: int = 8, start_s: float = 0.0,
                  duration_s: float = math.inf, data: bytes | None = None) -> Iterator[tuple[float, Frame]]:
    """Frames of one COB-ID released evenly so that they use `load` of the bus (worst-case frame bits)."""
    if not 0.0 < load <= 1.0:
        raise ValueError(f"load must be in (0, 1], got {load}")
    payload = bytes(data) if data is not None else bytes(range(0xA0, 0xA0 + dlc))
    period = frame_bits(len(payload)) / (bitrate * load)
    k = 0
    while True:
        t = start_s + k * period
        if t >= start_s + duration_s:
            return
        yield t, Frame(cob_id, payload)
        k += 1


@dataclass(frozen=True)
class VirtualResult:
    coordinator: Coordinator
    trace: JobTrace
    first_sync: int
    last_sync: int
    settled: bool  # every axis stood still at its final position after the job


# who queued a frame
_MASTER, _DRIVES, _FOREIGN = 0, 1, 2


class _Queued(NamedTuple):
    release: float
    seq: int
    frame: Frame
    sender: int


class _Bus:
    """One CAN bus: queued frames, arbitration by COB-ID when the bus goes idle, worst-case frame bits."""

    def __init__(self, bitrate: int, foreign: ForeignTraffic | None):
        self.bit_s = 1.0 / bitrate
        self.free_at = 0.0
        self.queued: list[_Queued] = []
        self.foreign = foreign
        self._seq = 0

    def submit(self, frame: Frame, release: float, sender: int) -> None:
        self._seq += 1
        self.queued.append(_Queued(release, self._seq, frame, sender))

    def next_start(self) -> tuple[float, _Queued | None] | None:
        """When the next transmission starts and which queued frame it is (None: the foreign one)."""
        fn = self.foreign.peek() if self.foreign is not None else None
        if not self.queued and fn is None:
            return None
        earliest = min((q.release for q in self.queued), default=math.inf)
        if fn is not None and fn[0] < earliest:
            earliest = fn[0]
        start = max(self.free_at, earliest)
        best: _Queued | None = None
        for q in self.queued:
            if q.release <= start and (best is None or (q.frame.cob_id, q.seq) < (best.frame.cob_id, best.seq)):
                best = q
        if fn is not None and fn[0] <= start and (best is None or fn[1].cob_id < best.frame.cob_id):
            best = None
        return start, best

    def transmit(self, start: float, which: _Queued | None) -> tuple[float, _Queued]:
        if which is None:
            assert self.foreign is not None
            release, frame = self.foreign.pop()
            self._seq += 1
            which = _Queued(release, self._seq, frame, _FOREIGN)
        else:
            self.queued.remove(which)
        end = start + frame_bits(len(which.frame.data)) * self.bit_s
        self.free_at = end
        return end, which


class VirtualRuntime:
    """One cell of simulated drives plus the streamer core, in virtual time. Runs jobs back to back."""

    def __init__(
        self,
        cell: CellConfig,
        *,
        vcell: VirtualCell | None = None,
        log: FrameLog | None = None,
        link: Link | None = None,
        sync_time: Callable[[int], float] | None = None,
        foreign: ForeignTraffic | None = None,
        profile: DriveProfile | None = None,
        settings: StreamerSettings | None = None,
        bus_load_events: bool = True,
    ):
        self.cell = cell
        self.period_s = cell.sync_period_s
        self.vcell = vcell if vcell is not None else VirtualCell(cell, profile=profile)
        # each node's family (bus/families.py), as the drives were built
        self.profiles: dict[int, DriveProfile] = {n: m.profile for n, m in self.vcell.models.items()}
        # settings given by the caller are taken as they are; else the cell's, with what the master knows
        # of each drive ([axis.probed]) completed by the standstill probe before the first job
        self._settings_given = settings is not None
        self.settings = settings if settings is not None else replace(
            StreamerSettings.from_cell(cell), feedback=self.vcell.feedback)
        # what the master knows of each drive; a cyclic drive has no FIFO whose open points a probe measures
        self.known: dict[int, DriveReadings] = {
            a.node_id: a.probed.for_cyclic() if PROFILES[a.profile].kind == "cyclic" else a.probed for a in cell.axes}
        self.probe_result: ProbeResult | None = None
        self._probe: StandstillProbe | None = None
        self._time_offset = 0.0  # SYNC times after a probe continue from where the probe left off
        self.nodes = frozenset(a.node_id for a in cell.axes)
        self._log = log
        self._link = link
        self._accept = getattr(link, "accept", None)
        self._release = getattr(link, "release", None)
        self._sync_time = sync_time or (lambda n: n * self.period_s)
        self._bus = _Bus(cell.bus.bitrate, foreign)
        self._bitrate = cell.bus.bitrate
        self._bus_load_events = bus_load_events
        self._late: list[tuple[float, int, bool, Frame]] = []  # (arrival, seq, to_drives, frame)
        self._late_seq = 0
        self._cycle = -1  # SYNC producer cycles (the index given to sync_time)
        self._sync = -1  # SYNCs echoed (the count the core is fed, as the adapter counts them)
        self._last_sync_t: float | None = None
        self._run_since: float | None = None  # the first SYNC of the current unbroken run (Sync.since)
        self._window_bits = 0
        self._last_heartbeat: dict[int, float] = {}
        self._hb_lost: set[int] = set()
        self._hb_timeout_s = cell.drive.heartbeat_timeout_ms / 1000.0
        self._core: Coordinator | None = None
        self.trace: JobTrace | None = None
        self.counters: Counter[str] = Counter()
        for f in self.vcell.boot_frames:
            self._bus.submit(f, 0.0, _DRIVES)
        self._drain()  # the drives booted before the master starts: their boot-ups belong to no job

    @property
    def sync_count(self) -> int:
        return self._sync

    @property
    def now(self) -> float:
        """The release time of the current SYNC cycle."""
        return self._cycle_time(self._cycle) if self._cycle >= 0 else self._time_offset

    def _cycle_time(self, n: int) -> float:
        return self._sync_time(n) + self._time_offset

    # ---- frames onto the bus from outside the protocol flow
    def drive_frames(self, frames: Iterable[Frame], t: float) -> None:
        """Frames a drive sends on its own (e.g. the boot-up after `model.on_frame(0, reset)`), at `t`."""
        for f in frames:
            self._bus.submit(f, t, _DRIVES)

    # ---- the bus
    def _run_bus(self, until: float) -> None:
        """Transmit and deliver everything that starts (or arrives late) before `until`."""
        bus = self._bus
        while True:
            nxt = bus.next_start()
            start = nxt[0] if nxt is not None else math.inf
            late_at = self._late[0][0] if self._late else math.inf
            if min(start, late_at) >= until:
                return
            if late_at <= start:
                at, _, to_drives, frame = heapq.heappop(self._late)
                if to_drives:
                    self._arrive_drives(frame, at)
                else:
                    self._arrive_master(frame, at)
                continue
            assert nxt is not None
            end, q = bus.transmit(start, nxt[1])
            self._on_wire(q, start, end)

    def _drain(self) -> None:
        """Transmit and deliver everything queued or late (and the foreign frames competing with it)."""
        while self._bus.queued or self._late:
            nxt = self._bus.next_start()
            self._run_bus(math.nextafter(max(nxt[0] if nxt else 0.0, self._late[0][0] if self._late else 0.0),
                                         math.inf))

    def _on_wire(self, q: _Queued, start: float, end: float) -> None:
        frame = q.frame
        if q.sender == _MASTER and frame.cob_id == SYNC_COB_ID and self.cell.time_stamp:
            # seed 001: the master latches the SYNC's transmit time and sends it (0x1013, us) right after
            stamp = round(start * 1e6) % (1 << 32)
            self._bus.submit(Frame(TIME_STAMP_COB_ID, stamp.to_bytes(4, "little")), end, _MASTER)
        dlc = len(frame.data)
        if self._log is not None:
            self._log(start, frame.cob_id, frame.data)
        if self.trace is not None:
            self.trace.on_frame(frame.cob_id, dlc, frame.data, start)
        self._window_bits += frame_bits(dlc)
        self.counters["frames"] += 1
        if self._release is not None:
            to_drives, to_master = self._release(end)
            for f in to_drives:
                self._arrive_drives(f, end)
            for f in to_master:
                self._arrive_master(f, end)
        if q.sender == _MASTER:
            if frame.cob_id == SYNC_COB_ID:
                self._sync_echo(start, frame.data)
            self._deliver(frame, end, to_drives=True)
        elif q.sender == _DRIVES:
            self._deliver(frame, end, to_drives=False)
        else:
            self.counters["foreign"] += 1
            self._arrive_drives(frame, end)
            self._arrive_master(frame, end)

    def _deliver(self, frame: Frame, t: float, *, to_drives: bool) -> None:
        if self._link is None:
            arrivals: Sequence[Arrival] = (frame,)
        elif to_drives:
            arrivals = self._link.to_drives(frame, t)
        else:
            arrivals = self._link.to_master(frame, t)
        for a in arrivals:
            if isinstance(a, Frame):
                f, at = a, t
            else:
                f, at = a
            if at > t:
                self._late_seq += 1
                heapq.heappush(self._late, (at, self._late_seq, to_drives, f))
            elif to_drives:
                self._arrive_drives(f, t)
            else:
                self._arrive_master(f, t)

    def _arrive_drives(self, frame: Frame, t: float) -> None:
        is_sync = frame.cob_id == SYNC_COB_ID
        answers = self.vcell.sync(t, frame.data) if is_sync else self.vcell.deliver(frame.cob_id, frame.data, t)
        for f in answers:
            self._bus.submit(f, t, _DRIVES)

    def _arrive_master(self, frame: Frame, t: float) -> None:
        kind, node = classify(frame.cob_id)
        if kind == "HEARTBEAT" and node in self.nodes:
            self._last_heartbeat[node] = t
            self._hb_lost.discard(node)
        try:
            ev = frame_to_event(self.profiles, frame.cob_id, bytes(frame.data), t, self.nodes,
                                self._sync if self._sync >= 0 else None)
        except ProtocolError as e:
            self.counters["malformed"] += 1
            ev = AdapterError(f"decode 0x{frame.cob_id:03X}", str(e), t)
        if kind == "OTHER" or (node and node not in self.nodes):
            self.counters["unknown_cob_id" if kind == "OTHER" else "other_node"] += 1
        if ev is None:
            return
        if self._probe is not None:
            self._feed_probe(ev)
        if self._core is not None:
            self._apply(self._core, ev, t)

    def _sync_echo(self, t: float, data: bytes = b"") -> None:
        self._sync += 1
        n = self._sync
        last, self._last_sync_t = self._last_sync_t, t
        if last is None or abs(t - last - self.period_s) >= 0.5 * self.period_s:
            self._run_since = t  # a first SYNC, or one off its period by half of it: a drive's PLL starts over
        core = self._core
        if self.trace is not None:
            self.trace.on_sync(n, t)
        if self._probe is not None:
            for f in self._probe.on_sync(n, t, data[0] if data else None):
                self._send(f, t)
        if core is not None:
            self._apply(core, Sync(n, t, data[0] if data else None, since=self._run_since), t)
        if last is not None and self._bus_load_events:
            load = self._window_bits / (self._bitrate * max(t - last, self.period_s))
            if core is not None:
                self._apply(core, BusLoad(load, t), t)
        self._window_bits = 0

    def _send(self, frame: Frame, t: float) -> str | None:
        """The master queues a frame; returns the refusal reason when the controller refuses it."""
        if self._accept is not None:
            reason: str | None = self._accept(frame, t)
            if reason is not None:
                self.counters["send_refused"] += 1
                return reason
        self._bus.submit(frame, t, _MASTER)
        return None

    def _apply(self, core: Coordinator, ev: Event, t: float) -> None:
        """Feed one event; queue what the core returns (a refused frame becomes SendFailed)."""
        pending: list[Event] = [ev]
        while pending:
            e = pending.pop(0)
            reaction: Reaction = core.handle(e)
            if self.trace is not None:
                self.trace.on_event(answered(e, core.answered_sync))
                if reaction.changes:
                    self.trace.on_changes(reaction.changes)
            for s in reaction.sends:
                reason = self._send(Frame(s.cob_id, s.data), t)
                if reason is not None:
                    pending.append(SendFailed(f"{reason}: frame 0x{s.cob_id:03X} not sent", t))
                    break

    # ---- timers
    def _advance_drives(self, t: float) -> None:
        """The drives' timers up to t, each at its own deadline (a SYNC-loss EMCY at 1.5 periods, not at
        the next SYNC)."""
        vcell = self.vcell
        for _ in range(10_000):
            d = vcell.next_deadline()
            if d is None or d >= t:
                break
            at = min(t, d + 1e-9)
            for f in vcell.advance(at):
                self._bus.submit(f, at, _DRIVES)
            if vcell.next_deadline() == d:
                break
        for f in vcell.advance(t):
            self._bus.submit(f, t, _DRIVES)

    def _heartbeat_check(self, t: float) -> list[Event]:
        lost: list[Event] = []
        for node in sorted(self.nodes):
            seen = self._last_heartbeat.get(node)
            if seen is not None and node not in self._hb_lost and t - seen > self._hb_timeout_s:
                self._hb_lost.add(node)
                lost.append(HeartbeatLost(node, t))
        return lost

    def _cycle_once(self, t: float | None = None, t_next: float | None = None) -> float:
        """One SYNC cycle (see the module docstring); returns the SYNC's release time. `t`/`t_next`
        override the SYNC timing (the probe sets its own)."""
        self._cycle += 1
        if t is None:
            t = self._cycle_time(self._cycle)
        if t_next is None:
            t_next = self._cycle_time(self._cycle + 1)
        self._run_until(t)
        self._advance_drives(t)
        self._consumer_check(t)
        reason = self._send(Frame(SYNC_COB_ID, self._sync_data()), t)
        if reason is not None:
            self.counters["sync_refused"] += 1
            if self._core is not None:
                self._apply(self._core, SendFailed(f"{reason}: SYNC not sent", t), t)
        self._run_until(t_next)
        return t

    def _sync_data(self) -> bytes:
        """The SYNC's counter byte 1..N when TPDO2 is staggered (CiA 301 0x1019), else none."""
        fb = self.vcell.feedback
        if fb is None:
            return b""
        return bytes([1 + self._cycle % fb.counter_overflow])

    def _run_until(self, until: float) -> None:
        """The bus up to `until`, stopping at each drive timer (a TPDO held for its latency, an own
        clock's segment end, a heartbeat) and each heartbeat consumer deadline on the way (the master's
        consumer timer fires when the timeout passes, not at the next SYNC)."""
        last = -math.inf
        for _ in range(100_000):
            d_drive = self.vcell.next_deadline()
            d_cons = self._next_consumer_deadline()
            d = min(x for x in (d_drive, d_cons, math.inf) if x is not None)
            if d >= until - 1e-9:
                break  # due at `until` (a heartbeat at the SYNC's time): the next cycle runs it before its SYNC
            if d <= last:  # a timer that did not move: take it at the next instant
                d = math.nextafter(last, math.inf)
            self._run_bus(d)
            last = d
            if d_drive is not None and d_drive <= d:
                for f in self.vcell.advance(d):
                    self._bus.submit(f, d, _DRIVES)
            if d_cons is not None and d_cons <= d:
                self._consumer_check(d)
        self._run_bus(until)

    def _next_consumer_deadline(self) -> float | None:
        live = [seen for node, seen in self._last_heartbeat.items() if node not in self._hb_lost]
        return math.nextafter(min(live) + self._hb_timeout_s, math.inf) if live else None

    def _consumer_check(self, t: float) -> None:
        for ev in self._heartbeat_check(t):
            if self._core is not None:
                self._apply(self._core, ev, t)

    # ---- running a job
    def enable_drives(self, t: float) -> None:
        """What `MasterAdapter.enable_drives` does over SDO, written straight into the models
        (`VirtualCell.enable_drives`: the set point objects of cyclic drives = their position, fault reset
        when faulted, disable voltage from quick stop / fault reaction, shutdown 0x0006 unless already
        operation enabled (leaving operation enabled would drop the position demand to the actual position,
        and the next plan starts at the demand), enable operation 0x000F (bit 4 low, so the start is a
        rising edge), the family's writes (EPOS: buffer clear then enable)). A drive that does not get there
        is left as it is: the core finds it (DRIVE_NOT_READY). What the drives answer goes on the bus."""
        for f in self.vcell.enable_drives(t, check=False):
            self._bus.submit(f, t, _DRIVES)

    # ---- the standstill probe
    def probe(self, experiments: Sequence[Phase] = AUTO_EXPERIMENTS) -> ProbeResult:
        """Run the standstill probe (bus/probe.py) on every drive of the cell, as the master does at
        configuration: SYNC at the probe's times, its frames on the bus, SDO work (enable, buffer clear,
        fault reset) written straight into the models as `enable_drives` does."""
        self._core = None
        self.trace = None
        nodes = sorted(n for n in self.nodes if self.profiles[n].kind == "fifo")
        t0 = self._last_sync_t if self._last_sync_t is not None else self.now
        demand = EPOS_IPM.obj("position_demand")
        probe = StandstillProbe(nodes, self.cell.sync_period_ms, EPOS_IPM,
                                {n: self.vcell.sdo_read(n, demand.index, demand.sub) for n in nodes},
                                experiments=experiments, t0=t0, feedback=self.vcell.feedback)
        self._probe = probe
        try:
            t = t0
            for _ in range(10_000):
                if probe.done:
                    break
                if probe.wants_enable:
                    t_en = t + self.period_s / 2
                    self._run_until(t_en)
                    self.enable_drives(t_en)
                    probe.enabled({n: self.vcell.sdo_read(n, demand.index, demand.sub) for n in nodes})
                t = probe.next_sync_time()
                self._cycle_once(t, t + self.period_s)
            else:  # pragma: no cover - the probe's phases are bounded
                raise ProbeError("the probe did not finish")
        finally:
            self._probe = None
        # jobs after the probe: SYNC continues one period after the probe's last
        self._time_offset = t + self.period_s - self._sync_time(self._cycle + 1)
        result = probe.result()
        self.probe_result = result
        return result

    def read_object(self, node: int, index: int, sub: int = 0) -> int:
        """An SDO read of a drive (for the object survey): AbsentObject / WriteOnly for those aborts."""
        try:
            return self.vcell.sdo_read(node, index, sub)
        except SdoAbort as e:
            if e.code in (ABORT_NO_OBJECT, ABORT_NO_SUBINDEX):
                raise AbsentObject(f"0x{index:04X}:{sub:02X}") from None
            if e.code in (ABORT_WRITE_ONLY, ABORT_UNSUPPORTED_ACCESS):
                raise WriteOnly(f"0x{index:04X}:{sub:02X}") from None
            raise

    def _feed_probe(self, ev: Event) -> None:
        probe = self._probe
        assert probe is not None
        if isinstance(ev, BufferStatus):
            probe.on_tpdo1(ev.node, ev.statusword, ev.buffer_status, ev.free_size, ev.t)
        elif isinstance(ev, PositionFeedback):
            probe.on_tpdo2(ev.node, ev.position_actual, ev.position_demand, ev.t)
        elif isinstance(ev, Emcy):
            probe.on_emcy(ev.node, ev.code, ev.t)

    def ensure_readings(self) -> None:
        """Measure what the master does not know yet of the drives (`DriveReadings.needs_probe`), once,
        with the standstill probe; the job settings then carry every drive's readings."""
        if self._settings_given:
            return
        if any(r.needs_probe for n, r in self.known.items() if self.profiles[n].kind == "fifo"):
            try:  # as the real-time runtime says it: the job's configuration error, naming the drive
                self.known = self.probe().complete(self.known)
            except ProbeError as e:
                raise BusError(PROBE, str(e)) from None
        self.settings = replace(self.settings, readings=dict(self.known))

    def idle(self, duration_s: float, *, on_sync: Callable[[int], None] | None = None) -> None:
        """Keep SYNC running with no job for `duration_s` (what the drives do is seen in the models)."""
        self._core = None
        self.trace = None
        end = self.now + duration_s
        while True:
            t = self._cycle_once()
            if on_sync is not None:
                on_sync(self._sync)
            if t >= end:
                return

    def run(
        self,
        trajectory: PvtTrajectoryLike,
        *,
        stop_planner: StopPlanner | None = None,
        cancel_at_s: float | None = None,
        max_s: float | None = None,
        settle_s: float = 3.0,
        on_sync: Callable[[Coordinator, int], None] | None = None,
        feed: Callable[[Coordinator, int, float], Sequence[object]] | None = None,
        extender: Extender | None = None,
    ) -> VirtualResult:
        """Stream one trajectory to the drives. Returns when the job ended and the axes settled.

        `feed(core, sync, t)`, after each SYNC: events to feed the core at that moment (a `Change`, a
        `Cancel`), as the real-time runtime feeds what another thread asked for. `extender`: the next chunk of
        an open-ended (velocity) stream; default `planner.motion.travel.extend_velocity`, called on the SYNC (virtual
        time has no deadline to miss)."""
        self.ensure_readings()
        t_enable = self._cycle_time(self._cycle + 1) - self.period_s / 2
        self._core = None
        self._run_until(t_enable)  # frames still in flight from before belong to no job
        self.enable_drives(t_enable)
        if extender is None:
            from planner.motion.travel import extend_velocity

            extender = extend_velocity  # type: ignore[assignment]
        # an endless job's per-SYNC logs keep their old samples in temporary files (streamer/runtime/spill.py)
        core = Coordinator(trajectory, self.settings, stop_planner=stop_planner, extender=extender, store=temp_store)
        job_nodes = set(core.node_ids)
        self.trace = JobTrace(
            [(a.node_id, a.name) for a in self.cell.axes if a.node_id in job_nodes],
            sync_period_s=self.period_s,
            bitrate=self.cell.bus.bitrate,
            store=temp_store if core.open_ended else None,
        )
        self._core = core
        first_cycle = self._cycle + 1
        first = self._sync + 1
        dt_total_s = core.report().duration_ms / 1000.0
        limit_s = max_s if max_s is not None else dt_total_s + 30.0
        cancelled = False
        settle_until: float | None = None
        settled = False
        settled_at: int | None = None
        try:
            while True:
                t = self._cycle_once()
                elapsed = (self._cycle - first_cycle) * self.period_s
                if (cancel_at_s is not None and not cancelled and elapsed >= cancel_at_s
                        and core.state not in TERMINAL):
                    cancelled = True
                    self._apply(core, Cancel(t), t)
                if on_sync is not None:
                    on_sync(core, self._sync)
                if feed is not None:
                    for ev in feed(core, self._sync, t):
                        self._apply(core, ev, t)  # type: ignore[arg-type]
                if core.state in TERMINAL:
                    if settle_until is None:
                        settle_until = t + settle_s
                    if self._settled() or t >= settle_until:
                        settled = self._settled()
                        if settled and settled_at is None:
                            settled_at = self._sync  # one more cycle: TPDOs held for their latency come in
                            continue
                        break
                if max_s is None:  # an extended (open-ended) or changed stream runs longer
                    limit_s = max(limit_s, core.stream_duration_ms / 1000.0 + 30.0)
                if elapsed > limit_s:
                    raise TimeoutError(
                        f"job still {core.state.value} after {elapsed:.1f} s of virtual time (limit {limit_s:.1f} s)"
                    )
        finally:
            self._core = None
        return VirtualResult(core, self.trace, first, self._sync, settled)

    def home(self, job: Job, *, cancel_at_s: float | None = None) -> dict[str, Any]:
        """Run a home job (streamer/runtime/homing.py) on the simulated drives, SYNC running between the
        statusword reads; returns its report."""
        from streamer.runtime.homing import run_homing

        self.ensure_readings()
        self._core = None
        self.trace = None
        t0 = self.now
        return run_homing(self.cell, job, _VirtualPort(self),
                          cancelled=lambda: cancel_at_s is not None and self.now - t0 >= cancel_at_s)

    def _settled(self) -> bool:
        return all(
            m.position_actual == m.position_demand and abs(m.velocity_actual_rpm) < 1.0
            for m in self.vcell.models.values()
        )


class _VirtualPort:
    """`HomingPort` of the virtual-time runtime: SDO written straight into the models (as `enable_drives`),
    waiting = SYNC cycles with no job."""

    def __init__(self, rt: VirtualRuntime):
        self.rt = rt

    def write(self, node: int, index: int, sub: int, value: int) -> None:
        t = self.rt.now
        for f in self.rt.vcell.sdo_write(node, index, sub, value, t):
            self.rt._bus.submit(f, t, _DRIVES)

    def read(self, node: int, index: int, sub: int) -> int:
        return self.rt.vcell.sdo_read(node, index, sub)

    def enable(self) -> None:
        self.rt.enable_drives(self.rt.now)

    def wait(self, seconds: float) -> None:
        for _ in range(max(1, round(seconds / self.rt.period_s))):
            self.rt._cycle_once()

    def now(self) -> float:
        return self.rt.now


def send_frames(sends: Sequence[Send]) -> list[Frame]:
    return [Frame(s.cob_id, s.data) for s in sends]
