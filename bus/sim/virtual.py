"""The simulated drives of one cell in virtual time: frames in, frames out, no bus, no threads.

A `VirtualCell` holds one drive per axis, boots them, configures them as the master would
(`DriveDevice.configure`) and starts them. The runtime plays the bus: `deliver(cob_id, data, t)` hands a
master frame to the drives that consume it, `sync(t)` is a SYNC, `advance(t)` runs their timers. Drives do
not hear each other (none monitors another here), so routing is O(1) per frame.
"""

from __future__ import annotations

from collections.abc import Mapping

from bus import codec
from bus.budget import cell_feedback_every
from bus.codec import Frame
from bus.families import setpoint_slots
from bus.profile import DriveProfile, FeedbackSchedule, feedback_schedule
from bus.sim import make_drive
from bus.sim.device import DriveDevice
from bus.sim.motor import DEFAULT_MOTOR, MotorParams
from planner.config import CellConfig

CONFIG_SPACING_S = 0.002


class VirtualCell:
    def __init__(
        self,
        cell: CellConfig,
        *,
        motor: MotorParams = DEFAULT_MOTOR,
        configure: bool = True,
        t0: float = 0.0,
        initial_positions: Mapping[int, float] | None = None,
        sync_gap_factor: float = 1.5,
        profile: DriveProfile | None = None,
        feedback_every: int | None = None,
    ):
        self.cell = cell
        self.models: dict[int, DriveDevice] = {}
        self.boot_frames: list[Frame] = []
        positions = dict(initial_positions or {})
        # a master configures drives one after another (tens of SDO exchanges each), so their heartbeat
        # producers start at different times: drive k is powered on and configured CONFIG_SPACING_S before
        # drive k + 1, the last one at t0
        n = len(cell.axes)
        self._config_t = {a.node_id: t0 - (n - 1 - k) * CONFIG_SPACING_S for k, a in enumerate(cell.axes)}
        self.slots = setpoint_slots(cell.axes)
        for axis in cell.axes:
            m = make_drive(axis, cell.drive, motor=motor,
                           initial_position=positions.get(axis.node_id, 0.0),
                           sync_gap_factor=sync_gap_factor, profile=profile)
            self.boot_frames += m.power_on(self._config_t[axis.node_id])
            self.models[axis.node_id] = m
        # what the master configures: TPDO2 staggered when the cell needs it (bus.budget) and every drive
        # has the SYNC counter (the master learns that over SDO; here each model says so itself)
        every = feedback_every if feedback_every is not None else cell_feedback_every(cell)
        self.feedback: FeedbackSchedule | None = feedback_schedule(
            [a.node_id for a in cell.axes], every, all(m.has_object(0x1019) for m in self.models.values()))
        if configure:
            for node, m in self.models.items():
                self.boot_frames += m.configure(cell.sync_period_ms, t=self._config_t[node], feedback=self.feedback,
                                                time_stamp=cell.time_stamp, slot=self.slots.get(node))
        self._models = tuple(self.models.values())
        self._routes: dict[int, tuple[DriveDevice, ...]] = {}
        self._versions: dict[int, int] = {}
        self._rebuild_routes()

    def model(self, node: int) -> DriveDevice:
        return self.models[node]

    def _rebuild_routes(self) -> None:
        routes: dict[int, list[DriveDevice]] = {}
        for m in self._models:
            for cob_id in m.rx_cob_ids():
                routes.setdefault(cob_id, []).append(m)
            self._versions[m.node_id] = m.pdo_config_version
        self._routes = {k: tuple(v) for k, v in routes.items()}

    def deliver(self, cob_id: int, data: bytes, t: float) -> list[Frame]:
        """A frame from the master: the drives that consume `cob_id` see it; returns their frames."""
        out: list[Frame] = []
        targets = self._models if cob_id == 0 else self._routes.get(cob_id, ())
        changed = False
        for m in targets:
            out += m.on_frame(cob_id, data, t)
            if m.pdo_config_version != self._versions[m.node_id]:
                changed = True
        if changed or cob_id == 0:
            self._rebuild_routes()
        return out

    def sync(self, t: float, data: bytes = b"") -> list[Frame]:
        out: list[Frame] = []
        for m in self._models:
            out += m.on_sync(t, data)
        return out

    def advance(self, t: float) -> list[Frame]:
        out: list[Frame] = []
        for m in self._models:
            out += m.advance(t)
        return out

    def next_deadline(self) -> float | None:
        times = [d for d in (m.next_deadline() for m in self._models) if d is not None]
        return min(times) if times else None

    def enable_drives(self, t: float | None = None, *, check: bool = True) -> list[Frame]:
        """What `MasterAdapter.enable_drives` does over SDO: the set point objects = the drive's position
        (cyclic families), fault reset if faulted, 0x0006, 0x000F (bit 4 low), then the family's writes
        (EPOS: buffer clear then enable). With `check`, raises RuntimeError if a drive does not get there."""
        S = codec.Cia402State
        out: list[Frame] = []
        for node, m in self.models.items():
            commands: list[codec.Command] = []
            if m.state == S.FAULT:
                commands += [codec.Command.DISABLE_VOLTAGE, codec.Command.FAULT_RESET]
            elif m.state in (S.QUICK_STOP_ACTIVE, S.FAULT_REACTION_ACTIVE, S.NOT_READY_TO_SWITCH_ON):
                commands.append(codec.Command.DISABLE_VOLTAGE)
            if m.state != S.OPERATION_ENABLED:
                commands.append(codec.Command.SHUTDOWN)
            commands.append(codec.Command.ENABLE_OPERATION)
            writes = [(w.index, w.sub, w.value) for w in m.profile.hold_writes(m.sdo_read(0x6064, 0))]
            writes += [(0x6040, 0, c.value) for c in commands]
            writes += [(*m.profile.obj(name), value) for name, value in m.profile.after_enable]
            for index, sub, value in writes:
                out += self.sdo_write(node, index, sub, value, t)
            if check and not m.ready_for_job:
                raise RuntimeError(f"drive {node} is {m.state.value!r} after the enable sequence")
        return out

    def sdo_read(self, node: int, index: int, sub: int) -> int:
        return self.models[node].sdo_read(index, sub)

    def sdo_write(self, node: int, index: int, sub: int, value: int, t: float | None = None) -> list[Frame]:
        out = self.models[node].sdo_write(index, sub, value, t)
        self._rebuild_routes()
        return out
