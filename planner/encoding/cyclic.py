"""One set point per SYNC: what a cyclic drive is sent, and how far its own interpolation strays from the plan.

A cyclic drive (bus/families.py) latches x_j, the plan at jP in counts (and in the XtrapulsPac's PV
sub-mode v_j, the instantaneous velocity, seed 003), at one SYNC and reaches it at the next, interpolating
by sub-mode: linear (0, CSP), the PV Hermite (-1), the P3 parabola through three set points (-2). The
deviation is measured as the EPOS encoder's (whole counts at every ms, both permitted roundings); `assess`
refuses a job beyond its tolerance, naming a sub-mode or SYNC period that would do. Wire limits: a
multiplexed step of at most 32767 counts, a multiplexed PV velocity within 32767 counts/s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from planner.config import AxisConfig
from planner.encoding import hermite
from planner.errors import AXIS_ID, ENCODING_RANGE, INFEASIBLE, PlanningError
from planner.motion.reference import FloatArray, IntArray

if TYPE_CHECKING:
    from planner.trajectory import PvtTrajectory

INTERPOLATIONS = ("linear", "pv", "p3")
STEP_16BIT = 32767  # the largest step a 16-bit set point can carry unambiguously
VELOCITY_16BIT = 32767


def interpolation_of(axis: AxisConfig) -> str | None:
    """How the axis' drive interpolates what it is sent: None for the EPOS PVT FIFO (planner.encoding.hermite),
    else "linear", "pv" or "p3" (one set point per SYNC)."""
    if axis.profile == "epos-ipm":
        return None
    if axis.profile == "cia402-csp":
        return "linear"
    return axis.ip_submode


def sixteen_bit(axis: AxisConfig) -> bool:
    """Does the axis' set point travel as 16 bits (a multiplexed group)?"""
    return axis.mux_group != 0


@dataclass(frozen=True, eq=False)
class Setpoints:
    """One axis' set points: x_j (counts) and v_j (counts/s, zero unless PV) for j = 0..N, one per period."""

    period_ms: int
    positions: IntArray
    velocities: IntArray

    @property
    def n(self) -> int:
        return int(self.positions.size) - 1

    @property
    def end_ms(self) -> int:
        """When the drive reaches the last set point (ms after the start)."""
        return self.n * self.period_ms


def sample(positions: FloatArray, velocities_per_ms: FloatArray, period_ms: int, *, pv: bool,
           start_ms: int = 0) -> Setpoints:
    """Set points of one axis from a plan sampled at every ms (counts, counts/ms): x_j = the plan at
    start_ms + j*P rounded, v_j its velocity in counts/s (PV only). The last set point is the plan's end,
    at rest, at the first multiple of P at or after it."""
    if period_ms < 1:
        raise ValueError(f"period_ms must be >= 1, got {period_ms}")
    m = int(positions.size) - 1
    n = max(1, math.ceil((m - start_ms) / period_ms)) if m > start_ms else 1
    t = np.minimum(start_ms + np.arange(n + 1, dtype=np.int64) * period_ms, m)
    x = hermite.round_counts_array(np.asarray(positions, dtype=np.float64)[t])
    if pv:
        v = np.rint(np.asarray(velocities_per_ms, dtype=np.float64)[t] * 1000.0).astype(np.int64)
        v[t >= m] = 0
    else:
        v = np.zeros(n + 1, dtype=np.int64)
    return Setpoints(period_ms, x, v)


def drive_curve(sp: Setpoints, interpolation: str) -> FloatArray:
    """The drive's interpolated demand (counts, unrounded) at every ms 0..N*P."""
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, got {interpolation!r}")
    p = sp.period_ms
    x = sp.positions.astype(np.float64)
    n = sp.n
    t = np.arange(n * p + 1, dtype=np.int64)
    k = np.minimum(t // p, n - 1) if n > 0 else np.zeros_like(t)
    s = (t - k * p) / float(p)
    x0, x1 = x[k], x[np.minimum(k + 1, n)]
    if interpolation == "linear":
        out: FloatArray = x0 + (x1 - x0) * s
    elif interpolation == "pv":
        v = sp.velocities.astype(np.float64) * (p / 1000.0)  # counts per period
        v0, v1 = v[k], v[np.minimum(k + 1, n)]
        h00 = (1 + 2 * s) * (1 - s) ** 2
        h10 = s * (1 - s) ** 2
        h01 = s * s * (3 - 2 * s)
        h11 = s * s * (s - 1)
        out = h00 * x0 + h10 * v0 + h01 * x1 + h11 * v1
    else:
        xm = x[np.maximum(k - 1, 0)]
        out = x0 + s * (x1 - xm) / 2.0 + s * s * (x1 - 2.0 * x0 + xm) / 2.0
    return out


def _extend(plan: FloatArray, length: int) -> FloatArray:
    """The plan at every ms 0..length-1 (at rest at its end after it)."""
    if plan.size >= length:
        return plan[:length]
    return np.concatenate([plan, np.full(length - plan.size, plan[-1])])


def deviation(plan: FloatArray, sp: Setpoints, interpolation: str, *, until_ms: int | None = None) -> tuple[int, float]:
    """(whole counts, unrounded) max over every ms of |drive demand - planned demand|: the whole-count one
    for the worse of the two roundings (nearest, toward zero), the unrounded one against the plan itself.
    `until_ms`: only up to then (a cancel's stop replaced the set points after it)."""
    curve = drive_curve(sp, interpolation)
    want = _extend(np.asarray(plan, dtype=np.float64), curve.size)
    if until_ms is not None:
        curve, want = curve[:until_ms + 1], want[:until_ms + 1]
    whole = max(
        int(np.abs(hermite.round_counts_array(curve) - hermite.round_counts_array(want)).max()),
        int(np.abs(hermite.truncate_counts_array(curve) - hermite.truncate_counts_array(want)).max()),
    )
    return whole, float(np.abs(curve - want).max())


def wire_problem(axis: AxisConfig, sp: Setpoints) -> tuple[str, dict[str, Any]] | None:
    """Why the set points do not fit the axis' wire format (16-bit steps / velocities), or None."""
    if not sixteen_bit(axis):
        return None
    steps = np.abs(np.diff(sp.positions))
    if steps.size and int(steps.max()) > STEP_16BIT:
        j = int(steps.argmax())
        return (f"axis {axis.name!r}: the set point moves {int(steps[j])} counts in one {sp.period_ms} ms SYNC "
                f"period (set point {j + 1}); a multiplexed 16-bit set point carries at most {STEP_16BIT}: take "
                f"the axis out of mux_group {axis.mux_group}, shorten the SYNC period or lower its velocity",
                {"axis": axis.name, "step_counts": int(steps[j]), "index": j + 1, "limit": STEP_16BIT})
    if interpolation_of(axis) == "pv":
        vmax = int(np.abs(sp.velocities).max())
        if vmax > VELOCITY_16BIT:
            j = int(np.abs(sp.velocities).argmax())
            return (f"axis {axis.name!r}: velocity {int(sp.velocities[j])} counts/s at set point {j} does not fit "
                    f"the 16-bit velocity of multiplexed group {axis.mux_group} (|v| <= {VELOCITY_16BIT}): use "
                    "sub-mode p3 in the group, or take the axis out of it",
                    {"axis": axis.name, "velocity_counts_per_s": int(sp.velocities[j]), "index": j,
                     "limit": VELOCITY_16BIT})
    return None


@dataclass(frozen=True)
class CyclicStats:
    """How one cyclic axis will follow the plan: its interpolation, period, and deviation."""

    interpolation: str
    period_ms: int
    setpoints: int
    max_deviation_counts: int
    max_deviation_from_plan_counts: float
    alternatives: dict[str, int] = field(default_factory=dict)  # other sub-mode -> its deviation

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def assess(axis: AxisConfig, plan_positions: FloatArray, plan_velocities_per_ms: FloatArray, period_ms: int,
           tolerance_counts: int, *, path: str = "") -> CyclicStats:
    """Set points and deviation of one cyclic axis; raises PlanningError when they do not fit the wire
    (ENCODING_RANGE) or the drive's interpolation strays beyond the tolerance (INFEASIBLE), saying what
    would meet it."""
    interp = interpolation_of(axis)
    if interp is None:
        raise ValueError(f"axis {axis.name!r} ({axis.profile}) is not a cyclic axis")
    pos = np.asarray(plan_positions, dtype=np.float64)
    vel = np.asarray(plan_velocities_per_ms, dtype=np.float64)
    sp = sample(pos, vel, period_ms, pv=interp == "pv")
    problem = wire_problem(axis, sp)
    if problem is not None:
        raise PlanningError(ENCODING_RANGE, problem[0], path=path, detail=problem[1])
    whole, raw = deviation(pos, sp, interp)
    alternatives: dict[str, int] = {}
    if axis.profile == "xtrapuls-ip":
        for other in INTERPOLATIONS:
            if other != interp:
                alternatives[other] = deviation(pos, sample(pos, vel, period_ms, pv=other == "pv"), other)[0]
    if whole > tolerance_counts:
        meets = sorted(m for m, d in alternatives.items() if d <= tolerance_counts)
        longest = _longest_period(pos, vel, interp, period_ms, tolerance_counts)
        ways = [f"sub-mode {m!r} ({alternatives[m]} counts)" for m in meets]
        if longest is not None:
            ways.append(f"a SYNC period of {longest} ms")
        hint = " or ".join(ways) if ways else "slower limits for this axis"
        raise PlanningError(
            INFEASIBLE,
            f"axis {axis.name!r}: its drive's own {interp} interpolation at a {period_ms} ms SYNC period "
            f"deviates {whole} counts from the plan (tolerance {tolerance_counts}); {hint} would meet it",
            path=path,
            detail={"axis": axis.name, "deviation_counts": whole, "tolerance_counts": tolerance_counts,
                    "interpolation": interp, "sync_period_ms": period_ms, "alternatives": alternatives,
                    "period_that_meets_ms": longest},
        )
    return CyclicStats(interp, period_ms, sp.n + 1, whole, raw, alternatives)


def _longest_period(pos: FloatArray, vel: FloatArray, interp: str, period_ms: int, tol: int) -> int | None:
    for p in range(period_ms - 1, 0, -1):
        if deviation(pos, sample(pos, vel, p, pv=interp == "pv"), interp)[0] <= tol:
            return p
    return None


def with_cyclic_stats(traj: PvtTrajectory, cfg: Sequence[AxisConfig], period_ms: int,
                      cell_axes: Sequence[AxisConfig] = ()) -> PvtTrajectory:
    """The trajectory with every cyclic axis' stats measured on its drive's own interpolation (`assess`:
    raises PlanningError when an axis cannot follow within the tolerance or its set points do not fit).
    `cell_axes`: every axis of the cell, to refuse a job with only part of a multiplexed group (the frame
    would carry nothing sensible for the others)."""
    if all(interpolation_of(c) is None for c in cfg):
        return traj
    in_job = {c.name for c in cfg}
    for c in cfg:
        if c.mux_group:
            left_out = [a.name for a in cell_axes if a.mux_group == c.mux_group and a.name not in in_job]
            if left_out:
                raise PlanningError(
                    AXIS_ID, f"axis {c.name!r} shares multiplexed frame (mux_group {c.mux_group}) with {left_out}: "
                    "a job must include every axis of the group", path="axes",
                    detail={"axis": c.name, "mux_group": c.mux_group, "missing": left_out})
    ref = traj.plan
    stats = list(traj.stats)
    for i, c in enumerate(cfg):
        if interpolation_of(c) is None:
            continue
        cs = assess(c, ref.positions[i], ref.velocities[i], period_ms, traj.tolerance_counts,
                    path=f"axis[{c.name}]")
        stats[i] = replace(stats[i], max_deviation_counts=cs.max_deviation_counts,
                           max_deviation_from_plan_counts=cs.max_deviation_from_plan_counts,
                           interpolation=cs.interpolation, setpoint_period_ms=period_ms,
                           interpolation_alternatives=dict(cs.alternatives))
    return replace(traj, stats=tuple(stats))
