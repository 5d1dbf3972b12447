"""Run simulated drives (bus/sim/device.py and a family model each) in real time on any python-can bus,
through canopen `LocalNode`s.

What it owns: one python-can bus (unless given one), one canopen `Network`, one `LocalNode` per
simulated drive (object dictionary from configs/drives/epos-ipm.eds), a timer thread, and the lock
that serialises everything that touches the models. What it does:

- SDO server: canopen's `SdoServer` of each LocalNode, whose reads and writes are redirected to the
  model (`add_read_callback`/`add_write_callback`), so the model is the only store of values; a
  model `SdoAbort` becomes canopen's `SdoAbortedError` with the same code. In NMT stopped the SDO
  server does not answer (CiA 301).
- RPDOs: through `rpdo[n].add_callback` (canopen delivers received RPDOs only there). canopen only
  applies a PDO mapping after `rpdo.read()`/`tpdo.read()`, so the adapter re-reads the maps whenever
  the model's PDO configuration changed (master remapping over SDO, NMT resets).
- NMT, SYNC, the time stamp and heartbeats: a raw python-can listener hands them to the models; canopen's own
  `NmtSlave` is detached (it would run its own heartbeat with its own idea of the state).
- TPDOs, EMCYs, heartbeats, boot-up: whatever frames the model returns are sent as they are (a
  LocalNode sends no TPDO by itself).
- Timers: a thread calls `model.advance(now)` at each model's `next_deadline()` (heartbeat producer,
  SYNC loss, heartbeat consumer).

Time is `time.time()` (the clock python-can stamps virtual-bus frames with). An exception in any
callback is recorded in `errors` (and re-raised by `check()`/`stop()`), never swallowed.
"""

from __future__ import annotations

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
    ):
        self.cell = cell
        self.bus_config = bus_config or cell.bus
        self.eds_path = eds_path  # None: each drive's family EDS
        self.clock = clock
        self.errors: list[BusError] = []
        positions = dict(initial_positions or {})
        self.models: dict[int, DriveDevice] = {
            a.node_id: make_drive(a, cell.drive, motor=motor,
                                  initial_position=positions.get(a.node_id, 0.0),
                                  sync_gap_factor=sync_gap_factor, profile=profile)
            for a in cell.axes
        }
        self.nodes: dict[int, Any] = {}  # canopen.LocalNode (untyped library)
        self._bus = bus
        self._own_bus = bus is None
        self._network: canopen.Network | None = None
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._kick = threading.Event()
        self._timer: threading.Thread | None = None
        self._versions: dict[int, int] = {}
        self._pending: list[Frame] = []
        self._sync_ids: frozenset[int] = frozenset({cob.SYNC_COB_ID})
        self._started = False

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
            self._send_all(frames)
        except Exception as e:
            self._record_error(f"frame 0x{cob_id:03X}", e)

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

        def on_request(can_id: int, data: bytearray, timestamp: float) -> None:
            try:
                with self._lock:
                    if model.nmt_state in (NmtState.STOPPED, NmtState.BOOTUP):
                        return
                    node.sdo.on_request(can_id, data, timestamp)
                    self._refresh_pdos(node_id)
                    self._update_sync_ids()
                self._kick.set()
                self._flush_pending()
            except Exception as e:
                self._record_error(f"SDO request to node {node_id}", e)

        return on_request

    def _read_callback(self, model: DriveDevice) -> Callable[..., int | None]:
        def on_read(index: int, subindex: int, od: Any) -> int | None:
            spec = model.objects.objects.get((index, subindex))
            if spec is None or spec.dtype == odm.DataType.VISIBLE_STRING:
                return None
            with self._lock:
                try:
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
                    pending = (m.next_deadline() for m in self.models.values())
                    deadlines = [d for d in pending if d is not None]
                self._send_all(frames)
                wait = TIMER_MAX_SLEEP_S
                if deadlines:
                    wait = max(0.0, min(wait, min(deadlines) - self.clock()))
            except Exception as e:
                self._record_error("timer thread", e)
                wait = TIMER_MAX_SLEEP_S
            if wait > 0.0:
                self._kick.wait(wait)
            self._kick.clear()
