"""The simulated cyclic synchronous position drive (bus/sim/csp.py): enabling in mode 8, the target 0x607A
followed with one period of latency along a line at 1 ms ticks, seed 000 6.7's following-error check of
each new target, a SYNC without a new target holds, SYNC loss, and the master's own configuration."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import replace
from typing import Any

import pytest
from bus_testkit import make_axis, make_cell

from bus import cob, codec
from bus.codec import Cia402State, Frame, NmtState
from bus.families import CIA402_CSP, setpoint_slots
from bus.profile import pack_setpoints
from bus.sim import make_drive
from bus.sim import od as odm
from bus.sim.csp import CspDrive
from bus.sim.od import SdoAbort
from bus.sim.virtual import VirtualCell
from planner.config import AxisConfig, DriveSettings

SETTINGS = DriveSettings(heartbeat_ms=0, heartbeat_timeout_ms=350, following_error_counts=5000)


def caxis(node: int = 1) -> AxisConfig:
    return replace(make_axis(node), profile="cia402-csp")


class Recording(CspDrive):
    """Records the demand the position loop gets at every 1 ms tick."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.tick_demands: list[int] = []
        super().__init__(*args, **kwargs)

    def _integrate(self, demands: Iterable[int]) -> int:
        ds = list(demands)
        self.tick_demands += ds
        return super()._integrate(ds)


class Rig:
    def __init__(self, *, period_ms: int = 10, initial_position: float = 0.0, configure: bool = True) -> None:
        self.axis = caxis()
        self.m = Recording(1, self.axis, SETTINGS, initial_position=initial_position)
        self.period = period_ms / 1000.0
        self.t = 0.0
        self.frames: list[Frame] = list(self.m.power_on(0.0))
        self.slot = setpoint_slots([self.axis])[1]
        if configure:
            self.frames += self.m.configure(period_ms, slot=self.slot, t=0.0)

    def sdo(self, index: int, sub: int, value: int) -> None:
        self.frames += self.m.sdo_write(index, sub, value, self.t)

    def sync(self, n: int = 1) -> None:
        for _ in range(n):
            self.t += self.period
            self.frames += self.m.advance(self.t)
            self.frames += self.m.on_sync(self.t)

    def target(self, x: int) -> None:
        data = bytearray(self.slot.frame_bytes)
        pack_setpoints(self.slot, data, x)
        self.frames += self.m.on_frame(self.slot.cob_id, bytes(data), self.t + 0.001)

    def enable(self) -> None:
        for w in CIA402_CSP.hold_writes(self.m.sdo_read(0x6064, 0)):
            self.sdo(w.index, w.sub, w.value)
        self.sdo(0x6040, 0, 0x0006)
        self.sdo(0x6040, 0, 0x000F)

    def emcys(self) -> list[codec.EmcyMessage]:
        return [codec.decode_emcy(f.data) for f in self.frames if f.cob_id == cob.emcy_id(1)]


def test_enable_in_mode_8_follows_without_a_start_bit() -> None:
    r = Rig(configure=False)
    m = r.m
    assert m.sdo_read(0x6502, 0) == 0xA0  # homing and cyclic synchronous position
    assert m.has_object(0x1019) and m.has_object(0x1012) and m.has_object(0x1013)  # CiA 301 v4.2
    with pytest.raises(SdoAbort) as e:
        m.sdo_write(0x6060, 0, 7)
    assert e.value.code == odm.ABORT_INVALID_VALUE
    r.sdo(0x6060, 0, 8)
    r.sdo(0x6040, 0, 0x0006)
    r.sdo(0x6040, 0, 0x000F)
    assert m.state == Cia402State.OPERATION_ENABLED and m.ready_for_job
    assert m.statusword & codec.SW_IP_ACTIVE  # bit 12: the drive follows the command value
    r.sdo(0x6040, 0, 0x0007)  # disable operation: no longer following
    assert not m.statusword & codec.SW_IP_ACTIVE
    r.sdo(0x6060, 0, 0)
    r.sdo(0x6040, 0, 0x000F)
    assert not m.statusword & codec.SW_IP_ACTIVE
    r.sdo(0x6060, 0, 8)  # mode 8 selected while operation enabled
    assert m.statusword & codec.SW_IP_ACTIVE


def test_configured_by_the_masters_writes() -> None:
    r = Rig()
    m = r.m
    assert m.sdo_read(0x6060, 0) == 8 and m.sdo_read(0x1006, 0) == 10_000 and m.sdo_read(0x60C2, 1) == 10
    assert m.sdo_read(0x1602, 1) == 0x607A0020 and m.sdo_read(0x1402, 2) == 1
    assert m.sdo_read(0x6065, 0) == 5000 and m.nmt_state == NmtState.OPERATIONAL
    assert make_drive(caxis()).family == "cia402-csp"


def test_target_followed_with_one_period_of_latency_along_a_line() -> None:
    r = Rig(initial_position=300.0)
    r.enable()
    assert r.m.sdo_read(0x607A, 0) == 300
    xs = [300, 1300, 3300, 3000, 3000, -200]
    for x in xs:
        r.target(x)
        r.sync()
    r.target(-200)
    r.sync()
    ticks = r.m.tick_demands[-10 * len(xs):]
    for k in range(1, len(xs)):  # the period after the SYNC that latched xs[k]
        line = [math.floor(xs[k - 1] + (xs[k] - xs[k - 1]) * t / 10 + 0.5) for t in range(1, 11)]
        assert ticks[(k) * 10:(k + 1) * 10] == line, k
    assert r.m.sdo_read(0x6062, 0) == -200 and not r.emcys()


def test_a_sync_without_a_new_target_holds_it() -> None:
    r = Rig()
    r.enable()
    r.target(800)
    r.sync()
    r.sync(30)  # no new target: the last one holds, no error
    assert r.m.sdo_read(0x6062, 0) == 800 and r.m.ip_active and not r.emcys()
    assert abs(r.m.sdo_read(0x6064, 0) - 800) <= 2


def test_following_error_check_of_each_new_target() -> None:
    """Seed 000 6.7: "If the difference between actual and new position is greater than 'Max Following
    Error', an emergency procedure will be launched"."""
    r = Rig()
    r.enable()
    r.target(4999)
    r.sync()
    assert not r.emcys()
    r.sync(20)
    assert abs(r.m.sdo_read(0x6064, 0) - 4999) <= 2
    r.target(4999 + 5100)  # 5100 away from the actual position
    r.sync()
    emcy = r.emcys()
    assert [e.code for e in emcy] == [codec.EMCY_FOLLOWING_ERROR]
    assert r.m.state in (Cia402State.FAULT_REACTION_ACTIVE, Cia402State.FAULT)


def test_enabling_without_the_hold_write_trips_the_check() -> None:
    r = Rig(initial_position=20_000.0)
    r.sdo(0x6040, 0, 0x0006)
    r.sdo(0x6040, 0, 0x000F)  # 0x607A is still 0: 20 000 away
    r.sync()
    assert [e.code for e in r.emcys()] == [codec.EMCY_FOLLOWING_ERROR]


def test_sync_loss_while_following() -> None:
    r = Rig()
    r.enable()
    r.target(0)
    r.sync()
    r.t += 0.016
    r.frames += r.m.advance(r.t)
    assert [e.code for e in r.emcys()] == [codec.EMCY_SYNC_LOST]


def test_quick_stop_ramps_in_counts_per_s2() -> None:
    r = Rig()
    r.enable()
    for k in range(1, 6):
        r.target(1000 * k)  # 100 000 counts/s (the new target leads the actual position by two periods)
        r.sync()
    r.sdo(0x6085, 0, 2_000_000)
    r.sdo(0x6040, 0, 0x000B)  # quick stop option 2 (the master's): 50 ms at 2e6 counts/s^2
    r.sync(4)
    assert r.m.state == Cia402State.QUICK_STOP_ACTIVE
    r.sync(2)
    assert r.m.state == Cia402State.SWITCH_ON_DISABLED


def test_a_cell_of_csp_drives_in_virtual_time() -> None:
    cell = make_cell(2, settings=SETTINGS)
    cell = replace(cell, axes=tuple(replace(a, profile="cia402-csp") for a in cell.axes))
    vc = VirtualCell(cell, initial_positions={1: 0.0, 2: 1000.0})
    vc.enable_drives(0.0)
    t = 0.0
    demand: dict[int, list[int]] = {1: [], 2: []}
    moves = {1: [100 * k for k in range(30)], 2: [1000 - 50 * k for k in range(30)]}
    for k in range(32):
        for node, slot in vc.slots.items():
            data = bytearray(slot.frame_bytes)
            pack_setpoints(slot, data, moves[node][min(k, 29)])
            vc.deliver(slot.cob_id, bytes(data), t + 0.001)
        t += 0.01
        vc.sync(t)
        for node, m in vc.models.items():
            demand[node].append(m.sdo_read(0x6062, 0))
    for node, xs in moves.items():
        assert demand[node][1:31] == xs
    assert all(not m.fault_log for m in vc.models.values())
