"""Streamer core settings: one frozen, validated parameter object per job (`StreamerSettings.from_cell`).

Drive units. Policy: `lead_ms` (queued motion: survives bus trouble, delays a cancel), `repair_syncs`,
`loss_confirm_syncs`, `repair_margin_ms`, `prime_records_per_sync` (what makes losses repairable:
fifo_feeder.py). Per node: the drives' `readings` (planner/readings.py; `tpdo_sampling` and `rounding`
may be unknown, the others must be known), `feedback` (TPDO2 every n-th SYNC), `time_stamp`, seed 002's
target window and in-target timeout, and `cyclic` (nodes fed one set point per SYNC).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any

from bus.profile import FeedbackSchedule
from planner.readings import MUST_KNOW, DriveReadings, SimDriveOptions
from streamer.core.cyclic_feeder import CyclicAxis

FIFO_SIZE = 64
_EMPTY_CPR: Mapping[int, int] = MappingProxyType({})
_EMPTY_READINGS: Mapping[int, DriveReadings] = MappingProxyType({})
_EMPTY_CYCLIC: Mapping[int, CyclicAxis] = MappingProxyType({})
REFERENCE_READINGS = DriveReadings.of_sim(SimDriveOptions())


@dataclass(frozen=True)
class StreamerSettings:
    sync_period_ms: int = 10
    bitrate: int = 1_000_000
    underflow_watermark: int = 4  # 0x20C4:02
    overflow_watermark: int = 60  # 0x20C4:03
    lead_ms: int = 200
    repair_syncs: int = 2
    loss_confirm_syncs: int = 1
    repair_margin_ms: int | None = None  # None: one SYNC period
    bus_load_limit: float = 0.7
    heartbeat_ms: int = 100  # producer time of the drives (for bus-load accounting only)
    prime_records_per_sync: int = 1
    tpdo_timeout_syncs: int = 3
    # SYNCs the core is fed ahead of the wire (the real-time runtime's lead over the cycle engine: Sync(n) is fed
    # up to `ahead_syncs` periods before SYNC n goes out); > 0: the answers overdue are judged on `SyncOnWire`
    ahead_syncs: int = 0
    # the runtime feeds every PVT record frame back as the bus carried it (`RecordOnWire`, in the bus's order with
    # the SYNCs and the answers): a batch counts in the fill from the SYNC after it was on the wire (the real-time
    # runtime; in virtual time the frames are on the wire when the core returns them)
    records_echoed: bool = False
    finish_timeout_ms: int = 2000
    start_tolerance_counts: int = 0
    demand_tolerance_counts: int = 2
    # motor quadcounts per revolution per node id: converts rpm to counts/ms so the core can predict
    # the drive's position demand at every SYNC exactly (without it, demand is checked at knots only)
    counts_per_rev: Mapping[int, int] = field(default_factory=lambda: _EMPTY_CPR)
    sync_gap_factor: float | None = None  # core-side SYNC_LOST when a SYNC comes this many periods late
    fifo_size: int = FIFO_SIZE
    readings: Mapping[int, DriveReadings] = field(default_factory=lambda: _EMPTY_READINGS)
    feedback: FeedbackSchedule | None = None
    time_stamp: bool = False
    cyclic: Mapping[int, CyclicAxis] = field(default_factory=lambda: _EMPTY_CYCLIC)
    activate_timeout_ms: int = 1000  # a cyclic drive must report ip mode active this soon after bit 4
    # per node id: the target window (counts) and in-target timeout (ms) of seed 002 (positioning.py); a node
    # without a window is in its target when its plan ends (nothing to check the actual position against)
    target_window_counts: Mapping[int, int] = field(default_factory=lambda: _EMPTY_CPR)
    in_target_timeout_ms: Mapping[int, int] = field(default_factory=lambda: _EMPTY_CPR)

    def __post_init__(self) -> None:
        def bad(name: str, value: object, why: str) -> ValueError:
            return ValueError(f"streamer setting {name} = {value!r}: {why}")

        for name in (
            "sync_period_ms",
            "bitrate",
            "lead_ms",
            "heartbeat_ms",
            "prime_records_per_sync",
            "tpdo_timeout_syncs",
            "finish_timeout_ms",
            "fifo_size",
            "activate_timeout_ms",
        ):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
                raise bad(name, v, "must be a positive integer")
        for name in (
            "underflow_watermark",
            "ahead_syncs",
            "repair_syncs",
            "loss_confirm_syncs",
            "start_tolerance_counts",
            "demand_tolerance_counts",
        ):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise bad(name, v, "must be an integer >= 0")
        if not 2 <= self.overflow_watermark <= self.fifo_size:
            raise bad("overflow_watermark", self.overflow_watermark, f"must be in [2, {self.fifo_size}]")
        if not self.underflow_watermark < self.overflow_watermark:
            raise bad(
                "underflow_watermark",
                self.underflow_watermark,
                f"must be below overflow_watermark {self.overflow_watermark}",
            )
        if self.repair_margin_ms is not None and (
            isinstance(self.repair_margin_ms, bool)
            or not isinstance(self.repair_margin_ms, int)
            or self.repair_margin_ms < 0
        ):
            raise bad("repair_margin_ms", self.repair_margin_ms, "must be None or an integer >= 0")
        if not (math.isfinite(self.bus_load_limit) and 0.0 < self.bus_load_limit <= 1.0):
            raise bad("bus_load_limit", self.bus_load_limit, "must be in (0, 1]")
        if self.sync_gap_factor is not None and not (
            math.isfinite(self.sync_gap_factor) and self.sync_gap_factor > 1.0
        ):
            raise bad("sync_gap_factor", self.sync_gap_factor, "must be None or > 1")
        cpr = dict(self.counts_per_rev)
        for node, value in cpr.items():
            if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
                raise bad(f"counts_per_rev[{node}]", value, "must be a positive integer")
        object.__setattr__(self, "counts_per_rev", MappingProxyType(cpr))
        for name, low in (("target_window_counts", 0), ("in_target_timeout_ms", 1)):
            values = dict(getattr(self, name))
            for node, value in values.items():
                if isinstance(value, bool) or not isinstance(value, int) or value < low:
                    raise bad(f"{name}[{node}]", value, f"must be an integer >= {low}")
            object.__setattr__(self, name, MappingProxyType(values))
        readings = dict(self.readings)
        for node, r in readings.items():
            if not isinstance(r, DriveReadings):
                raise bad(f"readings[{node}]", r, "must be a DriveReadings")
            unknown = [k for k in MUST_KNOW if getattr(r, k) is None]
            if unknown:
                raise bad(f"readings[{node}]", r, f"{', '.join(unknown)} of node {node} not known: the "
                          "runtime measures them at configuration (pvt probe), or set them in [axis.probed]")
        object.__setattr__(self, "readings", MappingProxyType(readings))
        cyclic = dict(self.cyclic)
        for node, c in cyclic.items():
            if not isinstance(c, CyclicAxis) or c.slot.node != node:
                raise bad(f"cyclic[{node}]", c, "must be the CyclicAxis of that node")
        object.__setattr__(self, "cyclic", MappingProxyType(cyclic))

    def reading(self, node: int) -> DriveReadings:
        """What the core assumes of `node`: its entry in `readings`, else the reference drive's readings."""
        return self.readings.get(node, REFERENCE_READINGS)

    def segment_cap_ms(self, lead_ms: int | None = None) -> int:
        """The longest PVT segment for a job whose change or stop must act within about `lead_ms` (default
        the settings' lead): the feeders keep at least `repair_syncs` + `underflow_watermark` records
        queued whatever the lead, so a change acts after that many segments; planned with segments no
        longer than this (`plan_job(max_segment_ms=...)`), that queue spans no more than the lead."""
        lead = self.lead_ms if lead_ms is None else lead_ms
        return int(max(1, min(255, lead // (self.repair_syncs + self.underflow_watermark))))

    @property
    def margin_ms(self) -> int:
        return self.sync_period_ms if self.repair_margin_ms is None else self.repair_margin_ms

    @classmethod
    def from_cell(cls, cell: Any, **overrides: Any) -> StreamerSettings:
        """Settings for a `planner.config.CellConfig` (typed Any so this module does not pull the TOML
        loader into the core's type check); keyword overrides win."""
        from bus.families import PROFILES, setpoint_slots

        slots = setpoint_slots(cell.axes)
        cyclic = {a.node_id: CyclicAxis(slots[a.node_id], PROFILES[a.profile].submode(a),
                                        PROFILES[a.profile].starts_with_bit4, PROFILES[a.profile].sync_lock_ms)
                  for a in cell.axes if a.node_id in slots}
        base = cls(
            sync_period_ms=cell.sync_period_ms,
            bitrate=cell.bus.bitrate,
            underflow_watermark=cell.drive.underflow_warning,
            overflow_watermark=cell.drive.overflow_warning,
            heartbeat_ms=cell.drive.heartbeat_ms,
            tpdo_timeout_syncs=cell.drive.tpdo_timeout_syncs,
            counts_per_rev={a.node_id: int(a.counts_per_rev) for a in cell.axes},
            target_window_counts={a.node_id: round(a.target_window_user * a.counts_per_unit) for a in cell.axes},
            in_target_timeout_ms={a.node_id: int(a.in_target_timeout_ms) for a in cell.axes},
            time_stamp=bool(getattr(cell, "time_stamp", False)),
            cyclic=cyclic,
        )
        return replace(base, **overrides) if overrides else base
