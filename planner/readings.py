"""Readings: how one drive settles the points the maxon manuals leave open, as cell configuration.

Each open point of seed 000 chapter 4 and seed 001 is named with the readings the manuals permit
(`OPEN_POINTS`; docs/drive-model.md cites the sentences). `SimDriveOptions` (`[sim]`, `[axis.sim]`) says
which reading a simulated drive implements, plus its clock drift, TPDO latency and missing objects.
`DriveReadings` (`[probed]`, `[axis.probed]`, written by `pvt probe --write`) is what the master knows of
a real drive; a missing key is unknown, measured at configuration (bus/probe.py) or tolerated
(docs/streamer.md). Pure data, validated on construction; errors name the key and the value.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

from planner.errors import CONFIG, PlanningError

# point -> the readings the manuals permit; the first one is what the simulated drive does by default
OPEN_POINTS: Mapping[str, tuple[str, ...]] = {
    # the synchronous TPDOs of a SYNC are sampled after / before that SYNC's synchronous RPDOs apply
    "tpdo_sampling": ("after_rpdo", "before_rpdo"),
    # the record being interpolated towards counts in 0x60C4:02 until its segment ends / leaves the FIFO
    # when its segment starts
    "fifo_count": ("until_segment_end", "until_segment_start"),
    # the first record after enabling ends a segment that starts at the current demand / is the path's
    # point at time zero (the demand starts there)
    "first_record": ("segment_end", "time_zero"),
    # the position demand 0x6062 is the interpolated value rounded to nearest / truncated toward zero
    "rounding": ("nearest", "toward_zero"),
    # queue underflow is checked when a segment ends with no successor / at every 1 ms tick (< 2 records)
    "underflow_check": ("segment_end", "every_tick"),
    # the interpolation clock is SYNC (each SYNC = one period of 1 ms ticks) / the drive's own 1 kHz clock
    "clock": ("sync", "own"),
}

# an XtrapulsPac's answer to controlword bit 4 before its PLL has locked (seed 003 gives only the 180 ms)
EARLY_BIT4 = ("refused", "held")

# what the master must know before a job (they change what the drive does with the stream); the others it
# tolerates by design (docs/streamer.md)
MUST_KNOW = ("fifo_count", "first_record", "clock")

# objects a drive may lack without the master losing a function it cannot do without (seed 000 4.3.6
# marks none of them mandatory; CiA 301 makes 0x1006, 0x1010-0x1013 and 0x1019 optional)
OPTIONAL_OBJECTS: Mapping[int, str] = {
    0x1006: "communication cycle period (the drive then times ip by the SYNC it receives; no SYNC monitoring)",
    0x1010: "store parameters",
    0x1011: "restore default parameters",
    0x1012: "COB-ID time stamp (no clock correction by 0x1013)",
    0x1013: "high resolution time stamp (no clock correction)",
    0x1019: "synchronous counter overflow value (position feedback every SYNC instead of staggered)",
    0x6081: "profile velocity (no ip velocity warning)",
    0x6083: "profile acceleration (no ip acceleration warning)",
    0x6085: "quick stop deceleration (the drive's own quick stop ramp)",
    0x60C2: "interpolation time period (1 ms assumed, seed 000 4.3.6.4)",
}


def _choice(section: str, key: str, value: Any) -> str:
    allowed = OPEN_POINTS[key]
    if value not in allowed:
        raise PlanningError(CONFIG, f"{section}.{key} must be one of {list(allowed)}, got {value!r}",
                            path=f"{section}.{key}")
    return str(value)


def _indices(section: str, key: str, value: Any) -> tuple[int, ...]:
    if not isinstance(value, list | tuple):
        raise PlanningError(CONFIG, f"{section}.{key} must be a list of object indices like \"0x6085\", "
                            f"got {value!r}", path=f"{section}.{key}")
    out: list[int] = []
    for item in value:
        try:
            index = int(item, 16) if isinstance(item, str) else item
        except ValueError:
            index = None
        if isinstance(index, bool) or not isinstance(index, int) or index not in OPTIONAL_OBJECTS:
            raise PlanningError(
                CONFIG,
                f"{section}.{key}: {item!r} is not an optional object (optional: "
                f"{', '.join(f'0x{i:04X}' for i in OPTIONAL_OBJECTS)})",
                path=f"{section}.{key}",
            )
        out.append(index)
    return tuple(sorted(set(out)))


def _pair(section: str, key: str, value: Any, *, infinite: bool) -> tuple[float, float] | None:
    """None, or [low, high] with low < high (+-inf allowed when `infinite`)."""
    if value is None:
        return None
    ok = isinstance(value, list | tuple) and len(value) == 2 and all(
        not isinstance(v, bool) and isinstance(v, int | float) and not math.isnan(v)
        and (infinite or math.isfinite(v)) for v in value)
    if not ok or not value[0] < value[1]:
        raise PlanningError(CONFIG, f"{section}.{key} must be [low, high] with low < high (user units"
                            f"{', -inf/inf allowed' if infinite else ''}), got {value!r}", path=f"{section}.{key}")
    return float(value[0]), float(value[1])


def _float(section: str, key: str, value: Any, low: float, high: float) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise PlanningError(CONFIG, f"{section}.{key} must be a number, got {value!r}", path=f"{section}.{key}")
    if not low <= value <= high:
        raise PlanningError(CONFIG, f"{section}.{key} must be in [{low:g}, {high:g}], got {value!r}",
                            path=f"{section}.{key}")
    return float(value)


@dataclass(frozen=True)
class SimDriveOptions:
    """What a simulated drive does on each open point (defaults: the reference drive's readings)."""

    tpdo_sampling: str = "after_rpdo"
    fifo_count: str = "until_segment_end"
    first_record: str = "segment_end"
    rounding: str = "nearest"
    underflow_check: str = "segment_end"
    clock: str = "sync"
    clock_drift_ppm: float = 0.0  # own clock only: + runs fast, - slow
    tpdo_latency_ms: float = 0.0  # synchronous TPDOs go out up to this long after the SYNC (uniform)
    # and up to this much later still (a second uniform draw per SYNC, added): answers later than the drive
    # states, some past the next SYNC (a busy bus or host between drive and master); the order is kept
    tpdo_jitter_ms: float = 0.0
    absent: tuple[int, ...] = ()  # optional objects this drive does not have
    seed: int = 0  # for the TPDO latency draws (node id is added)
    # homing inputs (docs/drive-model.md "Homing"), in the axis' user units of the drive's position
    # at power-on (the machine's frame, which homing does not move): the home switch is active on [low, high]
    # (-inf / inf: a switch active on one side of an edge; finite: a cam), the negative limit switch at and
    # below limit_switches[0], the positive one at and above limit_switches[1]; a homing search that travels
    # farther than homing_travel (0: the axis' position range) without finding its input is a homing error
    home_switch: tuple[float, ...] | None = None
    limit_switches: tuple[float, ...] | None = None
    homing_travel: float = 0.0
    # XtrapulsPac (seed 003 3.1.1.4 "At least 180 ms are necessary for the servo-drive to start the
    # synchronisation"): how long its PLL needs SYNC before it locks (at least 180 ms), and what it does with
    # controlword bit 4 before that: "refused" until bit 4 is seen low and set again, or "held" and taken
    # at the lock (the manual says neither)
    sync_lock_ms: float = 180.0
    early_bit4: str = "refused"

    def __post_init__(self) -> None:
        for key in OPEN_POINTS:
            _choice("sim", key, getattr(self, key))
        _float("sim", "sync_lock_ms", self.sync_lock_ms, 180.0, 60000.0)
        if self.early_bit4 not in EARLY_BIT4:
            raise PlanningError(CONFIG, f"sim.early_bit4 = {self.early_bit4!r}: must be one of "
                                f"{', '.join(map(repr, EARLY_BIT4))}", path="sim.early_bit4")
        for key in ("home_switch", "limit_switches"):
            object.__setattr__(self, key, _pair("sim", key, getattr(self, key), infinite=key == "home_switch"))
        _float("sim", "homing_travel", self.homing_travel, 0.0, 1e12)
        _float("sim", "clock_drift_ppm", self.clock_drift_ppm, -5000.0, 5000.0)
        _float("sim", "tpdo_latency_ms", self.tpdo_latency_ms, 0.0, 1000.0)
        _float("sim", "tpdo_jitter_ms", self.tpdo_jitter_ms, 0.0, 1000.0)
        object.__setattr__(self, "absent", _indices("sim", "absent", self.absent))
        if self.clock_drift_ppm and self.clock != "own":
            raise PlanningError(CONFIG, "sim.clock_drift_ppm needs sim.clock = \"own\" (a SYNC-locked drive has "
                                "no clock of its own)", path="sim.clock_drift_ppm")

    def describe(self) -> str:
        """The non-default options, for reports and messages ("default" when none)."""
        base = SimDriveOptions()
        parts = [f"{f.name}={getattr(self, f.name)!r}" for f in fields(self)
                 if f.name != "seed" and getattr(self, f.name) != getattr(base, f.name)]
        return ", ".join(parts) or "default"


@dataclass(frozen=True)
class DriveReadings:
    """What the master knows of one drive's readings (None: unknown, measured at configuration)."""

    tpdo_sampling: str | None = None
    fifo_count: str | None = None
    first_record: str | None = None
    rounding: str | None = None
    underflow_check: str | None = None
    clock: str | None = None
    clock_ppm_max: float = 500.0  # the stated bound of an own clock's drift (both signs)
    tpdo_latency_ms: float | None = None  # the longest a synchronous TPDO comes after its SYNC
    absent: tuple[int, ...] | None = None  # optional objects the drive lacks (None: not probed)

    def __post_init__(self) -> None:
        for key in OPEN_POINTS:
            v = getattr(self, key)
            if v is not None:
                _choice("probed", key, v)
        _float("probed", "clock_ppm_max", self.clock_ppm_max, 0.0, 5000.0)
        if self.tpdo_latency_ms is not None:
            _float("probed", "tpdo_latency_ms", self.tpdo_latency_ms, 0.0, 1000.0)
        if self.absent is not None:
            object.__setattr__(self, "absent", _indices("probed", "absent", self.absent))

    def unknown(self) -> tuple[str, ...]:
        """The open points not known yet."""
        return tuple(k for k in OPEN_POINTS if getattr(self, k) is None)

    @property
    def needs_probe(self) -> bool:
        """Unknown points the master measures at configuration (the standstill probe): what it must know,
        the rounding (the plan is encoded for it) and the TPDO latency (attributing late TPDOs)."""
        return any(getattr(self, k) is None for k in (*MUST_KNOW, "rounding")) or self.tpdo_latency_ms is None

    def merged(self, other: DriveReadings) -> DriveReadings:
        """These readings with every unknown point taken from `other` (what a probe measured)."""
        kw = {f.name: getattr(self, f.name) for f in fields(self)}
        for f in fields(self):
            if kw[f.name] is None:
                kw[f.name] = getattr(other, f.name)
        return DriveReadings(**kw)

    def to_toml(self) -> dict[str, Any]:
        """The known points as TOML-ready values (what `pvt probe --write` puts in [axis.probed])."""
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if v is None or (f.name == "clock_ppm_max" and v == 500.0):
                continue
            out[f.name] = [f"0x{i:04X}" for i in v] if f.name == "absent" else v
        return out

    def for_cyclic(self) -> DriveReadings:
        """These readings for a drive of a cyclic family (one set point per SYNC, no FIFO): the FIFO's open
        points do not apply (taken as the reference drive's, never used), and its clock is locked to SYNC
        (the XtrapulsPac's PLL 0x2006; a CSP drive follows SYNC by definition)."""
        ref = SimDriveOptions()
        return self.merged(DriveReadings(fifo_count=ref.fifo_count, first_record=ref.first_record,
                                         rounding=ref.rounding, underflow_check=ref.underflow_check,
                                         clock="sync"))

    @classmethod
    def of_sim(cls, sim: SimDriveOptions) -> DriveReadings:
        """What a perfect probe of a drive simulated with `sim` finds."""
        return cls(**{k: getattr(sim, k) for k in OPEN_POINTS}, tpdo_latency_ms=sim.tpdo_latency_ms,
                   absent=sim.absent)


def _table(raw: Any, section: str, cls: type) -> dict[str, Any]:
    if not isinstance(raw, Mapping):
        raise PlanningError(CONFIG, f"[{section}] must be a table, got {type(raw).__name__}", path=section)
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(raw) - known)
    if unknown:
        raise PlanningError(CONFIG, f"unknown key(s) {unknown} in [{section}] (known: {sorted(known)})",
                            path=f"{section}.{unknown[0]}")
    return dict(raw)


def _build(cls: type, section: str, kwargs: dict[str, Any]) -> Any:
    try:
        return cls(**kwargs)
    except PlanningError as e:
        raise PlanningError(e.code, e.message.replace("sim.", f"{section}.").replace("probed.", f"{section}."),
                            path=e.path.replace("sim", section, 1).replace("probed", section, 1)) from None
    except TypeError as e:  # a list where a number belongs and the like
        raise PlanningError(CONFIG, f"[{section}]: {e}", path=section) from None


def sim_options(cell_raw: Any, axis_raw: Any, where: str) -> SimDriveOptions:
    """`[sim]` (the cell's default) overlaid with `[axis.sim]` of one axis (`where` names it)."""
    kw = _table(cell_raw, "sim", SimDriveOptions) if cell_raw is not None else {}
    if axis_raw is not None:
        kw.update(_table(axis_raw, f"{where}.sim", SimDriveOptions))
    return _build(SimDriveOptions, f"{where}.sim" if axis_raw is not None else "sim", kw)  # type: ignore[no-any-return]


def drive_readings(cell_raw: Any, axis_raw: Any, where: str) -> DriveReadings:
    """`[probed]` overlaid with `[axis.probed]` of one axis."""
    kw = _table(cell_raw, "probed", DriveReadings) if cell_raw is not None else {}
    if axis_raw is not None:
        kw.update(_table(axis_raw, f"{where}.probed", DriveReadings))
    return _build(DriveReadings, f"{where}.probed" if axis_raw is not None else "probed", kw)  # type: ignore[no-any-return]
