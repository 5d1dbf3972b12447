"""The simulated Infranor XtrapulsPac (bus/sim/xtrapuls.py) against seed 003: the enable sequence, modes,
NMT boot-up, 0x1006, the default PDO map, the multiplexed RPDO of the manual's example, 16-bit set
points, the interpolation per sub-mode at every 1 ms tick, errors 49/50/51, the PLL's 180 ms, the
master's own configuration (virtual time and over SDO in real time)."""

from __future__ import annotations

import itertools
import math
import random
from collections.abc import Iterable
from dataclasses import replace
from typing import Any

import pytest
from bus_testkit import make_axis, make_cell, wait_until

from bus import cob, codec
from bus.codec import Cia402State, Frame, NmtCommand, NmtState
from bus.families import XTRAPULS_IP, setpoint_slots
from bus.network import MasterAdapter
from bus.profile import SetpointSlot, pack_setpoints
from bus.sim import make_drive
from bus.sim import od as odm
from bus.sim.node import SimulatedCell
from bus.sim.od import SdoAbort
from bus.sim.virtual import VirtualCell
from bus.sim.xtrapuls import XtrapulsDrive
from planner.config import AxisConfig, CellConfig, DriveSettings
from planner.errors import PlanningError
from planner.readings import SimDriveOptions

SETTINGS = DriveSettings(heartbeat_ms=0, heartbeat_timeout_ms=350)
EMCY_SYNC, EMCY_IP, EMCY_FE, EMCY_HB = 0x8780, 0x8782, 0x8611, 0x8130


def xaxis(node: int = 1, submode: str = "linear", mux_group: int = 0, **kw: Any) -> AxisConfig:
    return replace(make_axis(node, **kw), profile="xtrapuls-ip", ip_submode=submode, mux_group=mux_group)


class Recording(XtrapulsDrive):
    """Records the demand the position loop gets at every 1 ms tick."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.tick_demands: list[int] = []
        super().__init__(*args, **kwargs)

    def _integrate(self, demands: Iterable[int]) -> int:
        ds = list(demands)
        self.tick_demands += ds
        return super()._integrate(ds)


class Rig:
    """One XtrapulsPac in virtual time, configured by the master's writes (`XTRAPULS_IP.configuration`)."""

    def __init__(self, axis: AxisConfig | None = None, *, period_ms: float = 10, cls: type[XtrapulsDrive] = Recording,
                 configure: bool = True, slot: SetpointSlot | None = None, **kw: Any) -> None:
        self.axis = axis or xaxis()
        self.node = self.axis.node_id
        self.m = cls(self.node, self.axis, SETTINGS, **kw)
        self.period = period_ms / 1000.0
        self.t = 0.0
        self.frames: list[Frame] = list(self.m.power_on(0.0))
        self.slot = slot or setpoint_slots([self.axis])[self.node]
        if configure:
            self.frames += self.m.configure(int(period_ms), slot=self.slot, t=0.0)
            if period_ms != int(period_ms):
                self.sdo(0x1006, 0, round(period_ms * 1000))

    def sdo(self, index: int, sub: int, value: int) -> None:
        self.frames += self.m.sdo_write(index, sub, value, self.t)

    def frame(self, cob_id: int, data: bytes, t: float | None = None) -> None:
        self.frames += self.m.on_frame(cob_id, data, self.t if t is None else t)

    def sync(self, n: int = 1, dt: float | None = None) -> None:
        for _ in range(n):
            self.t += self.period if dt is None else dt
            self.frames += self.m.advance(self.t)
            self.frames += self.m.on_sync(self.t)

    def cw(self, value: int) -> None:
        """Controlword in RPDO1 (type 1 after configuration: applied at the next SYNC)."""
        self.frame(cob.rpdo1_id(self.node), value.to_bytes(2, "little"), self.t + 0.0005)

    def setpoint(self, x: int, v: int = 0, lead_s: float | None = None) -> None:
        """The set point for the next SYNC, sent right after this one (or `lead_s` before the next)."""
        data = bytearray(self.slot.frame_bytes)
        pack_setpoints(self.slot, data, x, v)
        at = self.t + 0.001 if lead_s is None else self.t + self.period - lead_s
        self.frame(self.slot.cob_id, bytes(data), at)

    def enable(self) -> None:
        """What the master's enable_drives does: hold writes, shutdown, switch on + enable operation."""
        for w in XTRAPULS_IP.hold_writes(self.m.sdo_read(0x6064, 0)):
            self.sdo(w.index, w.sub, w.value)
        self.sdo(0x6040, 0, 0x0006)
        self.sdo(0x6040, 0, 0x000F)
        assert self.m.ready_for_job

    def lock(self) -> None:
        """SYNC for 180 ms and one more period."""
        self.sync(math.ceil(0.18 / self.period) + 1)
        assert self.m.pll_locked

    def start(self, x0: int | None = None, v0: int = 0) -> None:
        """Controlword 0x001F with the first set point, applied at the next SYNC."""
        self.cw(0x001F)
        self.setpoint(self.m.sdo_read(0x6064, 0) if x0 is None else x0, v0)
        self.sync()
        assert self.m.ip_active

    def emcys(self) -> list[codec.EmcyMessage]:
        return [codec.decode_emcy(f.data) for f in self.frames if f.cob_id == cob.emcy_id(self.node)]

    def of(self, cob_id: int) -> list[Frame]:
        return [f for f in self.frames if f.cob_id == cob_id]


def abort_code(fn: Any, *args: Any) -> int:
    with pytest.raises(SdoAbort) as e:
        fn(*args)
    return e.value.code


# ---- CiA 402 and CiA 301 as the manual has them --------------------------------------------------------
def test_enable_sequence_gives_the_manuals_statuswords() -> None:
    r = Rig(configure=False)
    seen = []
    for cw in (0x0000, 0x0006, 0x0007, 0x000F):  # seed 003 "Correct sequence to enable the drive"
        r.sdo(0x6040, 0, cw)
        seen.append(r.m.sdo_read(0x6041, 0))
    assert seen == [0x0240, 0x0221, 0x0223, 0x0227]
    assert [sw & 0x026F for sw in seen] == seen  # "The mask for testing the status word is 0x026F"
    r2 = Rig(configure=False)
    r2.sdo(0x6040, 0, 0x0006)
    r2.sdo(0x6040, 0, 0x000F)  # "seq 1 and seq 3 may be omitted"
    assert r2.m.statusword == 0x0227 and r2.m.state == Cia402State.OPERATION_ENABLED


def test_bit4_starts_ip_and_bit12_reports_it_halt_does_nothing() -> None:
    r = Rig()
    r.enable()
    r.lock()
    r.start()
    assert r.m.statusword == 0x1227  # "Ip-Mode active"
    x = r.m.sdo_read(0x6064, 0)
    r.cw(0x011F)  # halt: "only in PV, PT, AS, AT"
    r.setpoint(x + 500)
    r.sync()
    r.setpoint(x + 1000)
    r.sync()
    assert r.m.ip_active and r.m.statusword == 0x1227 and r.m.sdo_read(0x6062, 0) == x + 500
    assert not r.emcys()
    r2 = Rig()
    r2.enable()
    r2.lock()
    r2.start()
    r2.setpoint(5000)
    r2.sync()
    r2.cw(0x000F)  # bit 4 low ends interpolation; the demand holds where it is
    r2.sync()
    held = r2.m.sdo_read(0x6062, 0)
    r2.sync(3)
    assert not r2.m.ip_active and r2.m.statusword == 0x0227 and r2.m.sdo_read(0x6062, 0) == held
    assert not r2.emcys()


def test_modes_and_submodes() -> None:
    r = Rig(configure=False)
    assert r.m.sdo_read(0x6502, 0) == 0x60  # homing and interpolated position mode
    r.sdo(0x6060, 0, 7)
    assert r.m.sdo_read(0x6061, 0) == 7 and r.m.mode == 7
    assert abort_code(r.m.sdo_write, 0x6060, 0, 8) == odm.ABORT_INVALID_VALUE  # no CSP on CANopen
    assert r.m.sdo_read(0x60C0, 0) == 0  # default: linear
    for submode in (0, -1, -2):
        r.sdo(0x60C0, 0, submode)
        assert r.m.sdo_read(0x60C0, 0) == submode
    assert abort_code(r.m.sdo_write, 0x60C0, 0, -3) == odm.ABORT_VALUE_TOO_LOW
    assert abort_code(r.m.sdo_write, 0x60C0, 0, 1) == odm.ABORT_VALUE_TOO_HIGH
    assert abort_code(r.m.sdo_write, 0x1600, 1, 0x60C00010) == odm.ABORT_PARAMETER_INCOMPATIBLE  # PDO valid
    r.sdo(0x1400, 1, 0x80000201)
    r.sdo(0x1600, 0, 0)
    assert abort_code(r.m.sdo_write, 0x1600, 1, 0x60C00010) == odm.ABORT_CANNOT_MAP  # "PDO Mapping No"


def test_no_bootup_message_unless_0x2010() -> None:
    r = Rig(configure=False)
    assert r.frames == [] and r.m.nmt_state == NmtState.PRE_OPERATIONAL  # default 0: "No Bootup message"
    r.frame(0, bytes((NmtCommand.RESET_NODE, 1)))
    assert r.of(0x701) == []
    r.sdo(0x2010, 0, 1)
    r.frame(0, bytes((NmtCommand.RESET_COMMUNICATION, 1)))  # 0x2010 is not a communication object: kept
    assert r.of(0x701) == [Frame(0x701, b"\x00")] and r.m.nmt_state == NmtState.PRE_OPERATIONAL
    r.frame(0, bytes((NmtCommand.RESET_NODE, 1)))  # back to its default 0 ...
    assert len(r.of(0x701)) == 1
    r.sdo(0x2010, 0, 1)
    r.sdo(0x1010, 1, 0x65766173)  # ... unless saved
    r.frame(0, bytes((NmtCommand.RESET_NODE, 1)))
    assert len(r.of(0x701)) == 2
    assert abort_code(r.m.sdo_write, 0x2010, 0, 2) == odm.ABORT_VALUE_TOO_HIGH


def test_sync_period_multiples_of_500_us_up_to_150_ms() -> None:
    r = Rig(configure=False)
    assert r.m.sdo_read(0x1006, 0) == 10_000  # default 10 ms
    for ok in (0, 500, 1500, 2000, 150_000):
        r.sdo(0x1006, 0, ok)
        assert r.m.sdo_read(0x1006, 0) == ok
    for bad in (250, 1250, 10_001):
        assert abort_code(r.m.sdo_write, 0x1006, 0, bad) == odm.ABORT_INVALID_VALUE
    assert abort_code(r.m.sdo_write, 0x1006, 0, 150_500) == odm.ABORT_VALUE_TOO_HIGH  # "0..150000"
    assert r.m.sdo_read(0x1006, 0) == 150_000


def test_ds301_v401_objects_only() -> None:
    m = XtrapulsDrive(1, xaxis(), SETTINGS)
    for index in (0x1012, 0x1013, 0x1019, 0x60C5, 0x60C2, 0x60C4):
        assert not m.has_object(index)
        assert abort_code(m.sdo_read, index, 0) == odm.ABORT_NO_OBJECT
    assert abort_code(m.sdo_read, 0x1800, 3) == odm.ABORT_NO_SUBINDEX  # PDO parameters: 2 sub-indices
    assert abort_code(m.sdo_read, 0x0006, 0) == odm.ABORT_NO_OBJECT  # dummies: "cannot be accessed via SDO"
    assert m.sdo_read(0x6080, 0) == 3000 and m.sdo_read(0x6085, 0) == 0x00200000
    assert m.sdo_read(0x6093, 1) == 4096 and m.sdo_read(0x6093, 2) == 4096
    assert abort_code(m.sdo_write, 0x6093, 1, 8192) == odm.ABORT_VALUE_TOO_HIGH  # "must be set at 4096"


def test_default_pdo_map() -> None:
    r = Rig(configure=False)
    m = r.m
    assert [m.sdo_read(0x1600 + n, 1) for n in range(3)] == [0x60400010, 0x60FF0020, 0x60C10120]
    assert [m.sdo_read(0x1400 + n, 2) for n in range(4)] == [255, 255, 1, 0]
    assert [m.sdo_read(0x1400 + n, 1) for n in range(4)] == [0x201, 0x301, 0x401, 0x501]
    assert [m.sdo_read(0x1A00 + n, 1) for n in range(3)] == [0x60410010, 0x606C0020, 0x60640020]
    assert [m.sdo_read(0x1800 + n, 2) for n in range(4)] == [253, 253, 1, 0]
    r.frame(0, bytes((NmtCommand.START, 0)))
    r.sync(3)
    assert r.of(0x381) == [Frame(0x381, (0).to_bytes(4, "little"))] * 3  # TPDO3: 0x6064 at every SYNC
    assert r.of(0x181) == [] and r.of(0x281) == []  # RTR only
    r.frame(0x201, (0x0006).to_bytes(2, "little"))  # RPDO1 type 255: applied on reception
    assert m.state == Cia402State.READY_TO_SWITCH_ON and r.of(0x181) == []
    r.sdo(0x1800, 1, 0x80000181)
    r.sdo(0x1800, 2, 253)  # an RTR type is accepted here (TPDO1/2 default to it)
    assert abort_code(m.sdo_write, 0x1400, 2, 253) == odm.ABORT_INVALID_VALUE  # not for an RPDO


# ---- multiplexed RPDO and 16-bit set points ----------------------------------------------------------
def test_the_manuals_multiplexed_example_driven_by_one_frame() -> None:
    """Seed 003 "Multiplexed data": COB-ID 0x501, drive k maps 0x60C10110 as entry k after k-1 dummies
    0x00060010 (no trailing dummies), drive 4 also maps 0x60FF0010 over Data_Ax3."""
    uppers = {1: 0, 2: 0x10000, 3: -0x10000, 4: 5 * 0x10000}
    drives = {}
    for k in range(1, 5):
        m = XtrapulsDrive(k, xaxis(k), SETTINGS)
        m.power_on(0.0)
        m.sdo_write(0x3350, 0, 1)
        m.sdo_write(0x60C1, 1, uppers[k])  # "set the upper word with object 60C1-1 via SDO"
        m.sdo_write(0x1402, 1, 0x80000000 | 0x501)
        m.sdo_write(0x1602, 0, 0)
        entries = [0x00060010] * (k - 1) + [0x60C10110]
        if k == 4:
            entries = [0x00060010, 0x00060010, 0x60FF0010, 0x60C10110]
        for i, e in enumerate(entries, start=1):
            m.sdo_write(0x1602, i, e)
        m.sdo_write(0x1602, 0, len(entries))
        m.sdo_write(0x1402, 1, 0x501)
        m.on_frame(0, bytes((NmtCommand.START, 0)), 0.0)
        drives[k] = m
    data = [0x0011, 0x2233, 0xFFFE, 0x7FF0]  # Data_Ax1..Data_Ax4, LSB first
    frame = b"".join(d.to_bytes(2, "little") for d in data)
    for m in drives.values():
        assert m.on_frame(0x501, frame, 0.001) == []  # one frame for all; a longer one than drive 1's map
        m.on_sync(0.01)
    assert drives[1].sdo_read(0x60C1, 1) == 0x0011
    assert drives[2].sdo_read(0x60C1, 1) == 0x10000 + 0x2233
    assert drives[3].sdo_read(0x60C1, 1) == -0x10000 + 0xFFFE - 0x10000  # nearest -0x10000: -65538
    assert drives[4].sdo_read(0x60C1, 1) == 5 * 0x10000 + 0x7FF0
    assert drives[4].sdo_read(0x60FF, 0) == -2  # Data_Ax3 = 0xFFFE as a signed 16-bit velocity
    assert drives[3].sdo_read(0x60FF, 0) == 0
    short = drives[4].on_frame(0x501, frame[:6], 0.012)  # shorter than its mapping: CiA 301 EMCY 0x8210
    assert codec.decode_emcy(short[0].data).code == codec.EMCY_PDO_LENGTH


def test_16_bit_mapping_needs_0x3350() -> None:
    m = XtrapulsDrive(1, xaxis(), SETTINGS)
    m.sdo_write(0x1402, 1, 0x80000401)
    m.sdo_write(0x1602, 0, 0)
    assert abort_code(m.sdo_write, 0x1602, 1, 0x60C10110) == odm.ABORT_CANNOT_MAP
    assert abort_code(m.sdo_write, 0x1602, 1, 0x60640010) == odm.ABORT_CANNOT_MAP  # only the set points
    m.sdo_write(0x3350, 0, 1)
    m.sdo_write(0x1602, 1, 0x60C10110)


@pytest.mark.parametrize("start", [65_530, -65_540, 2**31 - 400_000])
def test_16_bit_set_points_across_65536_boundaries(start: int) -> None:
    a1, a2 = xaxis(1, mux_group=1), xaxis(2, mux_group=1)
    slots = setpoint_slots([a1, a2])
    r = Rig(a1, slot=slots[1], initial_position=float(start))
    assert r.m.sdo_read(0x3350, 0) == 1 and r.m.sdo_read(0x1602, 1) == 0x60C10110
    r.enable()  # the hold write 0x60C1:01 = position sets the upper word
    r.lock()
    r.start(start)
    xs = [start + 1500 * k for k in range(1, 40)] + [start + 1500 * 39 - 2000 * k for k in range(1, 40)]
    for x in xs:
        r.setpoint(x)
        r.sync()
        assert r.m.sdo_read(0x60C1, 1) == x
    r.setpoint(xs[-1])
    r.sync()
    assert r.m.sdo_read(0x6062, 0) == xs[-1] and not r.emcys()


def test_16_bit_velocities_of_a_pv_group_are_sign_extended() -> None:
    a1, a2 = xaxis(1, "pv", mux_group=1), xaxis(2, "pv", mux_group=1)
    slots = setpoint_slots([a1, a2])
    assert slots[2].velocity_bits == 16 and slots[2].offset == 4
    r = Rig(a2, slot=slots[2], initial_position=-70_000.0)
    assert r.m.sdo_read(0x1602, 2) == 0x60C10110 and r.m.sdo_read(0x1602, 3) == 0x60C10210
    r.sdo(0x60C1, 1, -70_000)
    r.frame(0, bytes((NmtCommand.START, 0)))
    frame = bytearray(8)
    pack_setpoints(slots[1], frame, 5, 7)
    pack_setpoints(slots[2], frame, -70_100, -1234)
    r.frame(0x401, bytes(frame), 0.001)
    r.sync()
    assert (r.m.sdo_read(0x60C1, 1), r.m.sdo_read(0x60C1, 2)) == (-70_100, -1234)


# ---- the interpolation, tick by tick -------------------------------------------------------------------
def round_half_away(x: float) -> int:
    return math.floor(x + 0.5) if x >= 0 else -math.floor(-x + 0.5)


def expected_ticks(submode: str, xs: list[int], vs: list[int], k: int, n: int, period_s: float) -> list[int]:
    """The brief's formulas for the period after the SYNC that latched xs[k], at s = tau / n."""
    out = []
    for tau in range(1, n + 1):
        s = tau / n
        x0, x1 = xs[k - 1], xs[k]
        if submode == "linear":
            p = x0 + (x1 - x0) * s
        elif submode == "pv":
            h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
            p = h00 * x0 + h10 * period_s * vs[k - 1] + h01 * x1 + h11 * period_s * vs[k]
        else:
            xm = xs[k - 2]
            p = x0 + s * (x1 - xm) / 2 + s * s * (x1 - 2 * x0 + xm) / 2
        out.append(round_half_away(p))
    return out


@pytest.mark.parametrize("submode", ["linear", "pv", "p3"])
@pytest.mark.parametrize("period_ms", [10, 3])
def test_demand_at_every_tick_follows_the_submode_formula(submode: str, period_ms: int) -> None:
    r = Rig(xaxis(submode=submode), period_ms=period_ms, initial_position=1000.0)
    m = r.m
    assert isinstance(m, Recording)
    r.enable()
    r.lock()
    rng = random.Random(period_ms)
    xs = [1000, 1000, 1000]  # the hold write latched at two SYNCs, then the first set point (where it is)
    vs = [0, 0, 0]
    r.start(1000)
    for _ in range(30):
        xs.append(xs[-1] + rng.randint(-3000, 3000))
        vs.append(rng.randint(-400_000, 400_000))
        r.setpoint(xs[-1], vs[-1])
        r.sync()
    for _ in range(2):  # the last set point twice: the drive reaches it and stays
        xs.append(xs[-1])
        vs.append(0)
        r.setpoint(xs[-1], 0)
        before = len(m.tick_demands)
        r.sync()
    assert not r.emcys()
    ticks = m.tick_demands
    n = period_ms
    # the period after the SYNC that latched xs[k] ends at the next SYNC with the demand exactly xs[k]:
    # the ticks since the start are those of k = 2 (the start) .. len(xs) - 2
    periods = len(xs) - 3
    got = ticks[len(ticks) - periods * n:]
    assert before == len(ticks) - n
    for j in range(periods):
        k = j + 2
        assert got[j * n:(j + 1) * n] == expected_ticks(submode, xs, vs, k, n, period_ms / 1000.0), k
        assert got[(j + 1) * n - 1] == xs[k]
    assert m.sdo_read(0x6062, 0) == xs[-2] == m.sdo_read(0x30C1, 0)


def test_a_period_of_half_milliseconds_samples_the_polynomial_where_the_ticks_fall() -> None:
    r = Rig(period_ms=2.5, initial_position=0.0)
    m = r.m
    assert isinstance(m, Recording)
    r.enable()
    r.lock()
    r.start(0)
    for x in (2500, 5000, 7500, 10_000, 12_500):
        r.setpoint(x)
        r.sync()
    # each period's line climbs 2500 counts in 2500 us: the demand at a tick is its time in us since the
    # SYNC that latched 2500 (1 ms ticks on a 2.5 ms period fall at s = 0.4, 0.8 | 0.2, 0.6, 1.0 | ...)
    ticks = m.tick_demands[-10:]
    assert [b - a for a, b in itertools.pairwise(ticks)] == [1000] * 9
    assert 9000 < ticks[-1] <= 10_000 and ticks[0] > 0
    assert m.sdo_read(0x6062, 0) == ticks[-1]


def test_the_interpolator_runs_in_any_mode_and_starts_from_the_demand() -> None:
    r = Rig(xaxis(submode="p3"), initial_position=100.0)
    r.enable()
    r.lock()
    for x in (300, 700):  # set points while IP is inactive: the interpolator's output moves, the demand not
        r.setpoint(x)
        r.sync()
    assert r.m.sdo_read(0x30C1, 0) == 300 and r.m.sdo_read(0x6062, 0) == 100
    r.start(900)  # P3 from the demand 100 (not from 700) toward 900, with x_{k-2} = 300 from its history
    r.setpoint(900)
    r.sync()
    assert r.m.sdo_read(0x6062, 0) == 900
    assert isinstance(r.m, Recording)
    first = r.m.tick_demands[-10:]
    assert first == [round_half_away(100 + s * (900 - 300) / 2 + s * s * (900 - 200 + 300) / 2)
                     for s in (t / 10 for t in range(1, 11))]


# ---- errors 50, 49 and the PLL -------------------------------------------------------------------------
def running(period_ms: float = 10, **kw: Any) -> Rig:
    r = Rig(period_ms=period_ms, **kw)
    r.enable()
    r.lock()
    r.start()
    for _ in range(3):
        r.setpoint(r.m.sdo_read(0x60C1, 1) + 100)
        r.sync()
    assert r.m.ip_active and not r.emcys()
    return r


def test_error_50_on_a_missing_set_point() -> None:
    r = running()
    r.sync()
    emcy = r.emcys()
    assert [e.code for e in emcy] == [EMCY_IP]
    assert emcy[0].register & codec.ER_GENERIC and emcy[0].manufacturer == bytes((50, 0, 0, 0, 0))
    assert r.m.state == Cia402State.FAULT and r.m.sdo_read(0x603F, 0) == EMCY_IP
    assert r.m.sdo_read(0x6041, 0) == 0x0208


@pytest.mark.parametrize(("lead_us", "faults"), [(50, True), (99, True), (100, False), (150, False)])
def test_error_50_on_a_set_point_less_than_100_us_before_its_sync(lead_us: int, faults: bool) -> None:
    r = running()
    for _ in range(3):
        r.setpoint(r.m.sdo_read(0x60C1, 1) + 100, lead_s=lead_us * 1e-6)
        r.sync()
    assert [e.code for e in r.emcys()] == ([EMCY_IP] if faults else [])
    assert r.m.ip_active is not faults


def test_error_49_on_sync_jitter_of_half_a_period() -> None:
    r = running()
    r.setpoint(r.m.sdo_read(0x60C1, 1) + 100)
    r.sync(dt=0.0149)  # 4.9 ms late: no error
    r.setpoint(r.m.sdo_read(0x60C1, 1) + 100)
    r.sync(dt=0.0051)
    assert not r.emcys()
    r.setpoint(r.m.sdo_read(0x60C1, 1) + 100)
    r.sync(dt=0.005)  # half a period early
    emcy = r.emcys()
    assert [e.code for e in emcy] == [EMCY_SYNC] and emcy[0].manufacturer[0] == 49
    late = running()
    late.setpoint(late.m.sdo_read(0x60C1, 1) + 100)
    late.sync(dt=0.015)
    assert [e.code for e in late.emcys()] == [EMCY_SYNC]


def test_error_49_on_sync_loss() -> None:
    r = running()
    r.t += 0.016
    r.frames += r.m.advance(r.t)
    assert [e.code for e in r.emcys()] == [EMCY_SYNC]


@pytest.mark.parametrize(("error", "faults", "gap_factor"), [
    (0.005, True, 1.5), (-0.005, True, 1.5), (0.002, False, 1.5), (-0.002, False, 1.5),
    # the in-process runtimes' looser checks (factor 3.0): 1.6 %
    (0.005, False, 3.0), (0.017, True, 3.0)])
def test_error_49_on_a_period_error_of_0_4_percent(error: float, faults: bool, gap_factor: float) -> None:
    r = Rig(sync_gap_factor=gap_factor)
    r.period = 0.010 * (1 + error)  # the master's SYNC runs slow or fast; the PLL still locks (< 500 us)
    r.enable()
    r.lock()
    r.start()
    for _ in range(40):
        r.setpoint(r.m.sdo_read(0x60C1, 1) + 100)
        r.sync()
        if r.emcys():
            break
    assert [e.code for e in r.emcys()] == ([EMCY_SYNC] if faults else [])


def test_bit4_before_180_ms_of_sync_is_refused_until_it_falls_and_rises_again() -> None:
    r = Rig(initial_position=0.0)
    r.enable()
    r.cw(0x001F)  # bit 4 high from the first SYNC on
    target = 0
    for _ in range(40):  # 400 ms: the PLL locks after 180 ms, the early request stays refused
        target += 200
        r.setpoint(target)
        r.sync()
        assert not r.m.ip_active and r.m.statusword & codec.SW_IP_ACTIVE == 0
        assert r.m.sdo_read(0x6062, 0) == 0 and r.m.position_actual == 0
    assert r.m.pll_locked and r.m.ip_refusals == 1 and not r.emcys()
    r.cw(0x000F)  # bit 4 low at a SYNC ...
    r.setpoint(target)
    r.sync()
    assert not r.m.ip_active
    r.cw(0x001F)  # ... and high again, now with the PLL locked: ip mode starts at the next SYNC
    r.setpoint(target + 200)
    r.sync()
    assert r.m.ip_active and r.m.statusword == 0x1227 and r.m.ip_refusals == 1
    r.setpoint(target + 400)
    r.sync()
    assert r.m.sdo_read(0x6062, 0) == target + 200  # from the demand 0 to the set point latched at the start


def test_bit4_after_180_ms_of_sync_starts_at_once() -> None:
    r = Rig(initial_position=0.0)
    r.enable()
    r.sync(18)  # SYNC since t = 10 ms: the 18th is 170 ms after the first, the 19th 180 ms
    assert not r.m.pll_locked
    r.sync()
    assert r.m.pll_locked
    r.cw(0x001F)
    r.setpoint(0)
    r.sync()
    assert r.m.ip_active and r.m.ip_refusals == 0


def test_a_drive_that_needs_more_than_180_ms_locks_later() -> None:
    """"At least 180 ms": `sim.sync_lock_ms` is the drive's own lock time."""
    r = Rig(replace(xaxis(), sim=SimDriveOptions(sync_lock_ms=300.0)), initial_position=0.0)
    r.enable()
    r.sync(30)  # the 30th SYNC is 290 ms after the first
    assert not r.m.pll_locked
    r.sync()
    assert r.m.pll_locked


def test_the_held_reading_takes_an_early_bit4_at_the_lock() -> None:
    """`sim.early_bit4 = "held"`: bit 4 set before the lock is kept and starts ip mode at the lock, no edge."""
    r = Rig(replace(xaxis(), sim=SimDriveOptions(early_bit4="held")), initial_position=0.0)
    r.enable()
    r.cw(0x001F)
    for _ in range(18):
        r.setpoint(0)
        r.sync()
        assert not r.m.ip_active
    r.setpoint(0)
    r.sync()  # 180 ms after the first SYNC: locked, the standing request taken
    assert r.m.pll_locked and r.m.ip_active and r.m.ip_refusals == 0


def test_sim_options_for_the_lock_name_the_bad_value() -> None:
    with pytest.raises(PlanningError, match=r"sim\.sync_lock_ms"):
        SimDriveOptions(sync_lock_ms=100.0)
    with pytest.raises(PlanningError, match=r"sim\.early_bit4 = 'later'"):
        SimDriveOptions(early_bit4="later")


def test_the_pll_needs_a_period_within_the_sync_error_limit() -> None:
    r = Rig()
    r.sdo(0x2006, 4, 30)  # 30 us
    r.period = 0.01004  # 40 us off
    r.sync(30)
    assert not r.m.pll_locked
    r.sdo(0x2006, 4, 50)
    r.sync()
    assert r.m.pll_locked
    r.sync(dt=0.004)  # a jitter of half a period or more restarts the lock
    assert not r.m.pll_locked
    r.sdo(0x1006, 0, 10_000)  # so does a new period
    r.sync(17)
    assert not r.m.pll_locked


# ---- faults, EMCY, quick stop, heartbeat ---------------------------------------------------------------
def test_fault_reaction_is_stop_0_and_emcy_follows_0x205f() -> None:
    r = running()
    r.m.sdo_write(0x6065, 0, 0)  # following error at the next tick
    r.setpoint(r.m.sdo_read(0x60C1, 1) + 500)
    r.sync()
    emcy = r.emcys()
    assert [e.code for e in emcy] == [EMCY_FE] and emcy[0].manufacturer == bytes((35, 0, 0, 0, 0))
    assert r.m.state == Cia402State.FAULT and r.m.current_a == 0.0  # power off at once, no ramp
    r.sdo(0x6040, 0, 0x0000)
    r.sdo(0x6040, 0, 0x0080)
    assert r.m.state == Cia402State.SWITCH_ON_DISABLED and len(r.emcys()) == 1  # 0x205F = 1: no reset EMCY
    r2 = running()
    r2.sdo(0x205F, 0, 2)
    r2.sync()
    r2.sdo(0x6040, 0, 0x0080)
    assert [e.code for e in r2.emcys()] == [EMCY_IP, 0x0000]
    r3 = running()
    r3.sdo(0x205F, 0, 0)
    r3.sync()
    assert r3.m.state == Cia402State.FAULT and r3.emcys() == []


def test_error_51_on_heartbeat_consumer_timeout() -> None:
    r = Rig()
    r.enable()
    r.sdo(0x1016, 1, (0x7F << 16) | 50)
    r.frame(0x77F, bytes((0x05,)))
    r.t += 0.06
    r.frames += r.m.advance(r.t)
    emcy = r.emcys()
    assert [e.code for e in emcy] == [EMCY_HB] and emcy[0].manufacturer[0] == 51


@pytest.mark.parametrize("option", [0, 1, 2, 3, 5, 6, 7])
def test_quick_stop_options(option: int) -> None:
    r = running()
    for _ in range(5):
        r.setpoint(r.m.sdo_read(0x60C1, 1) + 3000)
        r.sync()
    r.sdo(0x605A, 0, option)
    r.sdo(0x6085, 0, 2_000_000)  # user units/s^2 (= counts: the master's position factor)
    r.sdo(0x3300, 1, 1_000_000)
    r.sdo(0x6040, 0, 0x000B)
    assert not r.m.ip_active
    r.sync(40)
    final = Cia402State.QUICK_STOP_ACTIVE if option >= 5 else Cia402State.SWITCH_ON_DISABLED
    assert r.m.state == final and not r.emcys()


@pytest.mark.parametrize(("option", "ramp_ms"), [(2, 150), (1, 300)])
def test_quick_stop_ramps_in_user_units(option: int, ramp_ms: int) -> None:
    r = running()
    for _ in range(5):
        r.setpoint(r.m.sdo_read(0x60C1, 1) + 3000)  # 300 000 counts/s
        r.sync()
    r.sdo(0x605A, 0, option)
    r.sdo(0x6085, 0, 2_000_000)
    r.sdo(0x3300, 1, 1_000_000)
    r.sdo(0x6040, 0, 0x000B)
    r.sync(ramp_ms // 10 - 1)
    assert r.m.state == Cia402State.QUICK_STOP_ACTIVE
    r.sync(2)
    assert r.m.state == Cia402State.SWITCH_ON_DISABLED


def test_quick_stop_option_4_is_refused() -> None:
    r = Rig(configure=False)
    assert abort_code(r.m.sdo_write, 0x605A, 0, 4) == odm.ABORT_INVALID_VALUE
    assert r.m.sdo_read(0x605A, 0) == 1  # the manual's default


def test_position_factor_scales_user_units() -> None:
    axis = xaxis()
    r = Rig(axis, initial_position=0.0)
    assert r.m.sdo_read(0x6093, 2) == axis.counts_per_rev  # the master: user units = counts
    r.sdo(0x6093, 2, 2 * axis.counts_per_rev)  # one user unit = half a count
    r.sdo(0x6065, 0, 40_000)
    r.enable()
    r.lock()
    r.start(0)
    for x in list(range(2000, 20_001, 2000)) + [20_000] * 60:
        r.setpoint(x)
        r.sync()
    assert r.m.sdo_read(0x6062, 0) == 20_000 and r.m.position_demand == 10_000
    assert abs(r.m.position_actual - 10_000) <= 2 and abs(r.m.sdo_read(0x6064, 0) - 20_000) <= 4


# ---- configured by the master ------------------------------------------------------------------------
def xcell(n: int, submode: str, groups: dict[int, int] | None = None, period_ms: int = 10) -> CellConfig:
    cell = make_cell(n, sync_period_ms=period_ms, settings=SETTINGS)
    axes = tuple(replace(a, profile="xtrapuls-ip", ip_submode=submode, mux_group=(groups or {}).get(a.node_id, 0))
                 for a in cell.axes)
    return replace(cell, axes=axes)


def stream(vc: VirtualCell, moves: dict[int, list[int]], period: float = 0.01) -> dict[int, list[int]]:
    """Enable, SYNC 200 ms, start every axis on one SYNC, stream `moves` (per node, one position per SYNC,
    velocity = the finite difference), run out; returns each drive's 0x6062 at every SYNC."""
    vc.enable_drives(0.0)
    t = 0.0
    for _ in range(20):
        t += period
        vc.sync(t)
    demand: dict[int, list[int]] = {n: [] for n in vc.models}
    length = max(len(v) for v in moves.values())
    for k in range(length + 2):
        frames: dict[int, bytearray] = {}
        for node, slot in vc.slots.items():
            xs = moves[node]
            x = xs[min(k, len(xs) - 1)]
            v = round((xs[min(k + 1, len(xs) - 1)] - xs[min(max(k - 1, 0), len(xs) - 1)]) / (2 * period))
            pack_setpoints(slot, frames.setdefault(slot.cob_id, bytearray(slot.frame_bytes)), x, v)
            if k == 0:
                vc.deliver(cob.rpdo1_id(node), (0x001F).to_bytes(2, "little"), t + 0.0005)
        for cob_id, data in frames.items():
            vc.deliver(cob_id, bytes(data), t + 0.001)
        t += period
        vc.advance(t)
        vc.sync(t)
        for node, m in vc.models.items():
            demand[node].append(m.sdo_read(0x6062, 0))
    return demand


@pytest.mark.parametrize("submode", ["linear", "pv", "p3"])
def test_configured_by_the_masters_writes_own_rpdo3_per_submode(submode: str) -> None:
    cell = xcell(2, submode)
    vc = VirtualCell(cell, initial_positions={1: 0.0, 2: 50_000.0})
    for m in vc.models.values():
        assert isinstance(m, XtrapulsDrive)
        assert m.sdo_read(0x60C0, 0) == {"linear": 0, "pv": -1, "p3": -2}[submode]
        assert m.sdo_read(0x3350, 0) == 0 and m.sdo_read(0x1602, 1) == 0x60C10120
        assert m.nmt_state == NmtState.OPERATIONAL
    moves = {1: [round(20_000 * (1 - math.cos(math.pi * k / 30)) / 2) for k in range(31)],
             2: [50_000 - 300 * k for k in range(31)]}
    demand = stream(vc, moves)
    for node, xs in moves.items():
        assert demand[node][1:len(xs) + 1] == xs  # each set point is the demand one period later
    assert all(not m.fault_log for m in vc.models.values())


@pytest.mark.parametrize(("submode", "n", "step"), [("linear", 4, 2500), ("p3", 4, 2500), ("pv", 2, 250)])
def test_configured_by_the_masters_writes_multiplexed_group(submode: str, n: int, step: int) -> None:
    """Groups of 4 (16-bit positions) and of 2 in PV (16-bit positions and velocities: steps of 250 counts
    per 10 ms are 25 000 counts/s, which fits), each across 65536 boundaries."""
    cell = xcell(n, submode, {k: 3 for k in range(1, n + 1)})
    starts = {1: 0.0, 2: 70_000.0, 3: -70_000.0, 4: 2_000_000.0} if step > 1000 else {1: 65_000.0, 2: -60_000.0}
    vc = VirtualCell(cell, initial_positions={k: starts[k] for k in range(1, n + 1)})
    cob_ids = {s.cob_id for s in vc.slots.values()}
    assert cob_ids == {0x401}
    for node, m in vc.models.items():
        assert m.sdo_read(0x3350, 0) == 1 and m.sdo_read(0x1402, 1) == 0x401
        layout = XTRAPULS_IP.pdo_layouts(cell.axes[node - 1], vc.slots[node])[1]
        count = m.sdo_read(0x1602, 0)
        assert [m.sdo_read(0x1602, k) for k in range(1, count + 1)] == [e.word for e in layout.entries]
    moves = {k: [int(starts[k]) + (1 if k % 2 else -1) * step * j for j in range(40)] for k in range(1, n + 1)}
    demand = stream(vc, moves)
    for node, xs in moves.items():
        assert demand[node][1:len(xs) + 1] == xs, node
    assert all(not m.fault_log for m in vc.models.values())


def test_configured_and_enabled_over_sdo_in_real_time() -> None:
    """SimulatedCell (canopen LocalNodes) + MasterAdapter.configure_drives/enable_drives on the python-can
    virtual bus: the dummy mapping and the shared COB-ID of a multiplexed group of 4, then one frame."""
    cell = xcell(4, "linear", {k: 1 for k in range(1, 5)})
    starts = {1: 10.0, 2: 70_000.0, 3: -70_000.0, 4: 0.0}
    with SimulatedCell(cell, sync_gap_factor=5.0, initial_positions=starts) as sim, \
            MasterAdapter(None, cell, sdo_timeout_s=1.0) as m:  # a loaded machine answers SDO late
        m.configure_drives()
        assert m.absent[1] == (0x1012, 0x1013, 0x1019, 0x60C2)  # what a DS-301 v4.01 drive lacks
        m.enable_drives()
        with sim.locked() as models:
            for node, d in models.items():
                assert d.state == Cia402State.OPERATION_ENABLED and d.ready_for_job
                assert d.sdo_read(0x60C1, 1) == round(starts[node])
                assert d.nmt_state == NmtState.OPERATIONAL
        for node, local in sim.nodes.items():
            rpdo3 = local.rpdo.map[3]  # what canopen made of the mapping on the drive's side
            axis = cell.axes[node - 1]
            layout = XTRAPULS_IP.pdo_layouts(axis, m.slots[node])[1]
            assert rpdo3.enabled and rpdo3.cob_id == 0x401 and layout.number == 3
            assert [(v.index, v.length) for v in rpdo3.map] == [(e.index, e.bits) for e in layout.entries]
            assert any(v.index < 0x1000 for v in rpdo3.map)
        frame = bytearray(8)
        targets = {1: 1234, 2: 70_000 + 999, 3: -70_000 - 999, 4: -5}
        for node, slot in m.slots.items():
            pack_setpoints(slot, frame, targets[node])
        m.send(0x401, bytes(frame))
        m.send_sync()

        def latched() -> bool:
            with sim.locked() as models:
                return all(d.sdo_read(0x60C1, 1) == targets[n] for n, d in models.items())

        assert wait_until(latched, 2.0)
    sim.check()


def test_make_drive_picks_the_family() -> None:
    m = make_drive(xaxis())
    assert isinstance(m, XtrapulsDrive) and m.family == "xtrapuls-ip"
    with pytest.raises(ValueError, match="locked to SYNC"):
        XtrapulsDrive(1, replace(xaxis(), sim=SimDriveOptions(clock="own")), SETTINGS)
