"""The user's own timing: `timed` jobs (splined) and `pvt` jobs (raw rows), as references.

Theory of operation. `timed`: the clamped C2 cubic spline through the positions (rest to rest), each
row's time rounded to a whole ms so that every piece is one cubic a Hermite segment reproduces; rows
closer than 1 ms stretch the timing by under one ms. `pvt`: the drive's own Hermite through the
unquantised rows. The rows are the reference's `hints`. Neither is re-timed: a timing that exceeds a
limit is rejected (INFEASIBLE) with the axis, the time and the value.
"""

from __future__ import annotations

import numpy as np

from planner.errors import INFEASIBLE, PlanningError
from planner.motion.reference import FloatArray, IntArray, Reference


def timed_reference(times: FloatArray, positions: FloatArray, cpu: FloatArray) -> Reference:
    """Clamped cubic spline through (times, positions) (s, user units) sampled at every ms, in counts."""
    from scipy.interpolate import CubicSpline

    t = times - times[0]
    total_ms = t[-1] * 1000.0
    m = max(int(np.ceil(total_ms - 1e-6)), 1)
    rows = np.round(t * 1000.0)
    rows[-1] = m
    if np.all(np.diff(rows) >= 1):
        knots_s = rows / 1000.0  # every row on its own whole ms
    else:
        knots_s = t * (m / total_ms)  # rows closer than 1 ms: stretch the whole timing instead
        rows = np.zeros(0)
    spline = CubicSpline(knots_s, positions, bc_type="clamped", axis=0)
    ts = np.arange(m + 1, dtype=np.float64) / 1000.0
    c = cpu[:, None]
    pos = spline(ts).T * c
    vel = spline(ts, 1).T * c / 1000.0
    acc = spline(ts, 2).T * c / 1.0e6
    pos[:, 0] = positions[0] * cpu
    pos[:, -1] = positions[-1] * cpu
    vel[:, 0] = 0.0
    vel[:, -1] = 0.0
    acc_left = acc.copy()
    acc_right = acc.copy()
    # before the start and after the end the axes rest: the steps are on ticks 0 and M (knots)
    return Reference(pos, vel, acc_left, acc_right, np.zeros(0, dtype=np.int64), rows.astype(np.int64))


def pvt_reference(
    times: FloatArray, positions: FloatArray, velocities: FloatArray, cpu: FloatArray
) -> tuple[Reference, IntArray]:
    """The drive's Hermite through the unquantised rows (counts), and the knot times in ms."""
    knots = np.round((times - times[0]) * 1000.0).astype(np.int64)
    dt = np.diff(knots)
    c = cpu[:, None]
    p = positions.T * c  # (n, K)
    v = velocities.T * c / 1000.0  # counts/ms
    n = p.shape[0]
    m = int(knots[-1])
    seg = np.repeat(np.arange(dt.size), dt)
    off = np.arange(1, m + 1) - knots[seg]  # 1..T within each segment
    tt = dt[seg].astype(np.float64)
    s = off / tt
    s2 = s * s
    h00 = 1.0 - 3.0 * s2 + 2.0 * s2 * s
    h10 = (s - 2.0 * s2 + s2 * s) * tt
    h01 = 1.0 - h00
    h11 = (s2 * s - s2) * tt
    d00 = (6.0 * s2 - 6.0 * s) / tt
    d10 = 1.0 - 4.0 * s + 3.0 * s2
    d11 = 3.0 * s2 - 2.0 * s
    a00 = (12.0 * s - 6.0) / (tt * tt)
    a10 = (6.0 * s - 4.0) / tt
    a11 = (6.0 * s - 2.0) / tt
    pa, pb, va, vb = p[:, seg], p[:, seg + 1], v[:, seg], v[:, seg + 1]
    pos = np.empty((n, m + 1))
    vel = np.empty((n, m + 1))
    acc_left = np.empty((n, m + 1))
    pos[:, 0], vel[:, 0] = p[:, 0], v[:, 0]
    pos[:, 1:] = pa * h00 + va * h10 + pb * h01 + vb * h11
    vel[:, 1:] = pa * d00 + va * d10 - pb * d00 + vb * d11
    acc_left[:, 1:] = pa * a00 + va * a10 - pb * a00 + vb * a11
    # the acceleration at the start of every segment (s = 0), the right side of each knot
    t0 = dt.astype(np.float64)
    start_acc = (-6.0 * p[:, :-1] + 6.0 * p[:, 1:]) / t0**2 - (4.0 * v[:, :-1] + 2.0 * v[:, 1:]) / t0
    acc_right = acc_left.copy()
    acc_right[:, knots[:-1]] = start_acc
    acc_left[:, 0] = acc_right[:, 0]
    acc_right[:, -1] = acc_left[:, -1]
    return Reference(pos, vel, acc_left, acc_right, knots[1:-1], knots[1:-1]), knots


def check_user_timing(
    ref: Reference,
    vlim_counts: FloatArray,
    alim_counts: FloatArray,
    axes: tuple[str, ...],
    cpu: FloatArray,
    *,
    acc_slack: float = 0.0,
) -> None:
    """Reject (INFEASIBLE) a user timing whose velocity or acceleration exceeds a limit."""
    v = np.abs(ref.velocities) / vlim_counts[:, None]
    a = ref.acc_envelope() / alim_counts[:, None]
    for ratio, what, unit, scale in ((v, "velocity", "/s", 1000.0), (a, "acceleration", "/s^2", 1.0e6)):
        worst = ratio.max(axis=1)
        i = int(np.argmax(worst))
        if worst[i] > 1.0 + (1e-9 if what == "velocity" else acc_slack):
            tick = int(np.argmax(ratio[i]))
            value = np.abs(ref.velocities[i, tick]) if what == "velocity" else ref.acc_envelope()[i, tick]
            lim = vlim_counts[i] if what == "velocity" else alim_counts[i]
            raise PlanningError(
                INFEASIBLE,
                f"axis {axes[i]!r} needs {'an' if what[0] in 'aeiou' else 'a'} {what} of "
                f"{value * scale / cpu[i]:.4g}{unit} at "
                f"t = {tick / 1000:.3f} s, above its limit {lim * scale / cpu[i]:.4g}{unit} "
                f"(the job's own timing is kept: slow it down)",
                path="times",
                detail={"axis": axes[i], "time_s": tick / 1000.0, "what": what},
            )
