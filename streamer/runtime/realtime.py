"""The real-time runtime: the streamer core on a python-can bus, driven by the SYNCs on the wire.

Theory of operation. `MasterAdapter` (bus/network.py) owns the bus and turns what it hears into
`bus.events` on its receive thread; this runtime queues them and runs the `Coordinator` on ONE streaming
thread (the caller of `run`): pop an event, feed the trace and the core, send the returned frames at
once. Nothing heavy runs there (planning before, plotting after). Refused frames and cancel requests
become events through the same core. The same core, decoding and trace as the virtual-time runtime, so
what the tests prove there is what runs here. While a job streams, the objects that existed before it
are frozen out of the garbage collector (`quiet_gc`): a full collection of a service's heap stops every
thread for several SYNC periods (docs/streamer.md, "Real time"). Before the first job the standstill
probe (bus/probe.py) completes the drives' readings the cell does not state.
"""

from __future__ import annotations

import contextlib
import gc
import math
import os
import queue
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import can

from bus.cob import RPDO2_BASE
from bus.engine import LateBatch, thread_priority
from bus.errors import PROBE, BusError
from bus.events import BufferStatus, Cancel, Emcy, Event, PositionFeedback, SendFailed, Sync, SyncOnWire
from bus.families import EPOS_IPM, PROFILES
from bus.network import MasterAdapter
from bus.probe import AUTO_EXPERIMENTS, Phase, ProbeError, ProbeResult, StandstillProbe
from planner.config import CellConfig
from planner.readings import DriveReadings
from streamer.core.coordinator import Coordinator, JobState
from streamer.core.plan_source import Extender, PvtTrajectoryLike, StopPlanner
from streamer.core.settings import StreamerSettings
from streamer.runtime.extension import PrefetchExtender
from streamer.runtime.spill import temp_store
from streamer.runtime.trace import JobTrace, answered

TERMINAL = frozenset({JobState.DONE, JobState.CANCELLED, JobState.FAILED})
CYCLIC_AHEAD_MS = 50.0  # cells with drives fed one set point per SYNC: what a stall of this process may take
FIFO_AHEAD_MS = 0.0  # EPOS-only cells: one period (a FIFO rides out a late record; feedback stays fresh)
# the longest this machine may hold the drives' answers up: drives simulated in processes beside the master
# share its CPUs and stall with them (hardware does not). The TPDO timeout waits at least this long; set by
# PVT_HOST_STALL_MS in the environment (the test suite: tests/conftest.py), 0 by default (the cell's
# [drive] tpdo_timeout_syncs as it is)
HOST_STALL_MS = float(os.environ.get("PVT_HOST_STALL_MS", "0"))


# with the cycle engine: SCHED_FIFO of the streaming thread while a job or the probe runs (it paces the probe's
# SYNCs and feeds the engine its lead). Below the engine (80) and the simulated drives (70), which answer every
# SYNC; above the receive thread (60), which has no deadline of its own (what it hands over keeps the bus's
# order, however late). Below it, the receive thread and the drives held it up to 29-67 ms at 5 ms SYNC on an
# idle machine (each of 6 runs), past the cyclic lead: EMCY 0x8782 in 2 of 6 runs; above it, 10-14 ms
STREAMING_PRIORITY = 65
SWITCH_INTERVAL_S = 0.0005  # while a job streams: a thread holding the GIL gives it up this soon (default 5 ms)


@contextlib.contextmanager
def _switch_interval(seconds: float) -> Iterator[None]:
    before = sys.getswitchinterval()
    sys.setswitchinterval(seconds)
    try:
        yield
    finally:
        sys.setswitchinterval(before)


def default_ahead_ms(cell: CellConfig) -> float:
    """How far ahead of the cycle engine the core runs by default: far enough to ride out a stall of the
    master's process where a late frame faults a drive (cyclic set points: CYCLIC_AHEAD_MS, or the stall
    PVT_HOST_STALL_MS states for this machine when longer), one period where it does not."""
    cyclic = any(PROFILES[a.profile].kind == "cyclic" for a in cell.axes)
    return max(CYCLIC_AHEAD_MS, HOST_STALL_MS) if cyclic else FIFO_AHEAD_MS

def with_host_stall(settings: StreamerSettings, stall_ms: float) -> StreamerSettings:
    """`settings` for a machine that may hold the master and the drives' answers up `stall_ms`
    (PVT_HOST_STALL_MS), in whole SYNCs, at most 100: the TPDO timeout waits at least that long, and the FIFOs
    are kept topped up that much further ahead (`repair_syncs`), so a drive interpolating through the stall
    does not run below its underflow watermark while the master cannot send. A stop then begins up to that
    much later (it begins after what is queued)."""
    if stall_ms <= 0:
        return settings
    syncs = min(100, math.ceil(stall_ms / settings.sync_period_ms))
    return replace(settings, tpdo_timeout_syncs=max(settings.tpdo_timeout_syncs, syncs),
                   repair_syncs=max(settings.repair_syncs, syncs))


_gc_lock = threading.Lock()
_gc_holders = 0  # jobs streaming in this process (several runtimes may share one, as in the tests)


@contextlib.contextmanager
def quiet_gc() -> Iterator[None]:
    """Freeze what the process holds now while the block runs (see the module docstring); the last of
    overlapping blocks to end thaws it."""
    global _gc_holders
    with _gc_lock:
        if _gc_holders == 0:
            gc.freeze()
        _gc_holders += 1
    try:
        yield
    finally:
        with _gc_lock:
            _gc_holders -= 1
            if _gc_holders == 0:
                gc.unfreeze()


class _Tap(can.Listener):
    """Every frame the master's bus sees (its own included): candump log and the trace's frame tally."""

    def __init__(self, log_path: Path | None):
        self.writer: can.Listener | None = can.Logger(str(log_path)) if log_path is not None else None
        self.trace: JobTrace | None = None
        self._lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        with self._lock:
            if self.writer is not None:
                self.writer.on_message_received(msg)
            if self.trace is not None:
                self.trace.on_frame(msg.arbitration_id, msg.dlc, bytes(msg.data), msg.timestamp)

    def stop(self) -> None:
        with self._lock:
            if self.writer is not None:
                self.writer.stop()
                self.writer = None


@dataclass
class NodeSnapshot:
    """The latest TPDO values of one drive (for telemetry while no job runs, and start checks)."""

    node: int
    statusword: int | None = None
    buffer_status: int | None = None
    free_size: int | None = None
    position_actual: int | None = None
    position_demand: int | None = None
    velocity_counts_per_s: float = 0.0
    t: float = 0.0
    emcy_code: int | None = None

    def update(self, ev: object) -> None:
        if isinstance(ev, BufferStatus):
            self.statusword, self.buffer_status, self.free_size = ev.statusword, ev.buffer_status, ev.free_size
        elif isinstance(ev, PositionFeedback):
            if self.position_actual is not None and ev.t > self.t:
                self.velocity_counts_per_s = (ev.position_actual - self.position_actual) / (ev.t - self.t)
            self.position_actual, self.position_demand, self.t = ev.position_actual, ev.position_demand, ev.t
        elif isinstance(ev, Emcy):
            self.emcy_code = ev.code


@dataclass(frozen=True)
class RealtimeResult:
    coordinator: Coordinator
    trace: JobTrace
    first_sync: int
    last_sync: int
    settled: bool
    wall_s: float


class RealtimeRuntime:
    """Runs jobs on a configured `MasterAdapter`, one at a time, on the calling thread."""

    def __init__(
        self,
        cell: CellConfig,
        adapter: MasterAdapter,
        *,
        log_path: Path | None = None,
        settings: StreamerSettings | None = None,
        ahead_ms: float | None = None,
        streaming_priority: int | None = None,
    ):
        self.cell = cell
        self.adapter = adapter
        # with the cycle engine: how long before its SYNC the core is fed it (see `_Announcer`)
        self.ahead_ms = float(ahead_ms) if ahead_ms is not None else default_ahead_ms(cell)
        # SCHED_FIFO of the streaming thread while a job or the probe runs with the engine, where permitted
        self.streaming_priority = streaming_priority if streaming_priority is not None else STREAMING_PRIORITY
        # settings given by the caller are taken as they are; else the cell's, with what the master knows
        # of each drive ([axis.probed]) completed by the standstill probe before the first job
        self._settings_given = settings is not None
        self.settings = settings if settings is not None else replace(
            StreamerSettings.from_cell(cell), feedback=adapter.feedback)
        # what the master knows of each drive; a cyclic drive has no FIFO whose open points a probe measures
        self.known: dict[int, DriveReadings] = {
            a.node_id: a.probed.for_cyclic() if PROFILES[a.profile].kind == "cyclic" else a.probed for a in cell.axes}
        self.probe_result: ProbeResult | None = None
        self._probing = False
        self._events: queue.Queue[Event] = queue.Queue()
        self._sync = -1
        self._tap = _Tap(log_path)
        adapter.add_listener(self._tap)
        self._running = False
        # the running job's (plan, core, trace), None between jobs: read, never written, by the live view's
        # publishing thread (streamer/live), which follows the trace's append-only lists
        self.live: tuple[Any, Coordinator, JobTrace] | None = None
        self._snap_lock = threading.Lock()
        self._snapshot: dict[int, NodeSnapshot] = {a.node_id: NodeSnapshot(a.node_id) for a in cell.axes}
        adapter.on_event(self._on_event)
        engine = adapter.engine
        if engine is not None:
            engine.on_late = self._on_late
            engine.on_send_failed = lambda cob_id, why: self._on_event(
                SendFailed(f"the bus refused frame 0x{cob_id:03X}: {why}", adapter.now()))

    def _on_late(self, late: LateBatch) -> None:
        if self._running:
            self._events.put(late)  # type: ignore[arg-type]

    def _on_event(self, ev: Event) -> None:
        """Adapter thread: keep the latest state of every node (cheap), queue events only during a job."""
        node = getattr(ev, "node", None)
        snap = self._snapshot.get(node) if node is not None else None
        if snap is not None:
            with self._snap_lock:
                snap.update(ev)
        if self._running or self._probing:
            self._events.put(ev)

    def submit(self, ev: object) -> bool:
        """Queue an event for the running job's core (a `Change`), fed on the job's thread in order with the bus
        events; False when no job runs (nothing would take it)."""
        if not self._running:
            return False
        self._events.put(ev)  # type: ignore[arg-type]
        return True

    def snapshot(self) -> dict[int, NodeSnapshot]:
        with self._snap_lock:
            return {n: replace(s) for n, s in self._snapshot.items()}

    def close(self) -> None:
        self.adapter.stop_sync()
        self._tap.stop()

    # ---- the standstill probe
    def probe(self, experiments: tuple[Phase, ...] = AUTO_EXPERIMENTS) -> ProbeResult:
        """Run the standstill probe on every drive of the cell (see the module docstring)."""
        adapter = self.adapter
        was_running = adapter.sync_running
        adapter.stop_sync()
        # the probe's experiments are about the EPOS FIFO: the cyclic drives of a mixed cell sit them out
        nodes = sorted(a.node_id for a in self.cell.axes if adapter.profiles[a.node_id].kind == "fifo")
        demand = EPOS_IPM.obj("position_demand")

        def demands() -> dict[int, int]:
            return {n: adapter.read(n, demand.index, demand.sub) for n in nodes}

        adapter.enable_drives()
        probe = StandstillProbe(nodes, self.cell.sync_period_ms, EPOS_IPM, demands(),
                                experiments=experiments, t0=adapter.now(), feedback=adapter.feedback)
        fb = adapter.feedback
        counter = 0
        while self._drain(0.0) is not None:
            pass
        self._probing = True
        thaw = contextlib.ExitStack()
        thaw.enter_context(quiet_gc())  # the probe paces its SYNCs on this thread
        if adapter.engine is not None:  # it paces the probe's SYNCs: as the streaming thread runs a job
            thaw.enter_context(thread_priority(self.streaming_priority))
            thaw.enter_context(_switch_interval(SWITCH_INTERVAL_S))
        try:
            while not probe.done:
                if probe.wants_enable:
                    adapter.enable_drives()
                    probe.enabled(demands())
                if adapter.engine is not None:
                    # the engine sends every SYNC the probe already knows at its time: while a drive
                    # interpolates, no stall of this thread stretches a SYNC interval (one command: a late
                    # first SYNC moves the others with it, bus/engine.py `sync_once`)
                    times = probe.next_sync_times()
                    adapter.send_sync(at=times)
                else:  # this thread paces the SYNC, one at a time
                    t_next = probe.next_sync_time()
                    times = [t_next]
                    while (now := adapter.now()) < t_next:
                        ev = self._drain(min(0.002, t_next - now))
                        if ev is not None:
                            self._feed_probe(probe, ev)
                    if fb is not None:
                        counter = counter % fb.counter_overflow + 1
                    adapter.send_sync(counter if fb is not None else None)
                # the SYNCs' echoes (probe.on_sync) and their answers come through the queue
                for t_next in times:
                    deadline = time.monotonic() + 0.2 + max(0.0, t_next - adapter.now())
                    seen = probe.syncs_seen
                    while probe.syncs_seen == seen and time.monotonic() < deadline:
                        ev = self._drain(0.005)
                        if ev is not None:
                            self._feed_probe(probe, ev)
                    if probe.syncs_seen == seen:
                        raise ProbeError("no SYNC echo: the interface does not deliver own messages")
        except ProbeError as e:
            raise BusError(PROBE, str(e)) from None
        finally:
            self._probing = False
            thaw.close()
            if was_running:
                adapter.start_sync()
        result = probe.result()
        self.probe_result = result
        return result

    def read_object(self, node: int, index: int, sub: int = 0) -> int:
        """An SDO read of a drive (for the object survey): AbsentObject / WriteOnly for those aborts."""
        return self.adapter.read_object(node, index, sub)

    def _feed_probe(self, probe: StandstillProbe, ev: Event) -> None:
        if isinstance(ev, Sync):
            for f in probe.on_sync(ev.count, ev.t, ev.counter):
                self.adapter.send(f.cob_id, f.data)
        elif isinstance(ev, BufferStatus):
            probe.on_tpdo1(ev.node, ev.statusword, ev.buffer_status, ev.free_size, ev.t)
        elif isinstance(ev, PositionFeedback):
            probe.on_tpdo2(ev.node, ev.position_actual, ev.position_demand, ev.t)
        elif isinstance(ev, Emcy):
            probe.on_emcy(ev.node, ev.code, ev.t)

    def ensure_readings(self) -> None:
        """Measure what the master does not know yet of the drives, once (see the virtual runtime)."""
        if self._settings_given:
            return
        if any(r.needs_probe for n, r in self.known.items() if self.adapter.profiles[n].kind == "fifo"):
            try:
                self.known = self.probe().complete(self.known)
            except ProbeError as e:
                raise BusError(PROBE, str(e)) from None
        self.settings = replace(self.settings, readings=dict(self.known), feedback=self.adapter.feedback)

    def _drain(self, timeout_s: float) -> Event | None:
        try:
            return self._events.get(timeout=timeout_s)
        except queue.Empty:
            return None

    def run(
        self,
        trajectory: PvtTrajectoryLike,
        *,
        stop_planner: StopPlanner | None = None,
        cancel: threading.Event | None = None,
        settle_s: float = 3.0,
        on_change: Callable[[Coordinator], None] | None = None,
        timeout_s: float | None = None,
        lead_ms: int | None = None,
        extender: Extender | None = None,
    ) -> RealtimeResult:
        """Stream one trajectory: enable the drives, start SYNC if it is not running, run to the end.

        `lead_ms`: this job's lead (how much motion is kept queued: a change or a stop acts after it), else
        the settings'. Events given to `submit()` while it runs (a `Change`) are fed to the core in order
        with the bus events, on this thread. `extender`: the next chunk of an open-ended (velocity) stream;
        default a `PrefetchExtender` (streamer/runtime/extension.py: planned on a worker thread, ahead)."""
        cell = self.cell
        self.ensure_readings()
        wall0 = time.monotonic()
        self.adapter.enable_drives()
        settings = self.settings if lead_ms is None else replace(self.settings, lead_ms=lead_ms)
        if not self.adapter.sync_running:
            self.adapter.start_sync()
        engine = self.adapter.engine is not None
        if engine:
            settings = replace(settings, ahead_syncs=_Announcer.syncs_for(self.ahead_ms, cell.sync_period_s))
        settings = with_host_stall(settings, HOST_STALL_MS)
        # the adapter hands our own frames back as the bus carried them: the core counts each batch of records
        # from the SYNC after it was on the wire, whenever the machine let it go out (RecordOnWire)
        settings = replace(settings, records_echoed=True)
        prefetch: PrefetchExtender | None = None
        if extender is None:
            extender = prefetch = PrefetchExtender()
            prefetch.prefetch(trajectory)  # the first chunk's successor, while the drives are primed
        # an endless job's per-SYNC logs keep their old samples in temporary files (streamer/runtime/spill.py)
        core = Coordinator(trajectory, settings, stop_planner=stop_planner, extender=extender, store=temp_store)
        nodes = set(core.node_ids)
        trace = JobTrace([(a.node_id, a.name) for a in cell.axes if a.node_id in nodes],
                         sync_period_s=cell.sync_period_s, bitrate=cell.bus.bitrate,
                         store=temp_store if core.open_ended else None)
        # events queued before this job (TPDOs of the previous one) belong to nobody
        while self._drain(0.0) is not None:
            pass
        self._running = True
        self._tap.trace = trace
        self.live = (trajectory, core, trace)
        thaw = contextlib.ExitStack()
        thaw.enter_context(quiet_gc())
        if engine:  # this thread feeds the engine ahead: it preempts planning, logging and the API where permitted
            thaw.enter_context(thread_priority(self.streaming_priority))
            thaw.enter_context(_switch_interval(SWITCH_INTERVAL_S))
        limit = timeout_s if timeout_s is not None else core.stream_duration_ms / 1000.0 + 30.0
        # from now on the core is fed each SYNC ahead of the wire (after the work above: its first SYNC is on time)
        ahead = _Announcer.start(self.adapter, settings.ahead_syncs) if engine else None
        first_sync: int | None = None
        last_sync = -1
        cancelled = False
        settle_until: float | None = None
        settled = False
        try:
            while True:
                wait = 0.05 if ahead is None else min(0.05, max(0.0, ahead.next_due() - time.time()))
                ev = self._drain(wait)
                if ahead is not None:
                    # Sync(n) is fed `ahead` before SYNC n goes out (and before any answer to it: catch up first)
                    tag = getattr(ev, "sync_count", None) if ev is not None else None
                    for sync in ahead.due(time.time(), tag if isinstance(tag, int) else None):
                        self._feed(core, trace, sync, ahead)
                if cancel is not None and cancel.is_set() and not cancelled and core.state not in TERMINAL:
                    cancelled = True
                    self._feed(core, trace, Cancel(self.adapter.now()), ahead)
                if ev is None:
                    if settle_until is not None and time.monotonic() >= settle_until:
                        break  # the job ended and nothing comes any more (bus-off: no SYNC, no TPDO)
                    if timeout_s is None:  # a change may have made the stream longer
                        limit = max(limit, core.stream_duration_ms / 1000.0 + 30.0)
                    if time.monotonic() - wall0 > limit:
                        raise TimeoutError(f"job still {core.state.value} after {limit:.1f} s")
                    continue
                if isinstance(ev, LateBatch):
                    if ahead is not None and any(synchronous(c) for c in ev.cob_ids):
                        after = "after" if ev.delay_s is None else f"{1000 * ev.delay_s:.1f} ms after"
                        self._feed(core, trace, SendFailed(
                            f"frames for the cycle after SYNC {ev.cycle} reached the cycle engine {after} the next "
                            f"SYNC: the master fell behind its {ahead.lead_s * 1000:.0f} ms lead", self.adapter.now()),
                            ahead)
                    # PVT records only: the FIFOs take them whenever they come, and the core counts them from the
                    # SYNC after their echo (RecordOnWire), which the bus's order brings before any answer with them
                    continue
                fed: object = ev
                if isinstance(ev, Sync):
                    first_sync = ev.count if first_sync is None else first_sync
                    last_sync = ev.count
                    trace.on_sync(ev.count, ev.t)
                    if ahead is not None:  # the core was fed this SYNC ahead of the wire: now it is out
                        fed = SyncOnWire(ev.count, ev.t)
                self._feed(core, trace, fed, ahead)
                if on_change is not None:
                    on_change(core)
                if core.state in TERMINAL:
                    now = time.monotonic()
                    if settle_until is None:
                        settle_until = now + settle_s
                    settled = self._settled(trace, nodes)
                    if settled or now >= settle_until:
                        break
                if timeout_s is None:
                    limit = max(limit, core.stream_duration_ms / 1000.0 + 30.0)
                if time.monotonic() - wall0 > limit:
                    raise TimeoutError(f"job still {core.state.value} after {limit:.1f} s")
        finally:
            self._running = False
            self._tap.trace = None
            self.live = None
            thaw.close()
            if prefetch is not None:
                prefetch.close()
        return RealtimeResult(core, trace, first_sync if first_sync is not None else 0, last_sync, settled,
                              time.monotonic() - wall0)

    @staticmethod
    def _settled(trace: JobTrace, nodes: set[int]) -> bool:
        for n in nodes:
            ax = trace.axes[n]
            if len(ax.actual) < 3 or len(set(ax.actual[-3:])) != 1 or ax.actual[-1] != ax.demand[-1]:
                return False
        return True

    def _feed(self, core: Coordinator, trace: JobTrace, ev: Any, ahead: _Announcer | None = None) -> None:
        pending = [ev]
        while pending:
            e = pending.pop(0)
            reaction = core.handle(e, wire_sync=self.adapter.latest_sync if ahead is None else None)
            trace.on_event(answered(e, core.answered_sync))
            if reaction.changes:
                trace.on_changes(reaction.changes)
            if not reaction.sends:
                continue
            try:
                if ahead is None:
                    for s in reaction.sends:
                        self.adapter.send(s.cob_id, s.data)
                else:  # after the SYNC the core last saw: it is on the wire, or in the engine's ring for it
                    self.adapter.send_at(ahead.fed, [(s.cob_id, s.data) for s in reaction.sends])
            except BusError as err:
                pending.append(SendFailed(str(err), self.adapter.now()))


def synchronous(cob_id: int) -> bool:
    """Must this frame reach the drive between its SYNC and the next (a controlword, a cyclic set point)? A
    PVT record (asynchronous RPDO2, 0x300 + node) is taken whenever it comes: late, it only counts later."""
    return (cob_id & 0x780) != RPDO2_BASE


class _Announcer:
    """When the real-time runtime feeds the core each SYNC: `lead_s` before the cycle engine sends it.

    The engine sends SYNC n at t0 + n * period (its absolute-time schedule) and right after it the frames the
    core returned for SYNC n, so the core must have been fed Sync(n) before that: `lead_s` (a whole number of
    periods less half a period, so the core's work never meets the engine's busy moment) covers the longest
    stall of this process the cell tolerates. A synchronous frame (a controlword, a cyclic set point) that
    still reaches the engine after its SYNC is a fault (`synchronous`); a PVT record (asynchronous RPDO2) is not."""

    def __init__(self, t0: float, period_s: float, syncs: int, first: int,
                 counter: Callable[[int], int | None] = lambda n: None):
        self.t0 = t0
        self.counter = counter  # the SYNC counter (0x1019) SYNC n carries, if any
        self.period_s = period_s
        self.syncs = syncs
        self.lead_s = (syncs - 0.5) * period_s
        self.fed = first - 1  # the last SYNC fed to the core

    @staticmethod
    def syncs_for(ahead_ms: float, period_s: float) -> int:
        """The whole periods of lead (less half a period) that cover `ahead_ms`: at least one."""
        return max(1, math.ceil(ahead_ms / 1000.0 / period_s + 0.5))

    @staticmethod
    def start(adapter: MasterAdapter, syncs: int) -> _Announcer:
        schedule = adapter.sync_schedule
        if schedule is None:
            raise BusError(PROBE, "the cycle engine has no SYNC schedule running")
        t0, period = schedule
        lead = (syncs - 0.5) * period
        wire = adapter.latest_sync
        first = max(0 if wire is None else wire + 1, math.ceil((time.time() + lead - t0) / period) + 1)
        return _Announcer(t0, period, syncs, first, adapter.sync_counter)

    def next_due(self) -> float:
        return self.t0 + (self.fed + 1) * self.period_s - self.lead_s

    def due(self, now: float, tag: int | None) -> Iterator[Sync]:
        """The Syncs to feed now: every SYNC whose time to be fed has come, and every SYNC up to `tag`
        (an answer to it is about to be fed)."""
        while self.next_due() <= now or (tag is not None and tag > self.fed):
            self.fed += 1
            n = self.fed
            yield Sync(n, self.t0 + n * self.period_s, self.counter(n), since=self.t0)  # the engine's unbroken run

