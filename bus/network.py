"""The master-side bus adapter: python-can + canopen in, `bus.events` out, `Send` actions back out.

Owns one python-can bus, a canopen `Network` (SDO only), the SYNC producer, a receive listener and a
monitor thread. `configure_drives()` surveys every drive, writes the profile's SDO configuration, reads
it back and starts NMT; a missing essential object, no answer, an abort or a wrong read-back raises
`BusError` naming the node, the object and why the product needs it. Received frames become events in bus
order (TPDO1, TPDO2, EMCY, boot-up, our own SYNC echo -> Sync and BusLoad), TPDOs tagged with the newest
SYNC on the wire; with `cell.time_stamp` 0x1013 follows each SYNC echo (seed 001). The monitor consumes
heartbeats and checks SYNC echoes. A malformed frame or adapter exception becomes an `AdapterError` event;
a subscriber's exception is re-raised (`BusError(CALLBACK)`) by the next `send`, `check` or `close`.
Callbacks run one at a time and must not block on the bus (an SDO answer would arrive on their thread).
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from typing import Any

import can
import canopen
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from bus import cob, codec, virtual_can
from bus.budget import cell_feedback_every
from bus.engine import EngineBus, EngineSpec
from bus.errors import (
    BUS_OPEN,
    CALLBACK,
    CLOSED,
    CONFIG,
    MISSING_OBJECT,
    NO_RESPONSE,
    SDO_ABORT,
    SEND_FAILED,
    VERIFY,
    BusError,
    ProtocolError,
)
from bus.events import AdapterError, BusLoad, Event, HeartbeatLost, RecordOnWire, SendFailed, Sync
from bus.families import PROFILES, setpoint_slots
from bus.probe import AbsentObject, WriteOnly
from bus.profile import DriveProfile, FeedbackSchedule, SdoWrite, feedback_schedule, frame_to_event
from planner.config import AxisConfig, BusConfig, CellConfig
from planner.readings import OPTIONAL_OBJECTS

virtual_can.register()  # python-can's virtual bus, delivering every frame in one order (bus/virtual_can.py)

EventCallback = Callable[[Event], None]
ABORT_NO_OBJECT = 0x06020000
ABORT_NO_SUBINDEX = 0x06090011
ABORT_WRITE_ONLY = 0x06010001
ABORT_UNSUPPORTED_ACCESS = 0x06010000
MONITOR_PERIOD_S = 0.02
NOTIFIER_CYCLE_S = 0.1  # canopen's default 1 s makes every close() wait up to 1 s


def open_bus(bus_config: BusConfig, **extra: Any) -> can.BusABC:
    """A python-can bus from `BusConfig` (interface, channel, bitrate). Raises BusError(BUS_OPEN)."""
    import bus.ipc  # noqa: F401  (our "ipc" interface, for processes that did not install the entry point)

    try:
        return can.Bus(interface=bus_config.interface, channel=bus_config.channel, bitrate=bus_config.bitrate,
                       **extra)
    except Exception as e:  # python-can raises many types (CanInterfaceNotImplementedError, OSError, ...)
        raise BusError(BUS_OPEN, f"cannot open CAN bus {bus_config.interface}:{bus_config.channel}: {e}",
                       detail={"interface": bus_config.interface, "channel": str(bus_config.channel)}) from e


def open_engine(spec: EngineSpec) -> EngineBus:
    """The cycle engine process on `spec`'s bus (bus/engine.py). Raises BusError(BUS_OPEN)."""
    if spec.interface == "virtual":
        raise BusError(BUS_OPEN, "the cycle engine runs in a process of its own and python-can's virtual bus does "
                       "not leave its process: use the ipc bus (interface 'ipc', bus/ipc.py) or socketcan",
                       detail={"interface": spec.interface})
    try:
        return EngineBus(spec=spec)
    except Exception as e:
        raise BusError(BUS_OPEN, f"cannot start the cycle engine on {spec.interface}:{spec.channel}: {e}",
                       detail={"interface": spec.interface, "channel": str(spec.channel)}) from e


# with the cycle engine: the receive thread's SCHED_FIFO priority, below the engine's 80 and the streaming thread's
# 65 (streamer/runtime/realtime.py STREAMING_PRIORITY says why)
RECEIVE_PRIORITY = 60


class _MasterListener(can.Listener):
    def __init__(self, adapter: MasterAdapter):
        self.adapter = adapter
        self._prioritised = adapter.receive_priority is None

    def on_message_received(self, msg: can.Message) -> None:
        if not self._prioritised:
            self._prioritised = True
            with contextlib.suppress(PermissionError, OSError):  # best-effort where refused (the engine says so)
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.adapter.receive_priority or 1))
        self.adapter._on_message(msg)

    def on_error(self, exc: Exception) -> None:
        self.adapter._emit(AdapterError("receive", f"{type(exc).__name__}: {exc}", self.adapter.now()))

    def stop(self) -> None:
        pass


class MasterAdapter:
    """Callback-based master: `on_event(cb)`, `configure_drives()`, `send()`, `start_sync()`, `close()`."""

    def __init__(
        self,
        bus_config: BusConfig | None,
        cell: CellConfig,
        *,
        profile: DriveProfile | None = None,
        bus: can.BusABC | None = None,
        sdo_timeout_s: float = 0.3,
        sdo_attempts: int = 1,
        eds_path: str | None = None,
        clock: Callable[[], float] = time.time,
        engine: EngineSpec | None = None,
        receive_priority: int | None = None,
    ):
        self.cell = cell
        self.bus_config = bus_config or cell.bus
        # each axis' family (bus/families.py), or `profile` for all of them
        self.profiles: dict[int, DriveProfile] = {
            a.node_id: profile if profile is not None else PROFILES[a.profile] for a in cell.axes}
        self.slots = setpoint_slots(cell.axes)
        self.clock = clock
        self.nodes = frozenset(a.node_id for a in cell.axes)
        self.failures: list[BusError] = []
        # received frames that mean nothing here ("unknown_cob_id", "other_node") or do not decode
        # ("malformed", also reported as AdapterError): counted, never an exception
        self.counters: Counter[str] = Counter()
        self._callbacks: list[EventCallback] = []
        self._emit_lock = threading.RLock()
        self._closed = False
        self._own_bus = bus is None
        # with `engine`, a process of its own owns the bus and sends SYNC and each cycle's frames (bus/engine.py)
        self.engine: EngineBus | None = None
        if bus is None and engine is not None:
            self.engine = open_engine(engine)
            if receive_priority is None:
                receive_priority = RECEIVE_PRIORITY  # the way in of the cycle's answers
            bus = self.engine
            self._own_bus = True
        self._bus = bus if bus is not None else open_bus(self.bus_config, receive_own_messages=True)
        # SCHED_FIFO of the receive thread, where permitted (None: as it is)
        self.receive_priority = receive_priority
        self._network = canopen.Network(self._bus)
        self._network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
        listeners: list[Any] = self._network.listeners
        listeners.append(_MasterListener(self))
        self.remote: dict[int, canopen.RemoteNode] = {}
        for axis in cell.axes:
            path = eds_path or self.profiles[axis.node_id].eds_path
            node = canopen.RemoteNode(axis.node_id, canopen.objectdictionary.import_od(path, axis.node_id))
            node.sdo.RESPONSE_TIMEOUT = sdo_timeout_s
            node.sdo.MAX_RETRIES = max(1, sdo_attempts)  # canopen: attempts; 0 would retry forever
            self._network.add_node(node)
            self.remote[axis.node_id] = node
        self._sync_task: Any = None
        self._sync_count = 0
        self.absent: dict[int, tuple[int, ...]] = {}  # node -> optional objects it lacks (after the survey)
        self.feedback: FeedbackSchedule | None = None  # TPDO2 schedule (after configure_drives)
        self._sync_started_at: float | None = None
        self._sync_period_s = cell.sync_period_s
        self._sync_echo_warned = False
        self._last_sync_t: float | None = None
        self._window_bits = 0
        self._bitrate = max(1, int(self.bus_config.bitrate))
        self._hb_last: dict[int, float] = {}
        self._hb_armed: set[int] = set()
        self._hb_lost: set[int] = set()
        self._hb_timeout_s = cell.drive.heartbeat_timeout_ms / 1000.0
        self._stop = threading.Event()
        self._network.connect()
        self._monitor = threading.Thread(target=self._run_monitor, name="pvt-master-monitor", daemon=True)
        self._monitor.start()

    # ---- public API ---------------------------------------------------------------------------------
    def now(self) -> float:
        return self.clock()

    def on_event(self, callback: EventCallback) -> None:
        """Subscribe to every event (called on the adapter's threads, one event at a time)."""
        self._callbacks.append(callback)

    def add_listener(self, listener: can.Listener) -> None:
        """Also hand every received frame (own frames included) to a python-can `Listener` (a trace
        tap, a logger), on the receive thread, after the adapter's own processing."""
        self._check_open()
        notifier = self._network.notifier
        if notifier is None:  # pragma: no cover - connect() always creates it
            raise BusError(CLOSED, "the bus adapter has no running notifier")
        notifier.add_listener(listener)

    def configure_drives(self, *, start: bool = True, feedback_every: int | None = None) -> None:
        """Survey, configure and verify every drive of the cell over SDO, then (if `start`) NMT start them.
        `feedback_every`: TPDO2 every n-th SYNC (default: what the cell needs, bus.budget)."""
        self._check_open()
        for axis in self.cell.axes:
            self.nmt(codec.NmtCommand.ENTER_PRE_OPERATIONAL, axis.node_id)
            self.absent[axis.node_id] = self.survey(axis.node_id)
        every = feedback_every if feedback_every is not None else cell_feedback_every(self.cell)
        self.feedback = feedback_schedule([a.node_id for a in self.cell.axes], every,
                                          all(0x1019 not in self.absent[a.node_id] for a in self.cell.axes))
        for axis in self.cell.axes:
            self.configure_drive(axis)
        if start:
            for axis in self.cell.axes:
                self.nmt(codec.NmtCommand.START, axis.node_id)

    def read_object(self, node_id: int, index: int, sub: int = 0) -> int:
        """An SDO read for the survey and the probe: AbsentObject / WriteOnly for those aborts."""
        try:
            return self.read(node_id, index, sub)
        except BusError as e:
            code = e.detail.get("abort_code") if e.detail else None
            if code in (ABORT_NO_OBJECT, ABORT_NO_SUBINDEX):
                raise AbsentObject(f"0x{index:04X}:{sub:02X}") from None
            if code in (ABORT_WRITE_ONLY, ABORT_UNSUPPORTED_ACCESS):
                raise WriteOnly(f"0x{index:04X}:{sub:02X}") from None
            raise

    def survey(self, node_id: int) -> tuple[int, ...]:
        """The optional objects a drive lacks; checks an EPOS' interpolation period (0x60C2) is 1 ms, the
        tick the product's interpolation model (planner.encoding.hermite) assumes. Raises BusError for anything else."""
        profile = self.profiles[node_id]
        self.read(node_id, profile.obj("device_type").index)
        absent: list[int] = []
        od = self._remote(node_id).object_dictionary
        for index in OPTIONAL_OBJECTS:
            if index not in od:
                absent.append(index)  # not in the family's EDS (a DS-301 v4.01 drive has no 0x1012/0x1019)
                continue
            sub = 1 if index in (0x1010, 0x1011, 0x60C2) else 0
            try:
                self.read_object(node_id, index, sub)
            except (AbsentObject, WriteOnly) as e:
                if isinstance(e, AbsentObject):
                    absent.append(index)
        if 0x60C2 not in absent and profile.kind == "fifo":
            value = self.read(node_id, 0x60C2, 1)
            exp = self.read(node_id, 0x60C2, 2)
            exp = exp - 256 if exp > 127 else exp
            if value * 10.0 ** exp != 1e-3:
                raise BusError(CONFIG, f"node {node_id}: interpolation period 0x60C2 is {value} x 10^{exp} s; the "
                               "product interpolates at 1 ms (seed 000 4.3.6.4)", node=node_id, obj=(0x60C2, 1))
        return tuple(absent)

    def configure_drive(self, axis: AxisConfig) -> None:
        node = self._remote(axis.node_id)
        n = axis.node_id
        self.nmt(codec.NmtCommand.ENTER_PRE_OPERATIONAL, n)
        absent = self.absent.get(n)
        if absent is None:
            absent = self.absent[n] = self.survey(n)
        profile = self.profiles[n]
        writes = [w for w in profile.configuration(axis, self.cell.drive, self.cell.sync_period_ms,
                                                   feedback=self.feedback, time_stamp=self.cell.time_stamp,
                                                   slot=self.slots.get(n))
                  if w.index not in absent]
        for w in writes:
            try:
                self._write(node, w)
            except BusError as e:
                code = e.detail.get("abort_code") if e.detail else None
                if code in (ABORT_NO_OBJECT, ABORT_NO_SUBINDEX) and w.essential:
                    raise BusError(MISSING_OBJECT, f"node {n} has no object {w.ref} ({w.what}): {w.why}; the "
                                   "product cannot run this drive without it", node=n,
                                   obj=(w.index, w.sub)) from None
                raise
        final: dict[tuple[int, int], SdoWrite] = {}
        for w in writes:
            if w.verify:
                final[(w.index, w.sub)] = w
            else:
                final.pop((w.index, w.sub), None)
        for w in final.values():
            got = self.read(axis.node_id, w.index, w.sub)
            if got != w.value:
                raise BusError(VERIFY, f"node {axis.node_id} reads back {got} from {w.ref} ({w.what}), "
                               f"wrote {w.value}", node=axis.node_id, obj=(w.index, w.sub),
                               detail={"wrote": w.value, "read": got})
        with self._emit_lock:
            self._hb_armed.add(axis.node_id)
            self._hb_last[axis.node_id] = self.now()
            self._hb_lost.discard(axis.node_id)

    def enable_drives(self, *, timeout_s: float = 1.0) -> None:
        """Bring every drive to operation enabled, ready for a job (over SDO): the set point objects = the
        drive's position (cyclic families, so that enabling moves nothing), fault reset if faulted,
        shutdown 0x0006, switch on + enable operation 0x000F (bit 4 low, so the streamer's start is a
        rising edge), then the family's writes (EPOS: buffer clear 0x60C4:06 = 0 then enable = 1, verified
        by reading 0x20C4:01 back). Raises BusError naming the node otherwise."""
        S = codec.Cia402State
        for axis in self.cell.axes:
            n = axis.node_id
            profile = self.profiles[n]
            cw = profile.obj("controlword")
            sw = profile.obj("statusword")
            state = codec.state_from_statusword(self.read(n, sw.index, sw.sub))
            reaction_ends = self.now() + timeout_s
            while state == S.FAULT_REACTION_ACTIVE and self.now() < reaction_ends:
                time.sleep(0.005)  # the drive is still ramping down: it enters FAULT by itself (CiA 402)
                state = codec.state_from_statusword(self.read(n, sw.index, sw.sub))
            commands: list[codec.Command] = []
            if state == S.FAULT:
                commands += [codec.Command.DISABLE_VOLTAGE, codec.Command.FAULT_RESET]
            elif state in (S.QUICK_STOP_ACTIVE, S.FAULT_REACTION_ACTIVE, S.NOT_READY_TO_SWITCH_ON):
                commands.append(codec.Command.DISABLE_VOLTAGE)  # quick stop active, fault reaction
            if state != S.OPERATION_ENABLED:
                commands.append(codec.Command.SHUTDOWN)
            commands.append(codec.Command.ENABLE_OPERATION)  # in OE: bit 4 low (ends an old ip run)
            if profile.hold_objects:
                here = self.read(n, *profile.obj("position_actual"))
                for w in profile.hold_writes(here):
                    self._write(self._remote(n), w)
            for command in commands:
                self.write(n, cw.index, cw.sub, command.value)
            deadline = self.now() + timeout_s
            while True:
                state = codec.state_from_statusword(self.read(n, sw.index, sw.sub))
                if state == codec.Cia402State.OPERATION_ENABLED:
                    break
                if self.now() > deadline:
                    raise BusError(VERIFY, f"node {n} is {state.value!r}, not operation enabled, after "
                                   f"0x0006/0x000F on 0x6040", node=n, obj=(sw.index, sw.sub))
                time.sleep(0.005)
            for name, value in profile.after_enable:
                ref = profile.obj(name)
                self.write(n, ref.index, ref.sub, value)
            if profile.has("buffer_status"):
                bs = profile.obj("buffer_status")
                status = codec.decode_buffer_status(self.read(n, bs.index, bs.sub))
                if not status.buffer_enabled or status.any_error:
                    clear = profile.obj("buffer_clear")
                    raise BusError(VERIFY, f"node {n}: ip buffer not enabled and clean after 0x60C4:06 = 0, 1 "
                                   f"({status})", node=n, obj=(clear.index, clear.sub))

    def read(self, node_id: int, index: int, sub: int = 0) -> int:
        """SDO upload of an integer object. Raises BusError naming node and object."""
        var = self._sdo_var(self._remote(node_id), index, sub)
        try:
            value = var.raw
        except SdoCommunicationError as e:
            raise BusError(NO_RESPONSE, f"node {node_id} did not answer reading 0x{index:04X}:{sub:02X}: {e}",
                           node=node_id, obj=(index, sub)) from None
        except SdoAbortedError as e:
            raise BusError(SDO_ABORT, f"node {node_id} refused reading 0x{index:04X}:{sub:02X}: "
                           f"abort 0x{e.code:08X} ({e})", node=node_id, obj=(index, sub),
                           detail={"abort_code": e.code}) from None
        if not isinstance(value, int):
            raise BusError(CONFIG, f"0x{index:04X}:{sub:02X} of node {node_id} is not an integer object",
                           node=node_id, obj=(index, sub))
        return value

    def write(self, node_id: int, index: int, sub: int, value: int) -> None:
        self._write(self._remote(node_id), SdoWrite(index, sub, value, "write"))

    def nmt(self, command: codec.NmtCommand, node_id: int = 0) -> None:
        frame = codec.nmt_frame(command, node_id)
        self.send(frame.cob_id, frame.data)

    def send(self, cob_id: int, data: bytes) -> None:
        """Send one frame now. Raises BusError(SEND_FAILED) when the bus refuses it (the caller emits
        SendFailed), BusError(CLOSED) after close, BusError(CALLBACK) for a pending callback failure."""
        self._check_open()
        self.check()
        try:
            self._network.send_message(cob_id, bytes(data))
        except Exception as e:
            raise BusError(SEND_FAILED,
                           f"bus refused frame 0x{cob_id:03X} [{len(data)}]: {type(e).__name__}: {e}",
                           detail={"cob_id": cob_id}) from None

    def start_sync(self, period_s: float | None = None) -> None:
        """Start the SYNC producer (python-can periodic send) at `period_s` (default: the cell's)."""
        self._check_open()
        self.stop_sync()
        period = self.cell.sync_period_s if period_s is None else float(period_s)
        if not period > 0:
            raise BusError(CONFIG, f"SYNC period must be > 0, got {period}")
        frame = codec.sync_frame()
        fb = self.feedback
        if fb is not None:
            # the SYNC counter 1..N (CiA 301 0x1019): the periodic task cycles through N frames
            msgs: Any = [can.Message(arbitration_id=frame.cob_id, data=bytes([c]), is_extended_id=False)
                         for c in range(1, fb.counter_overflow + 1)]
        else:
            msgs = can.Message(arbitration_id=frame.cob_id, data=frame.data, is_extended_id=False)
        with self._emit_lock:
            self._sync_count = 0
            self._last_sync_t = None
            self._sync_period_s = period
            self._sync_started_at = self.now()
            self._sync_echo_warned = False
        if self.engine is not None:
            try:
                self.engine.start_sync(period, range(1, fb.counter_overflow + 1) if fb is not None else None)
            except Exception as e:
                raise BusError(SEND_FAILED, f"cannot start SYNC in the cycle engine: {type(e).__name__}: {e}") from None
            self._sync_task = self.engine
            return
        try:
            task: Any = self._bus.send_periodic(msgs, period, autostart=False)
            if hasattr(task, "on_error"):  # python-can's thread-based task: report a refused SYNC
                task.on_error = self._on_sync_send_error
            task.start()  # every concrete task (thread-based, socketcan BCM) has start()
            self._sync_task = task
        except Exception as e:
            raise BusError(SEND_FAILED, f"cannot start SYNC producer: {type(e).__name__}: {e}") from None

    def _on_sync_send_error(self, exc: Exception) -> bool:
        """The periodic task could not send SYNC (bus-off...): a SendFailed event, and the task stops
        (`sync_running` turns False, so the next job starts SYNC again once the bus is back)."""
        self._emit(SendFailed(f"SYNC producer: {type(exc).__name__}: {exc}", self.now()))
        return False

    def stop_sync(self) -> None:
        task, self._sync_task = self._sync_task, None
        with self._emit_lock:
            self._sync_started_at = None
        if task is None:
            return
        if task is self.engine:
            self.engine.stop_sync()
        else:
            task.stop()

    def send_at(self, cycle: int, frames: Sequence[tuple[int, bytes]]) -> None:
        """With the cycle engine: send `frames` right after SYNC `cycle` (the count of `Sync` events since
        `start_sync`), or at once when it is out already (the engine reports it: `EngineBus.on_late`).
        Without the engine: at once."""
        self._check_open()
        self.check()
        if self.engine is None:
            for cob_id, data in frames:
                self.send(cob_id, data)
            return
        try:
            self.engine.send_at(cycle, frames)
        except Exception as e:
            raise BusError(SEND_FAILED, f"the cycle engine refused frames for SYNC {cycle}: {type(e).__name__}: {e}",
                           detail={"cycle": cycle}) from None

    @property
    def sync_schedule(self) -> tuple[float, float] | None:
        """(time of SYNC 0, period) of the engine's SYNC schedule; None without the engine or SYNC."""
        return self.engine.schedule if self.engine is not None else None

    def sync_counter(self, count: int) -> int | None:
        """With the engine: the SYNC counter SYNC `count` of its schedule carries (None without a counter)."""
        fb = self.feedback
        if fb is None or self.engine is None:
            return None
        return (self.engine.counter_start + count) % fb.counter_overflow + 1

    @property
    def latest_sync(self) -> int | None:
        """The count of the newest SYNC heard back from the bus (None before the first)."""
        count = self._sync_count
        return count - 1 if count else None

    @property
    def sync_running(self) -> bool:
        task = self._sync_task
        if task is not None and task is self.engine:
            return self.engine.schedule is not None
        return task is not None and not getattr(task, "stopped", False)

    def check(self) -> None:
        """Raise the first exception a subscriber callback raised (kept, never dropped)."""
        if self.failures:
            raise self.failures[0]

    def close(self, *, check: bool = True) -> None:
        if self._closed:
            return
        self._closed = True
        self.stop_sync()
        self._stop.set()
        self._monitor.join(timeout=5.0)
        if self._own_bus:
            self._network.disconnect()
        elif self._network.notifier is not None:
            self._network.notifier.stop(self._network.NOTIFIER_SHUTDOWN_TIMEOUT)
        if check:
            self.check()

    def __enter__(self) -> MasterAdapter:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        self.close(check=exc_type is None)

    # ---- internals ----------------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise BusError(CLOSED, "the bus adapter is closed")

    def _remote(self, node_id: int) -> canopen.RemoteNode:
        try:
            return self.remote[node_id]
        except KeyError:
            raise BusError(CONFIG, f"node {node_id} is not an axis of cell {self.cell.name!r}",
                           node=node_id) from None

    @staticmethod
    def _sdo_var(node: canopen.RemoteNode, index: int, sub: int) -> Any:
        node_id = int(node.id or 0)
        try:
            obj = node.sdo[index]
            if isinstance(node.object_dictionary[index], canopen.objectdictionary.ODVariable):
                return obj
            return obj[sub]
        except KeyError:
            raise BusError(CONFIG,
                           f"0x{index:04X}:{sub:02X} is not in the object dictionary of node {node_id}",
                           node=node_id, obj=(index, sub)) from None

    def _write(self, node: canopen.RemoteNode, w: SdoWrite) -> None:
        node_id = int(node.id or 0)
        var = self._sdo_var(node, w.index, w.sub)
        try:
            var.raw = w.value
        except SdoCommunicationError as e:
            raise BusError(NO_RESPONSE, f"node {node_id} did not answer writing {w.ref} ({w.what}): {e}",
                           node=node_id, obj=(w.index, w.sub)) from None
        except SdoAbortedError as e:
            raise BusError(SDO_ABORT, f"node {node_id} refused {w.ref} = {w.value} ({w.what}): abort "
                           f"0x{e.code:08X} ({e})", node=node_id, obj=(w.index, w.sub),
                           detail={"abort_code": e.code, "value": w.value}) from None
        except (ValueError, TypeError) as e:
            raise BusError(CONFIG, f"value {w.value} does not fit {w.ref} ({w.what}) of node {node_id}: {e}",
                           node=node_id, obj=(w.index, w.sub)) from None

    def _emit(self, event: Event) -> None:
        with self._emit_lock:
            for cb in list(self._callbacks):
                try:
                    cb(event)
                except Exception as e:
                    self.failures.append(BusError(
                        CALLBACK, f"event callback {cb!r} raised {type(e).__name__}: {e} on {event!r}",
                        detail={"event": repr(event)}))

    def _on_message(self, msg: can.Message) -> None:
        cob_id = msg.arbitration_id
        t = msg.timestamp
        try:
            if msg.is_error_frame:
                self._emit(AdapterError("receive", "CAN error frame", t))
                return
            if msg.is_remote_frame or msg.is_extended_id:
                return
            with self._emit_lock:
                self._window_bits += codec.frame_bits(min(8, msg.dlc))
                if cob_id == cob.SYNC_COB_ID:
                    count = self._sync_count
                    self._sync_count += 1
                    self._emit(Sync(count, t, msg.data[0] if msg.dlc else None))
                    if self.cell.time_stamp:
                        self._send_time_stamp(t)
                    last, self._last_sync_t = self._last_sync_t, t
                    if last is not None:
                        # everything seen since the previous SYNC, this SYNC included, over the cycle;
                        # a SYNC that comes early (sender jitter) still counts a whole period
                        window = max(t - last, self._sync_period_s)
                        self._emit(BusLoad(self._window_bits / (self._bitrate * window), t))
                    self._window_bits = 0
                    return
            # No `is_rx` filter: on socketcan every frame created on this host (vcan0, or drives
            # simulated in another process) arrives with is_rx False (MSG_DONTROUTE), not only ours.
            # The COB-ID says who sent it: frame_to_event decodes only what drives send (TPDOs,
            # EMCY, heartbeats) and ignores what the master sends (SYNC handled above, RPDOs, SDO, NMT).
            data = bytes(msg.data)
            kind, node = cob.classify(cob_id)
            if kind == "OTHER" or (node and node not in self.nodes):
                self.counters["unknown_cob_id" if kind == "OTHER" else "other_node"] += 1
            if kind == "HEARTBEAT" and node in self.nodes:
                with self._emit_lock:
                    self._hb_last[node] = t
                    self._hb_lost.discard(node)
            sync_count = self._sync_count - 1 if self._sync_count else None
            if kind == "RPDO2" and node in self.nodes:  # our own PVT record, received back: when it was on the wire
                self._emit(RecordOnWire(node, t, sync_count))
                return
            event = frame_to_event(self.profiles, cob_id, data, t, self.nodes, sync_count)
            if event is not None:
                self._emit(event)
        except ProtocolError as e:
            self.counters["malformed"] += 1
            self._emit(AdapterError(f"decode 0x{cob_id:03X}", str(e), t))
        except Exception as e:
            self._emit(AdapterError(f"receive 0x{cob_id:03X}", f"{type(e).__name__}: {e}", t))

    def _send_time_stamp(self, t: float) -> None:
        """0x1013 after a SYNC: the time (us) the SYNC was on the wire, as the echo's timestamp says."""
        stamp = round(t * 1e6) % (1 << 32)
        try:
            self._network.send_message(cob.TIME_STAMP_COB_ID, stamp.to_bytes(4, "little"))
        except Exception as e:
            self._emit(SendFailed(f"time stamp: {type(e).__name__}: {e}", t))

    def send_sync(self, counter: int | None = None, *, at: float | Sequence[float] | None = None) -> None:
        """One SYNC now, or with the cycle engine at time `at` exactly, or one at each of the times `at` (the
        probe paces SYNC itself; the periodic SYNC must be stopped)."""
        if self.engine is not None and at is not None:
            self._check_open()  # the engine carries the SYNC counter on from the last SYNC it sent
            fb = self.feedback
            self.engine.sync_once(at, range(1, fb.counter_overflow + 1) if fb is not None else None)
            return
        self.send(cob.SYNC_COB_ID, b"" if counter is None else bytes([counter]))

    def _run_monitor(self) -> None:
        while not self._stop.wait(min(MONITOR_PERIOD_S, self._hb_timeout_s / 4)):
            try:
                now = self.now()
                lost: list[int] = []
                with self._emit_lock:
                    for node in sorted(self._hb_armed - self._hb_lost):
                        if now - self._hb_last.get(node, now) > self._hb_timeout_s:
                            self._hb_lost.add(node)
                            lost.append(node)
                    started = self._sync_started_at
                    no_echo = (started is not None and self._sync_count == 0 and not self._sync_echo_warned
                               and now - started > max(0.25, 5 * self._sync_period_s))
                    if no_echo:
                        self._sync_echo_warned = True
                for node in lost:
                    self._emit(HeartbeatLost(node, now))
                if no_echo:
                    self._emit(AdapterError("sync", "no SYNC received back: the interface does not deliver "
                                            "own messages (receive_own_messages), so no Sync events", now))
            except Exception as e:
                self._emit(AdapterError("monitor", f"{type(e).__name__}: {e}", self.now()))
