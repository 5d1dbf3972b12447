"""`PvtTrajectory`: the encoded motion of all axes on one shared grid, plus what it was planned from.

Theory of operation. The planner's product and the streamer's input: the knots exactly as they go on
the wire (int32 counts, int24 rpm, one list of 1..255 ms segment times), the `Reference` they encode,
and per-axis statistics measured on the drive's reconstruction. Everything else is derived (records,
the drive's demand at every ms, the state at a knot for the stop planner). Deviation is in whole counts,
drive demand minus planned demand, within `tolerance_counts`. An open-ended trajectory (velocity move)
holds its `CruiseState` in `open_end` and has no end record: `travel.extend_velocity` continues it.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from planner.config import AxisConfig, CellConfig
from planner.encoding import hermite
from planner.encoding.record import PvtRecord, pack
from planner.errors import ENCODING_RANGE, PlanningError
from planner.limits import AxisLimits
from planner.motion.reference import FloatArray, IntArray, Reference

DEFAULT_CHUNK_MS = 2000  # cruise per chunk of a velocity move (plan and each extension, planner/motion/travel.py)
RPM_MS = 60000  # counts per ms = rpm * counts_per_rev / 60000

CSV_COLUMNS = ("axis", "node_id", "index", "time_s", "dt_ms", "position_counts", "velocity_rpm")


@dataclass(frozen=True)
class AxisStats:
    """Measured on the drive's reconstruction of one axis (user units unless the name says otherwise)."""

    name: str
    node_id: int
    max_deviation_counts: int  # |drive demand - planned demand|, whole counts, over every ms
    max_deviation_from_plan_counts: float  # |drive demand - unrounded plan|
    peak_velocity: float  # reconstruction, user units/s
    peak_velocity_rpm: float
    velocity_limit: float  # the job's limit (scales applied), user units/s
    drive_velocity_limit_rpm: float  # 0x607F
    planned_peak_acceleration: float  # the plan, user units/s^2
    peak_acceleration: float  # reconstruction (segment ends), user units/s^2
    acceleration_limit: float  # the job's limit (scales applied)
    axis_acceleration_limit: float  # the limit the excess budget refers to (before scales)
    drive_acceleration_limit: float  # 0x60C5, user units/s^2
    acceleration_excess: float  # max over segments of reconstruction peak - planned peak, user units/s^2
    acceleration_excess_share: float  # acceleration_excess / axis_acceleration_limit
    # how the axis' drive interpolates what it is sent (planner/encoding/cyclic.py): "pvt" (EPOS FIFO, the
    # deviations above are the encoder's), or "linear" / "pv" / "p3" (one set point per SYNC period
    # `setpoint_period_ms`; the deviations above are then the drive's interpolation against the plan, and
    # `interpolation_alternatives` the deviation the other sub-modes would make)
    interpolation: str = "pvt"
    setpoint_period_ms: int = 0
    # jerk (user units/s^3): the axis' limit, the plan's peak (its change of acceleration over every ms),
    # the reconstruction's peak inside its segments (a cubic's constant jerk), and the largest step of the
    # reconstruction's acceleration at a knot (user units/s^2; over the 1 ms tick: step * 1000 /s^3)
    jerk_limit: float = 0.0
    planned_peak_jerk: float = 0.0
    peak_jerk: float = 0.0
    knot_acceleration_step: float = 0.0
    interpolation_alternatives: dict[str, int] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        out = dict(self.__dict__)
        out["interpolation_alternatives"] = dict(self.interpolation_alternatives)
        return out


def _ro(a: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    a = np.array(a, copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class PvtTrajectory:
    """Knots of every axis on one shared grid (see the module docstring)."""

    kind: str
    axis_names: tuple[str, ...]
    node_ids: tuple[int, ...]
    dt_ms: IntArray  # (N,) shared segment times, each 1..255
    positions: IntArray  # (n_axes, N+1) counts, knot 0 = start
    velocities: IntArray  # (n_axes, N+1) rpm, last knot 0
    counts_per_unit: FloatArray  # (n_axes,)
    counts_per_rev: FloatArray  # (n_axes,)
    tolerance_counts: int
    plan: Reference  # the planned motion at every ms, counts
    stats: tuple[AxisStats, ...]
    info: dict[str, float] = field(default_factory=dict)  # e.g. optimal_s (toppra), planning details
    open_end: CruiseState | None = None  # set: the motion goes on (velocity move), see the module docstring

    def __post_init__(self) -> None:
        n = len(self.axis_names)
        dt = np.asarray(self.dt_ms, dtype=np.int64)
        pos = np.asarray(self.positions, dtype=np.int64)
        vel = np.asarray(self.velocities, dtype=np.int64)
        if dt.ndim != 1 or dt.size < 1 or dt.min() < 1 or dt.max() > 255:
            raise PlanningError(
                ENCODING_RANGE, "segment times must be 1..255 ms (at least one segment)", path="dt_ms"
            )
        if pos.shape != (n, dt.size + 1) or vel.shape != pos.shape:
            raise ValueError(
                f"positions/velocities must be ({n}, {dt.size + 1}), got {pos.shape}/{vel.shape}"
            )
        if len(self.node_ids) != n or self.plan.n_axes != n or self.plan.duration_ms != int(dt.sum()):
            raise ValueError("node_ids, plan and knots disagree on axes or duration")
        if self.open_end is None and np.any(vel[:, -1] != 0):
            raise ValueError("a trajectory ends at rest (last knot velocity 0) unless it is open-ended")
        for name, a in (
            ("dt_ms", dt),
            ("positions", pos),
            ("velocities", vel),
            ("counts_per_unit", np.asarray(self.counts_per_unit, dtype=np.float64)),
            ("counts_per_rev", np.asarray(self.counts_per_rev, dtype=np.float64)),
        ):
            object.__setattr__(self, name, _ro(a))

    # -- shape and time ------------------------------------------------------------------------------

    @property
    def n_axes(self) -> int:
        return len(self.axis_names)

    @property
    def open_ended(self) -> bool:
        """The motion goes on after the last knot (a velocity move's chunk): see the module docstring."""
        return self.open_end is not None

    @property
    def n_segments(self) -> int:
        return int(self.dt_ms.size)

    @property
    def n_points(self) -> int:
        """PVT points per axis, including the start point (knots)."""
        return int(self.dt_ms.size) + 1

    @property
    def knot_times_ms(self) -> IntArray:
        out: IntArray = np.concatenate([[0], np.cumsum(self.dt_ms)]).astype(np.int64)
        return out

    @property
    def knot_times_s(self) -> FloatArray:
        out: FloatArray = self.knot_times_ms / 1000.0
        return out

    @property
    def duration_ms(self) -> int:
        return int(self.dt_ms.sum())

    @property
    def duration_s(self) -> float:
        return self.duration_ms / 1000.0

    def axis_index(self, name: str) -> int:
        return self.axis_names.index(name)

    # -- wire ----------------------------------------------------------------------------------------

    def records(self, axis_index: int) -> list[PvtRecord]:
        """(p_k, v_k, dt_k) for k = 1..N, then the end record (p_N, 0, 0), which an open-ended trajectory
        leaves out (its extension's records follow)."""
        p = self.positions[axis_index].tolist()
        v = self.velocities[axis_index].tolist()
        dt = self.dt_ms.tolist()
        out = [PvtRecord(p[k], v[k], dt[k - 1]) for k in range(1, len(p))]
        if self.open_end is None:
            out.append(PvtRecord(p[-1], 0, 0))
        return out

    def packed(self, axis_index: int) -> list[bytes]:
        """The 8-byte 0x20C1 records of one axis (raises EncodingRangeError if one does not fit)."""
        return [pack(r) for r in self.records(axis_index)]

    # -- plan and reconstruction ---------------------------------------------------------------------

    def _scale_ms(self) -> FloatArray:
        out: FloatArray = self.counts_per_rev / 60000.0
        return out

    def reference(self, t_s: Sequence[float] | FloatArray | float) -> FloatArray:
        """Planned positions (counts, unrounded) of all axes at times `t_s` (s): (n_axes, len(t))."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64)) * 1000.0
        return self.plan.at(t)

    def reconstruction(self, t_s: Sequence[float] | FloatArray | float) -> FloatArray:
        """The drive's interpolated positions (counts, unrounded) at times `t_s` (s): (n_axes, len(t))."""
        t = np.clip(np.atleast_1d(np.asarray(t_s, dtype=np.float64)) * 1000.0, 0.0, float(self.duration_ms))
        kt = self.knot_times_ms
        seg = np.clip(np.searchsorted(kt, t, side="left") - 1, 0, self.n_segments - 1)
        tt = self.dt_ms[seg].astype(np.float64)
        tau = t - kt[seg + 1]  # in [-T, 0], measured from the segment end as in seed 000 4.2.3
        out = np.empty((self.n_axes, t.size))
        conv = self._scale_ms()
        for i in range(self.n_axes):
            p = self.positions[i].astype(np.float64)
            v = self.velocities[i].astype(np.float64) * conv[i]
            dp = p[seg + 1] - p[seg]
            a = (-2.0 * dp + tt * (v[seg + 1] + v[seg])) / tt**3
            b = (-3.0 * dp + tt * (2.0 * v[seg + 1] + v[seg])) / tt**2
            out[i] = ((a * tau + b) * tau + v[seg + 1]) * tau + p[seg + 1]
        return out

    def drive_profile(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Unrounded position (counts), velocity (counts/ms), acceleration (counts/ms^2) at every ms."""
        n, m = self.n_axes, self.duration_ms
        pos, vel, acc = np.empty((n, m + 1)), np.empty((n, m + 1)), np.empty((n, m + 1))
        conv = self._scale_ms()
        for i in range(n):
            pos[i], vel[i], acc[i] = hermite.reconstruct(
                self.positions[i].astype(np.float64),
                self.velocities[i].astype(np.float64) * conv[i],
                self.dt_ms,
            )
        return pos, vel, acc

    def demand(self, toward_zero: bool = False) -> IntArray:
        """The drive's position demand (0x6062) at every ms 0..M: whole counts, (n_axes, M+1). The drive
        rounds to nearest, or (`toward_zero`, the other reading the manuals permit) truncates."""
        pos = self.drive_profile()[0]
        return hermite.truncate_counts_array(pos) if toward_zero else hermite.round_counts_array(pos)

    def planned_demand(self, toward_zero: bool = False) -> IntArray:
        """The plan rounded to whole counts as the drive rounds, at every ms: (n_axes, M+1)."""
        pos = np.asarray(self.plan.positions)
        return hermite.truncate_counts_array(pos) if toward_zero else hermite.round_counts_array(pos)

    def deviation(self, toward_zero: bool = False) -> IntArray:
        """demand() - planned_demand() for one rounding reading: whole counts at every ms."""
        out: IntArray = self.demand(toward_zero) - self.planned_demand(toward_zero)
        return out

    def knot_state(self, k: int) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(positions, velocities, accelerations) of all axes at knot k, user units (/s, /s^2).

        Position and velocity are the knot's wire values; the acceleration is the drive's Hermite
        acceleration at the end of segment k (0 at knot 0). Feed this to planner.motion.stop.plan_stop to stop
        from the end of what is queued.
        """
        if not 0 <= k <= self.n_segments:
            raise IndexError(f"knot {k} outside 0..{self.n_segments}")
        cpu = self.counts_per_unit
        conv = self._scale_ms()
        pos = self.positions[:, k] / cpu
        vel = self.velocities[:, k] * conv * 1000.0 / cpu
        if k == 0:
            acc = np.zeros(self.n_axes)
        else:
            t = float(self.dt_ms[k - 1])
            p0, p1 = self.positions[:, k - 1].astype(np.float64), self.positions[:, k].astype(np.float64)
            v0, v1 = self.velocities[:, k - 1] * conv, self.velocities[:, k] * conv
            acc = (-6.0 * (p1 - p0) + 4.0 * t * v1 + 2.0 * t * v0) / (t * t) * 1.0e6 / cpu
        return pos, vel, acc

    # -- reports -------------------------------------------------------------------------------------

    def summary(self) -> dict[str, Any]:
        """A JSON-ready summary (what `pvt plan --json` prints)."""
        return {
            "kind": self.kind,
            "duration_s": self.duration_s,
            "points": self.n_points,
            "segments": self.n_segments,
            "points_per_second": self.n_points / self.duration_s if self.duration_s > 0 else 0.0,
            "tolerance_counts": self.tolerance_counts,
            "segment_ms": {
                "min": int(self.dt_ms.min()),
                "max": int(self.dt_ms.max()),
                "mean": float(self.dt_ms.mean()),
            },
            "info": dict(self.info),
            "open_ended": self.open_ended,
            "axes": [s.to_dict() for s in self.stats],
        }

    def csv_rows(self) -> list[tuple[str, int, int, float, int, int, int]]:
        """axis,node_id,index,time_s,dt_ms,position_counts,velocity_rpm; index 0 = start (dt_ms 0)."""
        rows: list[tuple[str, int, int, float, int, int, int]] = []
        t = self.knot_times_s.tolist()
        dt = [0, *self.dt_ms.tolist()]
        for i, (name, node) in enumerate(zip(self.axis_names, self.node_ids, strict=True)):
            p = self.positions[i].tolist()
            v = self.velocities[i].tolist()
            rows.extend((name, node, k, t[k], dt[k], p[k], v[k]) for k in range(len(p)))
        return rows

    def to_csv(self) -> str:
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(CSV_COLUMNS)
        for r in self.csv_rows():
            w.writerow((r[0], r[1], r[2], f"{r[3]:.3f}", r[4], r[5], r[6]))
        return buf.getvalue()


@dataclass(frozen=True)
class CruiseState:
    """Where an open-ended velocity move stands at the end of a chunk, and what extending it needs
    (planner/motion/travel.py plans and extends the chunks).

    Cruise knots lie at `position_at(e)` for e ms since the anchor, exactly (integers): see the module
    docstring. `elapsed_ms` is the cruise time at the end of the trajectory that carries this state.
    """

    cell: CellConfig
    axes: tuple[str, ...]
    anchor_counts: tuple[int, ...]
    velocity_rpm: tuple[int, ...]
    elapsed_ms: int
    deceleration: tuple[float, ...]  # user units/s^2: the limit stop's braking
    jerk: tuple[float, ...]  # user units/s^3
    velocity_limit: tuple[float, ...]  # the job's limits (user units), for the encoding checks
    acceleration_limit: tuple[float, ...]
    acceleration_axis: tuple[float, ...]
    tolerance_counts: int = 1
    chunk_ms: int = DEFAULT_CHUNK_MS

    @property
    def cfg(self) -> tuple[AxisConfig, ...]:
        return tuple(self.cell.axis(a) for a in self.axes)

    def position_at(self, elapsed_ms: int) -> list[int]:
        """Cruise position (counts) of every axis `elapsed_ms` after the anchor, rounded half up, exactly."""
        out = []
        for a, v, c in zip(self.anchor_counts, self.velocity_rpm, self.cfg, strict=True):
            q = v * c.counts_per_rev * int(elapsed_ms)
            out.append(a + (2 * q + RPM_MS) // (2 * RPM_MS))
        return out

    def velocity_counts_per_ms(self) -> FloatArray:
        return np.array([v * c.counts_per_rev / RPM_MS for v, c in zip(self.velocity_rpm, self.cfg, strict=True)])

    def limits(self) -> AxisLimits:
        return AxisLimits.of(np.array(self.velocity_limit), np.array(self.acceleration_limit), np.array(self.jerk),
                             acceleration_axis=np.array(self.acceleration_axis))
