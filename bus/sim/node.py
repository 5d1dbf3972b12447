"""Run simulated drives (bus/sim/device.py and a family model each) in real time on any python-can bus,
through canopen `LocalNode`s.

SDO is redirected to the model, the only store of values (block upload served here,
`SdoBlockUploadServer`, as canopen's server lacks it); RPDOs come through canopen's callbacks, NMT, SYNC,
time stamps and heartbeats through a raw listener (canopen's `NmtSlave` detached); the model's frames are
sent as they are. A timer thread calls `model.advance` at each `next_deadline()`. One lock serialises all
model access and the sends of what the models produced, so a drive's frames leave in the order it made them
(sent after the lock, a drive's answers to two SYNCs once crossed: the timer thread released the first, the
bus thread produced the second and sent it first, and the master rightly took that for records executed out
of order); time is `time.time()`; callback exceptions are kept and re-raised by `check()`/`stop()`.
"""

from __future__ import annotations

import binascii
import struct
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from typing import Any

import can
import canopen
from canopen.sdo.exceptions import SdoAbortedError

from bus import cob
from bus.codec import Frame, NmtState
from bus.errors import CALLBACK, BusError
from bus.network import NOTIFIER_CYCLE_S, open_bus
from bus.profile import DriveProfile
from bus.sim import make_drive
from bus.sim import od as odm
from bus.sim.device import DriveDevice
from bus.sim.motor import DEFAULT_MOTOR, MotorParams
from bus.sim.od import SdoAbort
from planner.config import BusConfig, CellConfig

TIMER_MAX_SLEEP_S = 0.05
# a SYNC or heartbeat that does not come at all is noticed this long after its deadline: the receive path of
# a drive simulated on a general-purpose OS (a notifier thread, then the lock) may hold a frame that was on
# the bus in time for a few ms; hardware has none. A SYNC that comes late is judged by its bus time stamp when
# it comes, exactly (bus/sim/device.py `receive_slack_s`)
RECEIVE_SLACK_S = 0.02

# CiA 301 SDO block upload (client command specifier 5, server 6)
_CCS_BLOCK_UPLOAD = 5 << 5
_SCS_BLOCK_UPLOAD = 6 << 5
_CS_INITIATE, _CS_END, _CS_ACK, _CS_START = 0, 1, 2, 3
_CRC_SUPPORTED = 0x04
_SIZE_INDICATED = 0x02
_LAST_SEGMENT = 0x80
ABORT_INVALID_COMMAND = 0x05040001
ABORT_INVALID_BLOCK_SIZE = 0x05040002
ABORT_INVALID_SEQUENCE = 0x05040003
ABORT_NO_DATA = 0x08000024


class SdoBlockUploadServer:
    """The server side of CiA 301 SDO block upload for one node, pure: request frames (8 bytes) in,
    response frames out. `read(index, sub)` gives the object's bytes or raises SdoAbortedError.

    initiate (client: index, sub, block size 1..127, CRC supported?) -> size and CRC support;
    start -> one block of up to `blksize` segments of 7 bytes, sequence numbers 1..n, bit 7 on the last
    segment of the object; block ack (the last sequence number received, the next block size) -> the
    next block, or the segments from the first one not received again, or after the last block the end
    (bytes unused in the last segment, CRC-16 XMODEM of the data); end confirmed -> idle."""

    def __init__(self, read: Callable[[int, int], bytes]):
        self._read = read
        self._data = b""
        self._index = 0
        self._sub = 0
        self._blksize = 0
        self._crc = False
        self._pos = 0  # bytes acknowledged
        self._block_start = 0  # bytes at the start of the block in flight
        self._state = "idle"
        self.frames_sent = 0

    @property
    def busy(self) -> bool:
        return self._state != "idle"

    def _abort(self, code: int) -> list[bytes]:
        self._state = "idle"
        return [struct.pack("<BHBL", 0x80, self._index, self._sub, code)]

    def on_request(self, data: bytes) -> list[bytes]:
        if len(data) < 8:
            return self._abort(ABORT_INVALID_COMMAND)
        command = data[0]
        if command == 0x80:  # the client aborted
            self._state = "idle"
            return []
        if command & 0xE0 != _CCS_BLOCK_UPLOAD:
            return self._abort(ABORT_INVALID_COMMAND)
        cs = command & 0x03
        out: list[bytes]
        if cs == _CS_INITIATE:
            out = self._initiate(data)
        elif cs == _CS_START and self._state == "initiated":
            self._state = "sending"
            out = self._block()
        elif cs == _CS_ACK and self._state == "sending":
            out = self._ack(data[1], data[2])
        elif cs == _CS_END and self._state == "ending":
            self._state = "idle"
            out = []
        else:
            out = self._abort(ABORT_INVALID_COMMAND)
        self.frames_sent += len(out)
        return out

    def _initiate(self, data: bytes) -> list[bytes]:
        _, self._index, self._sub, blksize = struct.unpack_from("<BHBB", data)
        if not 1 <= blksize <= 127:
            return self._abort(ABORT_INVALID_BLOCK_SIZE)
        try:
            payload = self._read(self._index, self._sub)
        except SdoAbortedError as e:
            return self._abort(e.code)
        if not payload:
            return self._abort(ABORT_NO_DATA)
        self._data = bytes(payload)
        self._blksize = blksize
        self._crc = bool(data[0] & _CRC_SUPPORTED)
        self._pos = 0
        self._block_start = 0
        self._state = "initiated"
        flags = _SIZE_INDICATED | (_CRC_SUPPORTED if self._crc else 0)
        return [struct.pack("<BHBL", _SCS_BLOCK_UPLOAD | flags, self._index, self._sub, len(self._data))]

    def _block(self) -> list[bytes]:
        out: list[bytes] = []
        self._block_start = self._pos
        pos = self._pos
        for seq in range(1, self._blksize + 1):
            chunk = self._data[pos:pos + 7]
            pos += len(chunk)
            last = pos >= len(self._data)
            out.append(bytes([seq | (_LAST_SEGMENT if last else 0)]) + chunk.ljust(7, b"\x00"))
            if last:
                break
        return out

    def _ack(self, ackseq: int, blksize: int) -> list[bytes]:
        if not 1 <= blksize <= 127:
            return self._abort(ABORT_INVALID_BLOCK_SIZE)
        sent = -(-(min(len(self._data), self._block_start + 7 * self._blksize) - self._block_start) // 7)
        if ackseq > sent:
            return self._abort(ABORT_INVALID_SEQUENCE)
        self._pos = min(len(self._data), self._block_start + 7 * ackseq)
        self._blksize = blksize
        if ackseq == sent and self._pos >= len(self._data):
            self._state = "ending"
            unused = (7 - len(self._data) % 7) % 7
            crc = binascii.crc_hqx(self._data, 0) if self._crc else 0
            return [struct.pack("<BH5x", _SCS_BLOCK_UPLOAD | (unused << 2) | _CS_END, crc)]
        return self._block()  # the next block, or the rest of this one from the first segment lost


class _RawListener(can.Listener):
    """NMT, SYNC, time stamp and heartbeat frames to the models (canopen handles SDO and RPDOs)."""

    def __init__(self, cell: SimulatedCell):
        self.cell = cell

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return
        cob_id = msg.arbitration_id
        if cob_id in (0, cob.TIME_STAMP_COB_ID) or cob_id in self.cell._sync_ids or 0x701 <= cob_id <= 0x77F:
            self.cell._dispatch_raw(cob_id, bytes(msg.data), msg.timestamp)

    def on_error(self, exc: Exception) -> None:
        self.cell._record_error("notifier", exc)

    def stop(self) -> None:
        pass


class SimulatedCell:
    """All simulated drives of a cell on one CAN bus, in real time."""

    def __init__(
        self,
        cell: CellConfig,
        bus_config: BusConfig | None = None,
        *,
        bus: can.BusABC | None = None,
        motor: MotorParams = DEFAULT_MOTOR,
        initial_positions: Mapping[int, float] | None = None,
        sync_gap_factor: float = 1.5,
        profile: DriveProfile | None = None,
        eds_path: str | None = None,
        clock: Callable[[], float] = time.time,
        block_upload: bool = True,
        receive_slack_s: float = RECEIVE_SLACK_S,
    ):
        self.cell = cell
        self.block_upload = block_upload
        self.bus_config = bus_config or cell.bus
        self.eds_path = eds_path  # None: each drive's family EDS
        self.clock = clock
        self.errors: list[BusError] = []
        positions = dict(initial_positions or {})
        self.models: dict[int, DriveDevice] = {
            a.node_id: make_drive(a, cell.drive, motor=motor,
                                  initial_position=positions.get(a.node_id, 0.0),
                                  sync_gap_factor=sync_gap_factor, profile=profile,
                                  receive_slack_s=receive_slack_s)
            for a in cell.axes
        }
        self.nodes: dict[int, Any] = {}  # canopen.LocalNode (untyped library)
        self._bus = bus
        self._own_bus = bus is None
        self._network: canopen.Network | None = None
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._kick = threading.Event()
        self._wake_at = 0.0  # when the timer thread means to run next (lock held to read or write)
        self._timer: threading.Thread | None = None
        self._versions: dict[int, int] = {}
        self._pending: list[Frame] = []
        self._sync_ids: frozenset[int] = frozenset({cob.SYNC_COB_ID})
        self._started = False
        self.block_servers: dict[int, SdoBlockUploadServer] = {}

    # ---- lifecycle --------------------------------------------------------------------------------
    def start(self) -> SimulatedCell:
        if self._started:
            raise RuntimeError("simulated cell already started")
        if self._bus is None:
            self._bus = open_bus(self.bus_config)
        network = canopen.Network(self._bus)
        network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
        listeners: list[Any] = network.listeners
        listeners.append(_RawListener(self))
        self._network = network
        for node_id, model in self.models.items():
            eds = self.eds_path or model.profile.eds_path
            node: Any = canopen.LocalNode(node_id, canopen.objectdictionary.import_od(eds, node_id))
            network.add_node(node)
            # the model owns NMT and the heartbeat: detach canopen's NmtSlave
            network.unsubscribe(0, node.nmt.on_command)
            node._write_callbacks.remove(node.nmt.on_write)
            # SDO: through the model, silent in NMT stopped
            network.unsubscribe(node.sdo.rx_cobid, node.sdo.on_request)
            network.subscribe(node.sdo.rx_cobid, self._sdo_handler(node_id, node))
            node.add_read_callback(self._read_callback(model))
            node.add_write_callback(self._write_callback(model))
            for n in node.rpdo.map:
                node.rpdo.map[n].add_callback(self._rpdo_callback(node_id))
            self.nodes[node_id] = node
        network.connect()
        self._started = True
        now = self.clock()
        with self._lock:
            frames: list[Frame] = []
            for model in self.models.values():
                frames += model.power_on(now)
            for node_id in self.models:
                self._refresh_pdos(node_id)
            self._update_sync_ids()
            self._send_all(frames)
        self._timer = threading.Thread(target=self._run_timers, name="sim-cell-timers", daemon=True)
        self._timer.start()
        return self

    def stop(self) -> None:
        """Stop the timer thread, the notifier and (if opened here) the bus. Raises the first recorded
        callback error as BusError(CALLBACK)."""
        if not self._started:
            return
        self._started = False
        self._stop.set()
        self._kick.set()
        if self._timer is not None:
            self._timer.join(timeout=5.0)
        network = self._network
        if network is not None:
            if self._own_bus:
                network.disconnect()
            elif network.notifier is not None:
                network.notifier.stop(network.NOTIFIER_SHUTDOWN_TIMEOUT)
        self._network = None
        self.check()

    @property
    def started(self) -> bool:
        return self._started

    def __enter__(self) -> SimulatedCell:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def check(self) -> None:
        """Raise the first exception recorded in a callback or thread (never silently dropped)."""
        if self.errors:
            raise self.errors[0]

    @contextmanager
    def locked(self) -> Iterator[dict[int, DriveDevice]]:
        """Inspect or poke the models consistently (the bus threads wait meanwhile)."""
        with self._lock:
            yield self.models

    def model(self, node: int) -> DriveDevice:
        return self.models[node]

    # ---- internals ----------------------------------------------------------------------------------
    def _record_error(self, where: str, exc: BaseException) -> None:
        self.errors.append(BusError(CALLBACK, f"simulated cell {where}: {type(exc).__name__}: {exc}",
                                    detail={"where": where}))

    def _send_all(self, frames: list[Frame]) -> None:
        network = self._network
        if network is None or not frames:
            return
        for f in frames:
            try:
                network.send_message(f.cob_id, f.data)
            except Exception as e:  # a closed bus on shutdown, a full queue
                if self._started:
                    self._record_error(f"send 0x{f.cob_id:03X}", e)
                return

    def _flush_pending(self) -> None:
        with self._lock:
            frames, self._pending = self._pending, []
            self._send_all(frames)

    def _update_sync_ids(self) -> None:
        self._sync_ids = frozenset(m.sync_cob_id for m in self.models.values())

    def _refresh_pdos(self, node_id: int) -> None:
        """Re-read canopen's PDO maps when the model's PDO configuration changed (lock held)."""
        model = self.models[node_id]
        if self._versions.get(node_id) == model.pdo_config_version:
            return
        node = self.nodes[node_id]
        node.rpdo.read()
        node.tpdo.read()
        self._versions[node_id] = model.pdo_config_version

    def _dispatch_raw(self, cob_id: int, data: bytes, t: float) -> None:
        try:
            with self._lock:
                frames: list[Frame] = []
                for node_id, model in self.models.items():
                    if cob_id == 0 or cob_id == model.sync_cob_id or cob_id in model.rx_cob_ids():
                        frames += model.on_frame(cob_id, data, t)
                        self._refresh_pdos(node_id)
                if cob_id == 0:
                    self._update_sync_ids()
                    self._kick.set()
                else:
                    self._kick_if_sooner()
                self._send_all(frames)
        except Exception as e:
            self._record_error(f"frame 0x{cob_id:03X}", e)

    def _kick_if_sooner(self) -> None:
        """Wake the timer thread when a model now has something to do before it meant to run (lock held): a
        SYNC's answers held for the drive's TPDO latency are due after the latency, not at the timer's next
        wake (up to TIMER_MAX_SLEEP_S, or the SYNC watchdog's deadline, later)."""
        if any(d < self._wake_at for d in self._deadlines()):
            self._kick.set()

    def _deadlines(self) -> list[float]:
        """When each model next has something to do (`next_deadline`), of those that have (lock held)."""
        return [d for m in self.models.values() if (d := m.next_deadline()) is not None]

    def _rpdo_callback(self, node_id: int) -> Callable[[Any], None]:
        model = self.models[node_id]

        def on_rpdo(pdo_map: Any) -> None:
            try:
                with self._lock:
                    frames = model.on_frame(pdo_map.cob_id, bytes(pdo_map.data), pdo_map.timestamp)
                    self._send_all(frames)
            except Exception as e:
                self._record_error(f"RPDO 0x{pdo_map.cob_id:03X} of node {node_id}", e)

        return on_rpdo

    def _sdo_handler(self, node_id: int, node: Any) -> Callable[[int, bytearray, float], None]:
        model = self.models[node_id]
        block = SdoBlockUploadServer(lambda index, sub: bytes(node.get_data(index, sub, check_readable=True)))
        self.block_servers[node_id] = block

        def on_request(can_id: int, data: bytearray, timestamp: float) -> None:
            try:
                with self._lock:
                    if model.nmt_state in (NmtState.STOPPED, NmtState.BOOTUP):
                        return
                    if self.block_upload and (data[0] & 0xE0 == _CCS_BLOCK_UPLOAD or (block.busy and data[0] == 0x80)):
                        self._pending += [Frame(0x580 + node_id, f) for f in block.on_request(bytes(data))]
                    else:
                        node.sdo.on_request(can_id, data, timestamp)
                    self._refresh_pdos(node_id)
                    self._update_sync_ids()
                self._kick.set()
                self._flush_pending()
            except Exception as e:
                self._record_error(f"SDO request to node {node_id}", e)

        return on_request

    def _read_callback(self, model: DriveDevice) -> Callable[..., int | bytes | None]:
        def on_read(index: int, subindex: int, od: Any) -> int | bytes | None:
            spec = model.objects.objects.get((index, subindex))
            if spec is None or spec.dtype == odm.DataType.VISIBLE_STRING:
                return None
            with self._lock:
                try:
                    if spec.dtype == odm.DataType.DOMAIN:
                        return model.read_domain(index, subindex)
                    return model.sdo_read(index, subindex)
                except SdoAbort as e:
                    raise SdoAbortedError(e.code) from None
                except Exception as e:
                    self._record_error(f"SDO read 0x{index:04X}:{subindex:02X}", e)
                    raise SdoAbortedError(odm.ABORT_GENERAL) from None

        return on_read

    def _write_callback(self, model: DriveDevice) -> Callable[..., None]:
        def on_write(index: int, subindex: int, od: Any, data: bytes) -> None:
            with self._lock:
                try:
                    spec = model.objects.spec(index, subindex)
                    value = odm.decode_value(spec, bytes(data))
                    self._pending += model.sdo_write(index, subindex, value, self.clock())
                except SdoAbort as e:
                    raise SdoAbortedError(e.code) from None
                except Exception as e:
                    self._record_error(f"SDO write 0x{index:04X}:{subindex:02X}", e)
                    raise SdoAbortedError(odm.ABORT_GENERAL) from None

        return on_write

    def _run_timers(self) -> None:
        while not self._stop.is_set():
            try:
                now = self.clock()
                with self._lock:
                    frames: list[Frame] = []
                    for model in self.models.values():
                        frames += model.advance(now)
                    wake_at = self._wake_at = min([*self._deadlines(), now + TIMER_MAX_SLEEP_S])
                    self._send_all(frames)
                wait = max(0.0, wake_at - self.clock())
            except Exception as e:
                self._record_error("timer thread", e)
                wait = TIMER_MAX_SLEEP_S
            if wait > 0.0:
                self._kick.wait(wait)
            self._kick.clear()
