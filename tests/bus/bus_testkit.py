"""Shared helpers for tests/bus: test axes and cells, a virtual-time drive harness, real-time buses.

Real-time tests use a fresh python-can `virtual` channel per test (`unique_channel`) and close every
bus, network and thread they open.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import replace

import canopen

from bus import cob, codec
from bus.codec import Frame
from bus.sim.epos import EposDrive
from planner.config import AxisConfig, BusConfig, CellConfig, DriveSettings
from planner.encoding import record
from planner.encoding.hermite import counts_per_ms_to_rpm

CPR = 8192
_channels = itertools.count()


def unique_channel(prefix: str = "bus-test") -> str:
    return f"{prefix}-{next(_channels)}-{time.monotonic_ns()}"


def make_axis(node_id: int = 1, **overrides: float) -> AxisConfig:
    """One motor revolution per user unit: velocity 20 rev/s = 1200 rpm, acceleration 200 rev/s^2."""
    kw: dict[str, float | int | str] = dict(
        name=f"a{node_id}", node_id=node_id, counts_per_unit=float(CPR), counts_per_rev=CPR,
        velocity=20.0, acceleration=200.0, jerk=4000.0, position_min=-1000.0, position_max=1000.0,
        max_profile_velocity_rpm=3000.0, max_acceleration=400.0,
    )
    kw.update(overrides)
    return AxisConfig(**kw)  # type: ignore[arg-type]


def make_cell(n_axes: int = 1, *, sync_period_ms: int = 10, channel: str | None = None,
              settings: DriveSettings | None = None) -> CellConfig:
    return CellConfig(
        name="test", sync_period_ms=sync_period_ms,
        axes=tuple(make_axis(i + 1) for i in range(n_axes)),
        bus=BusConfig("virtual", channel or unique_channel(), 1_000_000),
        drive=settings or DriveSettings(),
    )


def ramp_records(distance_counts: int, *, cruise_rpm: float = 600.0, seg_ms: int = 10,
                 start: int = 0) -> list[tuple[int, int, int]]:
    """Records (p, v_rpm, dt) of a smooth move (1 - cos) over `distance_counts`, plus the end record."""
    v_peak_cpms = cruise_rpm * CPR / 60000.0
    segments = math.ceil(math.pi * abs(distance_counts) / (2.0 * v_peak_cpms) / seg_ms)
    duration_ms = max(2, segments) * seg_ms
    n = duration_ms // seg_ms
    out = []
    for k in range(1, n + 1):
        s = k / n
        p = start + distance_counts * (1.0 - math.cos(math.pi * s)) / 2.0
        v = distance_counts * math.pi / (2.0 * duration_ms) * math.sin(math.pi * s)  # counts/ms
        out.append((round(p), round(counts_per_ms_to_rpm(v, CPR)), seg_ms))
    out[-1] = (start + distance_counts, 0, seg_ms)
    out.append((start + distance_counts, 0, 0))
    return out


class VDrive:
    """A EposDrive in virtual time, configured like the master would, with frame bookkeeping."""

    def __init__(self, axis: AxisConfig | None = None, *, sync_period_ms: int = 10, configure: bool = True,
                 settings: DriveSettings | None = None, **model_kw: object):
        self.axis = axis or make_axis()
        self.node = self.axis.node_id
        self.period_ms = sync_period_ms
        self.t = 0.0
        self.frames: list[Frame] = []
        self.model = EposDrive(self.node, self.axis, settings or DriveSettings(), **model_kw)  # type: ignore[arg-type]
        self.frames += self.model.power_on(self.t)
        if configure:
            self.frames += self.model.configure(sync_period_ms, t=self.t)

    # ---- bus
    def frame(self, cob_id: int, data: bytes) -> list[Frame]:
        out = self.model.on_frame(cob_id, data, self.t)
        self.frames += out
        return out

    def sync(self, n: int = 1, dt_s: float | None = None) -> list[Frame]:
        out: list[Frame] = []
        for _ in range(n):
            self.t += self.period_ms / 1000.0 if dt_s is None else dt_s
            out += self.model.advance(self.t)
            out += self.model.on_sync(self.t)
        self.frames += out
        return out

    def cw(self, value: int) -> list[Frame]:
        """Controlword through the synchronous RPDO1 (applied at the next SYNC)."""
        return self.frame(cob.rpdo1_id(self.node), cob.pack_controlword(value))

    def sdo(self, index: int, sub: int, value: int) -> list[Frame]:
        out = self.model.sdo_write(index, sub, value, self.t)
        self.frames += out
        return out

    def record(self, p: int, v: int, dt: int) -> list[Frame]:
        return self.frame(cob.rpdo2_id(self.node), record.pack((p, v, dt)))

    # ---- sequences
    def enable(self) -> None:
        """Seed sequence: shutdown, switch on + enable operation, buffer clear then enable."""
        self.cw(0x0006)
        self.sync()
        self.cw(0x000F)
        self.sync()
        assert self.model.state == codec.Cia402State.OPERATION_ENABLED
        self.sdo(0x60C4, 6, 0)
        self.sdo(0x60C4, 6, 1)

    def start(
        self, records: list[tuple[int, int, int]], prime: int | None = None
    ) -> list[tuple[int, int, int]]:
        """Prime the FIFO, controlword 0x001F, one SYNC to apply it. Returns the records not yet sent."""
        k = len(records) if prime is None else prime
        if self.model.controlword & codec.CW_ENABLE_IP:  # bit 4 must rise
            self.cw(self.model.controlword & ~codec.CW_ENABLE_IP)
            self.sync()
        for r in records[:k]:
            self.record(*r)
        self.cw(0x001F)
        self.sync()
        return records[k:]

    def run(self, pending: list[tuple[int, int, int]], *, keep: int = 8, max_syncs: int = 10_000,
            until: Callable[[EposDrive], bool] | None = None) -> int:
        """Feed `pending` keeping the FIFO at `keep`, SYNC by SYNC, until ip inactive (or `until`)."""
        pending = list(pending)
        for i in range(max_syncs):
            while pending and self.model.fifo_fill < keep:
                self.record(*pending.pop(0))
            self.sync()
            if until is not None and until(self.model):
                return i + 1
            if until is None and not self.model.ip_active:
                return i + 1
        raise AssertionError("run did not finish")

    def emcys(self) -> list[codec.EmcyMessage]:
        return [codec.decode_emcy(f.data) for f in self.frames if f.cob_id == cob.emcy_id(self.node)]

    def tpdo1(self) -> list[codec.Tpdo1]:
        return [codec.decode_tpdo1(f.data) for f in self.frames if f.cob_id == cob.tpdo1_id(self.node)]


def wait_until(predicate: Callable[[], object], timeout_s: float = 2.0, poll_s: float = 0.005) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(poll_s)
    return bool(predicate())


@contextmanager
def remote_network(channel: str) -> Iterator[canopen.Network]:
    """A stock canopen Network on `channel` (the test's master), disconnected at the end."""
    net = canopen.Network()
    net.NOTIFIER_CYCLE = 0.05
    net.connect(interface="virtual", channel=channel, receive_own_messages=False)
    try:
        yield net
    finally:
        net.sync.stop()  # no-op when never started
        net.disconnect()


def with_settings(cell: CellConfig, **changes: int | float) -> CellConfig:
    return replace(cell, drive=replace(cell.drive, **changes))
