"""The cycle engine: SYNC, each cycle's frames and the bus's receive side, in a process of its own.

A CPython thread cannot keep a real-time cycle (GIL, garbage collector), so the engine is a process
(`python -m bus.engine`, started by `EngineBus`) that owns the bus and runs one loop: at SYNC n's time
(t0 + n * period, late but never skipped) send SYNC n and the frames queued for cycle n, then read the bus,
and forward every frame with its time on the wire to the master (what was on the wire before SYNC n before
it), never waiting for it. The master queues frames ahead for their cycle (`send_at`); one arriving after
its cycle is reported `late`. It runs at SCHED_FIFO with locked memory and no garbage collector where
permitted (`EngineBus.realtime` says).
`EngineBus` is a python-can `BusABC`, so canopen and listeners work on it unchanged.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import ctypes.util
import dataclasses
import gc
import json
import os
import pickle
import queue
import select
import socket
import subprocess
import sys
import threading
import time
from array import array
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import can

SYNC_COB_ID = 0x080
DEFAULT_PRIORITY = 80  # SCHED_FIFO 1..99: above the kernel's soft-IRQ threads' default 50
START_DELAY_S = 0.003  # the first SYNC of a schedule: this long after the request
# a SYNC never follows the frames of the cycle before it by less than this: a drive that latches a set point
# at SYNC wants it at least 100 us before (the XtrapulsPac's error 50, seed 003); after a stall of the engine
# the SYNC waits that long rather than make the set point late (it is late as a SYNC, within the drive's
# SYNC-loss window of 1.5 periods, instead)
MIN_GAP_AFTER_FRAMES_S = 150e-6
POLL_S = 0.0005  # a bus without a file descriptor is polled this often
# a one-off SYNC this late moves the ones queued after it (`sync_once`); less is the spin's overshoot and the send
ONCE_LATE_S = 200e-6
IDLE_WAIT_S = 0.05
_MCL_CURRENT, _MCL_FUTURE = 1, 2
_FLAG_EXT, _FLAG_RTR, _FLAG_ERR, _FLAG_OWN = 1, 2, 4, 8
MAX_PACKET = 1 << 20
BACKLOG_LIMIT = 100_000  # messages the master has not read (frames beyond it are dropped and counted)

# one frame between the processes: (time on the wire, COB-ID, data, flags)
WireFrame = tuple[float, int, bytes, int]


@dataclass(frozen=True)
class EngineSpec:
    """What the engine opens and how it asks for real time."""

    interface: str
    channel: str
    bitrate: int = 1_000_000
    priority: int | None = DEFAULT_PRIORITY  # None: do not ask for real-time priority
    lock_memory: bool = True
    # wake this long before a SYNC is due (at most half a period) and wait the rest actively: a wake-up is
    # late by up to a few hundred us here even at SCHED_FIFO (measured: p99 190 us) and by milliseconds
    # while another task runs in the kernel (this kernel preempts only at user level); a running engine is
    # not held up by either
    spin_us: int = 300


@dataclass(frozen=True)
class LateBatch:
    """Frames queued for the cycle after SYNC `cycle` that reached the engine only after SYNC `cycle` + 1 had
    gone out too: sent at once, before SYNC `visible_from`. `cob_ids` names them (a batch is one `send_at`),
    so the master knows whose frames were late: in one cycle some axes' frames may be in time, others not."""

    cycle: int
    cob_ids: tuple[int, ...]
    delay_s: float | None  # after SYNC cycle + 1 went out (None: not known)
    visible_from: int


@dataclass(frozen=True)
class RealtimeStatus:
    """What the engine got: SCHED_FIFO at `priority` (or not, and why), memory locked (or not)."""

    fifo: bool
    priority: int | None
    memory_locked: bool
    message: str


@dataclass
class EngineStats:
    """Counters of the engine since the schedule started (or the last reset)."""

    cycles: int = 0
    late_batches: int = 0  # batches that reached the engine after their SYNC went out
    late_frames: int = 0
    sync_overruns: int = 0  # SYNCs sent more than half a period after their time
    send_errors: int = 0
    # per cycle, microseconds: SYNC's send time - its scheduled time; the last frame of the cycle - SYNC
    sync_delay_us: list[int] = field(default_factory=list)
    cycle_latency_us: list[int] = field(default_factory=list)
    wake_delay_us: list[int] = field(default_factory=list)  # the loop saw the SYNC due this late
    # per batch the master queued for a cycle of the schedule: how long before that cycle's SYNC was due it
    # reached the engine (negative: after; a set point is late once this is below -period + 100 us). The
    # master's own stalls show here, whatever the wire did
    lead_us: list[int] = field(default_factory=list)


def engine_spec(interface: str, channel: str, bitrate: int) -> EngineSpec | None:
    """The cycle engine for a bus, or None where the master sends itself: python-can's `virtual` bus (it does not
    leave this process), or PVT_ENGINE=0 in the environment (tools/vcan-vm: one emulated CPU cannot carry the
    engine, the master and the drives as three processes; the engine's function is tested on the ipc bus)."""
    if interface == "virtual" or os.environ.get("PVT_ENGINE", "1") == "0":
        return None
    return EngineSpec(interface, str(channel), bitrate)


def request_realtime(priority: int | None, lock_memory: bool) -> RealtimeStatus:
    """SCHED_FIFO for the calling thread and mlockall for the process, where the system permits."""
    notes: list[str] = []
    fifo = False
    if priority is not None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            fifo = True
        except (PermissionError, OSError, AttributeError) as e:
            notes.append(f"no SCHED_FIFO priority {priority} ({e}): running best-effort; allow it with an rtprio "
                         "limit or CAP_SYS_NICE (README, 'Real-time priority')")
    locked = False
    if lock_memory:
        libc_name = ctypes.util.find_library("c")
        try:
            libc = ctypes.CDLL(libc_name, use_errno=True)
            locked = libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) == 0
            if not locked:
                notes.append(f"memory not locked (mlockall: {os.strerror(ctypes.get_errno())})")
        except (OSError, AttributeError) as e:
            notes.append(f"memory not locked ({e})")
    message = "; ".join(notes) if notes else (
        f"SCHED_FIFO priority {priority}, memory locked" if fifo else "best-effort (no priority asked)")
    return RealtimeStatus(fifo, priority if fifo else None, locked, message)


# a message longer than a packet goes in pieces: each starts with this byte (a pickle starts with its PROTO
# opcode, 0x80), then 1 on the last piece, else 0
_PIECE = 0x00
_PIECE_DATA = MAX_PACKET - 2


class _Channel:
    """One direction of the engine's link: pickled messages, one SOCK_SEQPACKET packet each, or pieces of one
    packet each where a message is longer than MAX_PACKET (the engine's statistics of a long job at 1 ms: one
    figure per cycle, four series, over 2 MB; cut at the receive buffer, it failed the run with "pickle data was
    truncated"). The engine's outgoing side never blocks (`backlog`); the master's side blocks on receive."""

    def __init__(self, sock: socket.socket, *, nonblocking_send: bool = False):
        self.sock = sock
        self.backlog: deque[bytes] = deque()
        self.dropped = 0
        # one receive buffer for every message: `sock.recv(MAX_PACKET)` makes a fresh 1 MB object per message,
        # which the engine's locked memory (mlockall MCL_FUTURE) faults in whole: 330 us per command here
        # (4 us into this buffer), 25-35 % of a core at 18 axes, and stretches of tens of ms without a SYNC's
        # answers forwarded when the master's commands came in a burst
        self._buffer = bytearray(MAX_PACKET)
        self._view = memoryview(self._buffer)
        self._recv_lock = threading.Lock()  # one reader of the buffer at a time (the master's side has threads)
        if nonblocking_send:
            sock.setblocking(False)

    def fileno(self) -> int:
        return self.sock.fileno()

    def send(self, msg: object) -> None:
        data = pickle.dumps(msg, protocol=pickle.HIGHEST_PROTOCOL)
        packets = [data] if len(data) <= MAX_PACKET else [
            bytes((_PIECE, int(i + _PIECE_DATA >= len(data)))) + data[i:i + _PIECE_DATA]
            for i in range(0, len(data), _PIECE_DATA)]
        if self.sock.getblocking():
            for packet in packets:
                self.sock.sendall(packet)
            return
        if len(self.backlog) + len(packets) > BACKLOG_LIMIT:
            self.dropped += 1
            return
        self.backlog.extend(packets)
        self.flush()

    def flush(self) -> None:
        """Non-blocking side: send what the socket takes now, keep the rest in order."""
        backlog = self.backlog
        while backlog:
            try:
                self.sock.send(backlog[0])
            except BlockingIOError:
                return
            backlog.popleft()

    def poll(self, timeout: float | None = 0.0) -> bool:
        ready, _, _ = select.select([self.sock], [], [], timeout)
        return bool(ready)

    def recv(self) -> Any:
        with self._recv_lock:
            pieces: list[bytes] = []
            while True:
                n = self.sock.recv_into(self._buffer)
                if not n:
                    raise EOFError("the other end closed")
                if self._buffer[0] != _PIECE:
                    if pieces:
                        raise EOFError("a message in pieces was cut short by another message")
                    return pickle.loads(self._view[:n])  # copies what it builds: the buffer is free again
                pieces.append(bytes(self._view[2:n]))
                if self._buffer[1]:
                    return pickle.loads(b"".join(pieces))

    def close(self) -> None:
        self.sock.close()


@contextlib.contextmanager
def thread_priority(priority: int | None) -> Any:
    """SCHED_FIFO at `priority` for the calling thread while the block runs (where permitted; else as it
    was), then its policy as before. Yields whether it got it."""
    if priority is None:
        yield False
        return
    try:
        before = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (PermissionError, OSError, AttributeError):
        yield False
        return
    try:
        yield True
    finally:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, before[0], before[1])


# ---- the engine process ------------------------------------------------------------------------------
class _Loop:
    """The engine's one loop (see the module docstring). Runs in the engine process."""

    def __init__(self, bus: can.BusABC, ctrl: _Channel, out: _Channel, spin_s: float = 0.0):
        self.bus = bus
        self.spin_max_s = spin_s
        self.spin_s = spin_s
        self.ctrl = ctrl
        self.out = out
        self.heard: list[WireFrame] = []
        self.sync_mark = (0, 0.0)  # the latest SYNC's place in `heard` and the time just before it was sent
        self.ring: dict[int, list[tuple[int, bytes, int]]] = {}
        self.t0: float | None = None
        self.period = 0.0
        self.counters: list[bytes] | None = None
        # the SYNC counter (CiA 301 0x1019) runs on across schedules and single SYNCs: a drive that sends a
        # TPDO every n-th SYNC from the counter's start value keeps counting SYNCs, so a counter that started
        # again at 1 after the standstill probe would no longer say which drives answer which SYNC
        self.counter_pos = 0
        self.cycle = 0  # the next SYNC to send
        self.last_frame_t = 0.0  # when the last frame of the latest cycle went out
        self.once: list[float] = []  # single SYNCs at absolute times (no schedule running)
        self.sync_sent_at: dict[int, float] = {}
        self.stats = EngineStats()
        self._delay = array("i")
        self._latency = array("i")
        self._woke = array("i")
        self._lead = array("q")
        self.closing = False

    # ---- sending
    def _send(self, cob_id: int, data: bytes, flags: int) -> float | None:
        msg = can.Message(arbitration_id=cob_id, data=data, is_extended_id=bool(flags & _FLAG_EXT),
                          is_remote_frame=bool(flags & _FLAG_RTR))
        before = time.time()
        try:
            self.bus.send(msg)
        except can.CanError as e:
            self.stats.send_errors += 1
            self.out.send(("send_failed", cob_id, f"{type(e).__name__}: {e}"))
            return None
        # the frame's time on the wire: the bus's own stamp where it gives one (ipc: the stamp every drive
        # sees), else now. A note taken after `send` returns can be later than the stamp (the engine preempted
        # in its datagrams to the peers): in a failed run here, of a SYNC that left 1.2 ms late, a drive with
        # its own clock reported a demand that put the SYNC at least 0.26 ms before the master's note, a tick
        # "behind" it: PROTOCOL
        t = msg.timestamp if msg.timestamp >= before else time.time()
        self.heard.append((t, cob_id, data, flags | _FLAG_OWN))
        if cob_id != SYNC_COB_ID:
            self.last_frame_t = t
        return t

    def _send_sync(self) -> float | None:
        """SYNC with the next counter, its place in `heard` and the time before it left noted
        (`_flush_in_wire_order` forwards what was on the wire before it first)."""
        data = self._next_counter()
        self.sync_mark = (len(self.heard), time.time())
        return self._send(SYNC_COB_ID, data, 0)

    def _send_all(self, frames: Sequence[tuple[int, bytes, int]]) -> float | None:
        last = None
        for cob_id, data, flags in frames:
            last = self._send(cob_id, data, flags) or last
        return last

    def _sync(self) -> None:
        """SYNC `self.cycle`, then the frames queued for it."""
        assert self.t0 is not None
        n = self.cycle
        due = self.t0 + n * self.period
        woke = time.time()
        t = self._send_sync()
        if t is None:  # the bus refused SYNC: the schedule stops (as python-can's periodic task does)
            self.out.send(("sync_failed", n))
            self.t0 = None
            return
        frames = self.ring.pop(n, None)
        last = self._send_all(frames) if frames else None
        self.sync_sent_at[n] = t
        self.sync_sent_at.pop(n - 256, None)
        self.cycle = n + 1
        st = self.stats
        st.cycles += 1
        delay = t - due
        if delay > 0.5 * self.period:
            st.sync_overruns += 1
        self._delay.append(int(delay * 1e6))
        self._latency.append(int(((last or t) - t) * 1e6))
        self._woke.append(int((woke - due) * 1e6))

    def _next_counter(self) -> bytes:
        if not self.counters:
            return b""
        data = self.counters[self.counter_pos % len(self.counters)]
        self.counter_pos += 1
        return data

    def _set_counters(self, counters: Sequence[bytes] | None) -> None:
        new = list(counters) if counters else None
        if new != self.counters:
            self.counters = new
            self.counter_pos = 0

    # ---- receiving
    def _read_bus(self) -> None:
        recv = self.bus.recv
        while True:
            msg = recv(0.0)
            if msg is None:
                return
            flags = ((_FLAG_EXT if msg.is_extended_id else 0) | (_FLAG_RTR if msg.is_remote_frame else 0)
                     | (_FLAG_ERR if msg.is_error_frame else 0))
            self.heard.append((msg.timestamp, msg.arbitration_id, bytes(msg.data), flags))

    def _flush_in_wire_order(self) -> None:
        """After a SYNC: what arrived before it is read only now (the SYNC and its cycle's frames go out
        first: reading 18 axes' TPDOs before the SYNC held it up to 1.2 ms here), and what was on the wire
        before the SYNC left is still forwarded before it, as when it was read first."""
        heard = self.heard
        n = len(heard)
        self._read_bus()
        mark, before = self.sync_mark
        early = [f for f in heard[n:] if f[0] < before]  # stamped before the SYNC left
        if early:
            self.heard = heard[:mark] + early + heard[mark:n] + [f for f in heard[n:] if f[0] >= before]
        self._flush()

    def _flush(self) -> None:
        if self.heard:
            self.out.send(("rx", self.heard))
            self.heard = []
        else:
            self.out.flush()

    # ---- control
    def _control(self, msg: tuple[Any, ...]) -> None:
        kind = msg[0]
        if kind == "send":
            self._send_all(msg[1])
        elif kind == "at":
            n, frames = msg[1], msg[2]
            if self.t0 is None:
                self._send_all(frames)
                return
            self._lead.append(int((self.t0 + n * self.period - time.time()) * 1e6))
            if n < self.cycle:  # its SYNC is out already: send now, still in time while the next one is not
                self._send_all(frames)
                if n < self.cycle - 1:  # the next SYNC is out too: too late for a synchronous frame; say so
                    sent = self.sync_sent_at.get(n + 1)
                    self.stats.late_batches += 1
                    self.stats.late_frames += len(frames)
                    delay = None if sent is None else time.time() - sent
                    self.out.send(("late", n, tuple(f[0] for f in frames), delay, self.cycle))
            else:
                self.ring.setdefault(n, []).extend(frames)
        elif kind == "sync_start":
            period, counters = msg[1], msg[2]
            self.period = float(period)
            self.spin_s = min(self.spin_max_s, 0.5 * self.period)
            self._set_counters(counters)
            self.cycle = 0
            self.ring.clear()
            self.sync_sent_at.clear()
            self.t0 = time.time() + START_DELAY_S
            self.out.send(("sync_started", self.t0, self.period, self.counter_pos))
        elif kind == "sync_once":  # one SYNC at an absolute time, outside a schedule (the standstill probe)
            self._set_counters(msg[2])
            self.once.extend(msg[1])
            self.once.sort()
        elif kind == "sync_stop":
            self.t0 = None
            dropped = sum(len(v) for v in self.ring.values())
            self.ring.clear()
            self.out.send(("sync_stopped", self.cycle, dropped))
        elif kind == "stats":
            st = self.stats
            st.sync_delay_us = self._delay.tolist()
            st.cycle_latency_us = self._latency.tolist()
            st.wake_delay_us = self._woke.tolist()
            st.lead_us = self._lead.tolist()
            self.out.send(("stats", st))
            if msg[1]:
                self.stats = EngineStats()
                self._delay = array("i")
                self._latency = array("i")
                self._woke = array("i")
                self._lead = array("q")
            else:
                st.sync_delay_us, st.cycle_latency_us, st.wake_delay_us, st.lead_us = [], [], [], []
        elif kind == "close":
            self.closing = True
        else:
            self.out.send(("error", f"unknown engine command {kind!r}"))

    def _next_due(self) -> float | None:
        """When the next SYNC goes out: its time on the schedule, or a one-off SYNC's; never less than
        MIN_GAP_AFTER_FRAMES_S after the last frame."""
        if self.t0 is not None:
            return max(self.t0 + self.cycle * self.period, self.last_frame_t + MIN_GAP_AFTER_FRAMES_S)
        return self.once[0] if self.once else None

    def run(self) -> None:
        fd = _fileno(self.bus)
        rlist: list[Any] = [self.ctrl] + ([fd] if fd is not None else [])
        while not self.closing:
            if self.t0 is not None:
                due = self._next_due()
                assert due is not None
                wait = due - time.time()
                if wait <= self.spin_s:
                    while time.time() < due:
                        pass
                    self._sync()
                    self._flush_in_wire_order()
                    continue
                wait -= self.spin_s
            elif self.once:
                due = self.once[0]
                wait = due - time.time()
                if wait <= self.spin_s:
                    while time.time() < due:
                        pass
                    self.once.pop(0)
                    self._send_sync()
                    # the one-off SYNCs after a late one keep their intervals to it: the probe's intervals
                    # are its experiment, and catching up would shorten the one after the late SYNC (late:
                    # when it left, a preemption in the send included)
                    late = time.time() - due
                    if late > ONCE_LATE_S:
                        self.once = [t + late for t in self.once]
                    self._flush_in_wire_order()
                    continue
                wait -= self.spin_s
            else:
                wait = IDLE_WAIT_S
            if fd is None:
                wait = min(wait, POLL_S)
            wlist = [self.out] if self.out.backlog else []
            ready, _, _ = select.select(rlist, wlist, [], wait)
            self._read_bus()
            if self.ctrl in ready:
                # the master's commands until the next SYNC is near: a burst of them (the master catching up
                # after a stall) waits for the SYNC, never the SYNC for them
                due = self._next_due()
                while self.ctrl.poll():
                    self._control(self.ctrl.recv())
                    if self.closing or (due is not None and time.time() >= due - self.spin_s - POLL_S):
                        break
            self._flush()


def _fileno(bus: can.BusABC) -> int | None:
    try:
        fd = bus.fileno()
    except (NotImplementedError, AttributeError, OSError):
        return None
    return fd if isinstance(fd, int) and fd >= 0 else None


def engine_main(spec: EngineSpec, ctrl: _Channel, out: _Channel) -> None:
    """The engine process' work: real time where permitted, open the bus, run the loop until told to close."""
    status = request_realtime(spec.priority, spec.lock_memory)
    from bus import ipc  # noqa: F401  (registers the "ipc" interface in this process)

    try:
        can_bus = can.Bus(interface=spec.interface, channel=spec.channel, bitrate=spec.bitrate)
    except Exception as e:  # python-can raises many types
        out.send(("error", f"cannot open CAN bus {spec.interface}:{spec.channel}: {type(e).__name__}: {e}"))
        return
    gc.collect()
    gc.freeze()
    gc.disable()
    out.send(("ready", status))
    loop = _Loop(can_bus, ctrl, out, spec.spin_us / 1e6 if status.fifo else 0.0)  # spin only where it preempts
    try:
        loop.run()
    except (EOFError, BrokenPipeError, ConnectionResetError):
        pass  # the master went away: leave the bus
    finally:
        with contextlib.suppress(Exception):
            can_bus.shutdown()


def main(argv: Sequence[str] | None = None) -> None:
    """`python -m bus.engine --ctrl FD --out FD --spec JSON`: started by `EngineBus`, not by hand."""
    p = argparse.ArgumentParser(prog="python -m bus.engine")
    p.add_argument("--ctrl", type=int, required=True)
    p.add_argument("--out", type=int, required=True)
    p.add_argument("--spec", required=True)
    args = p.parse_args(argv)
    spec = EngineSpec(**json.loads(args.spec))
    ctrl = _Channel(socket.socket(fileno=args.ctrl))
    out = _Channel(socket.socket(fileno=args.out), nonblocking_send=True)
    engine_main(spec, ctrl, out)


# ---- the master's side --------------------------------------------------------------------------------
class EngineError(RuntimeError):
    pass


class EngineBus(can.BusABC):
    """The master's handle on the engine process: a python-can bus (see the module docstring)."""

    def __init__(self, channel: Any = None, *, spec: EngineSpec, receive_own_messages: bool = True,
                 start_timeout_s: float = 20.0, **kwargs: Any):
        self.spec = spec
        self.channel_info = f"cycle engine on {spec.interface}:{spec.channel}"
        self._own = receive_own_messages
        ctrl_ours, ctrl_theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        out_ours, out_theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        for sk in (ctrl_ours, ctrl_theirs, out_ours, out_theirs):
            sk.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 22)
            sk.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        self._ctrl = _Channel(ctrl_ours)
        self._in = _Channel(out_ours)
        cmd = [sys.executable, "-m", "bus.engine", "--ctrl", str(ctrl_theirs.fileno()), "--out",
               str(out_theirs.fileno()), "--spec", json.dumps(dataclasses.asdict(spec))]
        self._proc = subprocess.Popen(cmd, pass_fds=(ctrl_theirs.fileno(), out_theirs.fileno()),
                                      stdin=subprocess.DEVNULL)
        ctrl_theirs.close()
        out_theirs.close()
        self._send_lock = threading.Lock()
        self._pending: deque[can.Message] = deque()
        self._replies: queue.Queue[tuple[Any, ...]] = queue.Queue()
        self._closed = False
        self.schedule: tuple[float, float] | None = None  # (t0, period) while the engine sends SYNC
        self.counter_start = 0  # SYNC n of the schedule carries counters[(counter_start + n) % len(counters)]
        self.late: list[LateBatch] = []
        self.on_late: Callable[[LateBatch], None] | None = None
        self.on_send_failed: Callable[[int, str], None] | None = None
        if not self._in.poll(start_timeout_s):
            self._proc.kill()
            self._proc.wait()
            raise EngineError(f"the cycle engine did not start within {start_timeout_s} s")
        try:
            first = self._in.recv()
        except EOFError:
            first = ("error", f"the engine process ended at start (exit status {self._proc.wait()})")
        if first[0] != "ready":
            with contextlib.suppress(subprocess.TimeoutExpired):
                self._proc.wait(2.0)
            raise EngineError(str(first[1]))
        self.realtime: RealtimeStatus = first[1]
        super().__init__(channel=channel, **kwargs)

    # ---- python-can
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._command(("send", [(msg.arbitration_id, bytes(msg.data), _flags(msg))]))

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._pending:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            if self._closed:
                return None, False
            try:
                if not self._in.poll(left):
                    return None, False
                item = self._in.recv()
            except (EOFError, OSError):
                if self._closed:
                    return None, False
                raise can.CanOperationError("the cycle engine process ended") from None
            self._take(item)
        return self._pending.popleft(), False

    def _take(self, item: tuple[Any, ...]) -> None:
        kind = item[0]
        if kind == "rx":
            channel = self.spec.channel  # as the bus names it (a candump log's channel has no spaces)
            for t, cob_id, data, flags in item[1]:
                own = bool(flags & _FLAG_OWN)
                if own and not self._own:
                    continue
                self._pending.append(can.Message(
                    timestamp=t, arbitration_id=cob_id, data=data, is_extended_id=bool(flags & _FLAG_EXT),
                    is_remote_frame=bool(flags & _FLAG_RTR), is_error_frame=bool(flags & _FLAG_ERR),
                    is_rx=not own, channel=channel))
        elif kind == "sync_started":
            self.schedule = (item[1], item[2])
            self.counter_start = item[3]
            self._replies.put(item)
        elif kind in ("sync_stopped", "stats"):
            self._replies.put(item)
        elif kind == "sync_failed":
            self.schedule = None
            if self.on_send_failed is not None:
                self.on_send_failed(SYNC_COB_ID, f"SYNC {item[1]} refused by the bus: the engine's schedule stopped")
        elif kind == "late":
            late = LateBatch(item[1], item[2], item[3], item[4])
            self.late.append(late)
            if self.on_late is not None:
                self.on_late(late)
        elif kind == "send_failed":
            if self.on_send_failed is not None:
                self.on_send_failed(item[1], item[2])
        elif kind == "error":
            raise can.CanOperationError(f"cycle engine: {item[1]}")

    # ---- the engine's own verbs
    def send_at(self, cycle: int, frames: Sequence[tuple[int, bytes]]) -> None:
        """Queue frames to go out right after SYNC `cycle` (counted from `start_sync`, 0 first)."""
        if frames:
            self._command(("at", cycle, [(c, bytes(d), 0) for c, d in frames]))

    def start_sync(self, period_s: float, counters: Sequence[int] | None = None, timeout_s: float = 5.0) -> float:
        """Start the engine's SYNC schedule; returns t0, the time of SYNC 0 (then one every period_s)."""
        self._command(("sync_start", float(period_s), [bytes([c]) for c in counters] if counters else None))
        reply = self._reply("sync_started", timeout_s)
        return float(reply[1])

    def sync_once(self, at: float | Sequence[float], counters: Sequence[int] | None = None) -> None:
        """One SYNC at time `at` (time.time() base), or one at each of the times `at`, when no schedule runs;
        with `counters` each carries the next of them (the counter runs on from the last SYNC sent). One that
        goes out late moves every one-off SYNC queued after it as late: their intervals hold (the standstill
        probe's experiments). Several times go over in one command, so none is sent before the rest are
        queued to move with it."""
        times = [float(at)] if isinstance(at, int | float) else [float(t) for t in at]
        self._command(("sync_once", times, [bytes([c]) for c in counters] if counters else None))

    def stop_sync(self, timeout_s: float = 5.0) -> None:
        if self.schedule is None:
            return
        self.schedule = None
        self._command(("sync_stop",))
        self._reply("sync_stopped", timeout_s)

    def stats(self, *, reset: bool = False, timeout_s: float = 10.0) -> EngineStats:
        self._command(("stats", reset))
        reply: EngineStats = self._reply("stats", timeout_s)[1]
        return reply

    def _reply(self, kind: str, timeout_s: float) -> tuple[Any, ...]:
        """The engine's answer, read by whichever thread reads the frames (a Notifier), or here when none does."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                item = self._replies.get(timeout=0.01)
            except queue.Empty:
                if time.monotonic() > deadline:
                    raise EngineError(f"the cycle engine did not answer {kind!r} within {timeout_s} s") from None
                continue
            if item[0] == kind:
                return item

    def _command(self, msg: tuple[Any, ...]) -> None:
        if self._closed:
            raise can.CanOperationError("the cycle engine is closed")
        with self._send_lock:
            try:
                self._ctrl.send(msg)
            except OSError as e:
                raise can.CanOperationError(f"the cycle engine process ended: {e}") from None

    def shutdown(self) -> None:
        if self._closed:
            return
        with contextlib.suppress(Exception):
            self._command(("close",))
        self._closed = True
        try:
            self._proc.wait(5.0)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        with contextlib.suppress(Exception):
            self._ctrl.close()
        super().shutdown()


def _flags(msg: can.Message) -> int:
    return (_FLAG_EXT if msg.is_extended_id else 0) | (_FLAG_RTR if msg.is_remote_frame else 0)


if __name__ == "__main__":
    # run the module's own copy (`bus.engine`, not `__main__`), so what it pickles names bus.engine's classes
    from bus.engine import main as engine_entry

    engine_entry()
