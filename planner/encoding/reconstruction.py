"""The drive's reconstruction of PVT knots: what the encoder hands the drive, and what the drive makes of it.

Theory of operation. `Knots` are shared ms times and per-axis whole-count positions and whole-rpm
velocities, for axes described by `AxisScales` (conversions and limits in counts and ms). The drive
interpolates each segment with seed 000 4.2.3's cubic every ms and rounds (to nearest, or toward zero:
`drive_round`); `reconstruct` recomputes that (compiled), `planned_demand` is the plan rounded the same
way. The contract and the acceleration budget (`segment_envelope`, `acceleration_excess`) are stated
against these; the encoder, the uniform baseline and the tests all judge an encoding through them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from planner.encoding import hermite, quantise
from planner.motion.reference import FloatArray, IntArray, Reference


@dataclass(frozen=True, eq=False)
class AxisScales:
    """Per-axis conversions and limits in drive units (arrays of n_axes)."""

    counts_per_ms_per_rpm: FloatArray  # counts_per_rev / 60000
    velocity_limit: FloatArray  # counts/ms, the job's limit for this axis (scale applied)
    acceleration_limit: FloatArray  # counts/ms^2, the job's limit for this axis (scale applied)
    acceleration_axis: FloatArray  # counts/ms^2, the axis limit the 5 % excess budget refers to
    drive_velocity: FloatArray  # 0x607F in counts/ms
    drive_acceleration: FloatArray  # 0x60C5 in counts/ms^2
    # axes whose drive truncates its position demand toward zero (the other reading seed 000 permits,
    # known from `pvt probe`): their deviation is checked as that drive rounds; None: all to nearest
    toward_zero: NDArray[np.bool_] | None = None
    # the longest PVT segment this plan may use (ms; None: 255): a job with a short lead bounds it, so
    # that what the feeders keep queued (a few segments) spans about the lead and a change acts sooner
    max_segment_ms: int | None = None

    def subset(self, axes: IntArray) -> AxisScales:
        """These scales for some of the axes only (rows `axes`)."""
        return AxisScales(
            self.counts_per_ms_per_rpm[axes],
            self.velocity_limit[axes],
            self.acceleration_limit[axes],
            self.acceleration_axis[axes],
            self.drive_velocity[axes],
            self.drive_acceleration[axes],
            None if self.toward_zero is None else self.toward_zero[axes],
            self.max_segment_ms,
        )


@dataclass(frozen=True, eq=False)
class Knots:
    """The encoder's output: shared knot times and the quantised values of every axis."""

    times_ms: IntArray  # (N+1,), times_ms[0] == 0
    positions: IntArray  # (n_axes, N+1) counts
    velocities_rpm: IntArray  # (n_axes, N+1) rpm


@dataclass(frozen=True, eq=False)
class Reconstruction:
    """The drive's reconstruction at every ms (what the drive computes from the knots)."""

    demand: IntArray  # (n_axes, M+1) rounded position demand, counts
    position: FloatArray  # (n_axes, M+1) unrounded, counts
    velocity: FloatArray  # (n_axes, M+1) counts/ms
    acc_start: FloatArray  # (n_axes, N) acceleration at the start of each segment, counts/ms^2
    acc_end: FloatArray  # (n_axes, N) acceleration at the end of each segment


def drive_round(x: FloatArray, toward_zero: NDArray[np.bool_] | None) -> IntArray:
    """Positions (axis first) rounded to whole counts as each axis' drive rounds its demand: to nearest,
    or toward zero on the axes flagged in `toward_zero`."""
    if toward_zero is None or not toward_zero.any():
        return hermite.round_counts_array(x)
    tz = toward_zero.reshape((-1,) + (1,) * (x.ndim - 1))
    out: IntArray = np.where(tz, hermite.truncate_counts_array(x), hermite.round_counts_array(x))
    return out


def planned_demand(ref: Reference, toward_zero: NDArray[np.bool_] | None = None) -> IntArray:
    """The plan rounded to whole counts as the drive rounds: what a perfect encoding would command
    (read-only: kept on `ref`, the encoding and the statistics ask for it several times)."""
    key = None if toward_zero is None or not toward_zero.any() else toward_zero.tobytes()
    memo: dict[bytes | None, IntArray] = ref.__dict__.setdefault("_planned_demand", {})
    if key not in memo:
        demand = drive_round(ref.positions, toward_zero)
        demand.setflags(write=False)
        memo[key] = demand
    return memo[key]


# ----------------------------------------------------------------------------------------------------
# reconstruction (planner.encoding.hermite's interpolation and rounding, compiled: quantise.reconstruct)


def toward_zero_flags(scales: AxisScales) -> NDArray[np.bool_]:
    """Which axes' drives truncate their demand, one flag per axis (as the compiled kernels take it)."""
    n = scales.counts_per_ms_per_rpm.size
    if scales.toward_zero is None:
        return np.zeros(n, dtype=bool)
    return np.ascontiguousarray(scales.toward_zero, dtype=bool)


def reconstruct(knots: Knots, scales: AxisScales) -> Reconstruction:
    """The drive's position demand at every ms of every axis, and the segments' end accelerations."""
    demand, pos, vel, acc_s, acc_e = quantise.reconstruct(
        np.ascontiguousarray(knots.positions, dtype=np.float64),
        np.ascontiguousarray(knots.velocities_rpm, dtype=np.float64),
        np.ascontiguousarray(knots.times_ms, dtype=np.int64),
        np.ascontiguousarray(scales.counts_per_ms_per_rpm, dtype=np.float64),
        toward_zero_flags(scales),
    )
    return Reconstruction(demand, pos, vel, acc_s, acc_e)


def segment_envelope(ref: Reference, times: IntArray) -> FloatArray:
    """Planned |acceleration| peak over each segment (both end ticks included), (n_axes, N)."""
    if times.size < 2:
        return np.zeros((ref.n_axes, 0))
    return quantise.segment_envelope(ref.acc_left, ref.acc_right, np.ascontiguousarray(times, dtype=np.int64))


def acceleration_excess(ref: Reference, knots: Knots, rec: Reconstruction) -> FloatArray:
    """Per segment and axis: peak reconstruction |acceleration| minus the plan's peak over the segment.

    The drive's acceleration is linear inside a segment, so its peak is at one of the ends. Counts/ms^2,
    (n_axes, N); negative where the reconstruction stays below the plan.
    """
    peak = np.maximum(np.abs(rec.acc_start), np.abs(rec.acc_end))
    out: FloatArray = peak - segment_envelope(ref, knots.times_ms)
    return out
