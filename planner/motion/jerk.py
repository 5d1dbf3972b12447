"""Jerk-limited motions with ruckig: point-to-point moves along the straight line, and stops.

ruckig's constant-jerk phases are read from `Trajectory.profiles` and evaluated for all ms at once. A move
is ONE degree of freedom along the line, limited by the tightest axis: in phase and time-optimal on the line
(ruckig's phase synchronisation leaves the line in most multi-axis moves: docs/formats.md, "move"); its
duration is rounded up to whole ms, its phase boundaries are the `hints`; if ruckig rejects it, all axes
are time-synchronised (`straight_line` 0). Stops are time-synchronised. Never intermediate waypoints
(DESIGN.md); failures are PlanningError(INFEASIBLE) with ruckig's code.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from planner.errors import INFEASIBLE, TOO_LARGE, PlanningError
from planner.motion.reference import FloatArray, Reference, hold

CYCLE_S = 0.001


def ruckig_module() -> Any:
    """ruckig, imported when a motion first needs it (its absence is then reported where it matters)."""
    import ruckig

    return ruckig


def solve_ruckig(inp: Any, n: int) -> Any:
    """ruckig's trajectory for `inp` (n degrees of freedom, 1 ms cycle); INFEASIBLE when it finds none."""
    rk = ruckig_module()
    otg = rk.Ruckig(n, CYCLE_S)
    traj = rk.Trajectory(n)
    try:
        result = otg.calculate(inp, traj)
    except Exception as e:  # the bindings raise on invalid input
        raise PlanningError(
            INFEASIBLE,
            f"ruckig rejected the motion: {e}",
            detail={"solver": "ruckig", "return_code": type(e).__name__},
        ) from None
    if result not in (rk.Result.Working, rk.Result.Finished):
        name = getattr(result, "name", str(result))
        raise PlanningError(
            INFEASIBLE,
            f"ruckig found no trajectory ({name})",
            detail={"solver": "ruckig", "return_code": str(name)},
        )
    return traj


def ruckig_input(n: int, vlim: FloatArray, alim: FloatArray, jlim: FloatArray) -> Any:
    """The one ruckig set-up every move, stop, change and ramp of the planner uses: these limits, the axes
    time-synchronised, the duration a whole number of 1 ms cycles. No intermediate waypoints, ever (the
    community edition would call a cloud API for them)."""
    rk = ruckig_module()
    inp = rk.InputParameter(n)
    inp.max_velocity = [float(x) for x in vlim]
    inp.max_acceleration = [float(x) for x in alim]
    inp.max_jerk = [float(x) for x in jlim]
    inp.synchronization = rk.Synchronization.Time
    inp.duration_discretization = rk.DurationDiscretization.Discrete
    return inp


def solve_sampled(inp: Any, n: int, time_scale: float = 1.0) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Solve `inp` (stretched to `time_scale` times its duration, on whole ms, when > 1) and sample the
    profiles at every ms: (position, velocity, acceleration), each (n, duration_ms + 1)."""
    traj = solve_ruckig(inp, n)
    if time_scale > 1.0:
        inp.minimum_duration = float(np.ceil(traj.duration * time_scale * 1000.0 - 1e-6)) / 1000.0
        traj = solve_ruckig(inp, n)
    return sample_profiles(traj, n, max(round(traj.duration * 1000.0), 1))


def sample_profiles(traj: Any, n: int, duration_ms: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Position, velocity, acceleration of every axis at every ms 0..duration_ms (user units, per s)."""
    return sample_at(traj, n, np.arange(duration_ms + 1, dtype=np.float64) * CYCLE_S)


def phase_times(traj: Any, axis: int = 0) -> FloatArray:
    """Start times (s) of the profile phases of one axis (brake phases included)."""
    prof = traj.profiles[0][axis]
    durs = [prof.brake.t[k] for k in range(2) if prof.brake.duration > 0.0 and prof.brake.t[k] > 0.0]
    durs += [prof.t[k] for k in range(7)]
    out: FloatArray = np.cumsum(durs)
    return out


def sample_at(traj: Any, n: int, t: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Position, velocity, acceleration of every axis at the times t (s, the last one the end)."""
    pos = np.empty((n, t.size))
    vel = np.empty((n, t.size))
    acc = np.empty((n, t.size))
    profiles = traj.profiles[0]
    for i in range(n):
        prof = profiles[i]
        brake = prof.brake
        durs: list[float] = []
        p0: list[float] = []
        v0: list[float] = []
        a0: list[float] = []
        jj: list[float] = []
        if brake.duration > 0.0:
            for k in range(2):
                if brake.t[k] > 0.0:
                    durs.append(brake.t[k])
                    p0.append(brake.p[k])
                    v0.append(brake.v[k])
                    a0.append(brake.a[k])
                    jj.append(brake.j[k])
        for k in range(7):
            durs.append(prof.t[k])
            p0.append(prof.p[k])
            v0.append(prof.v[k])
            a0.append(prof.a[k])
            jj.append(prof.j[k])
        # a final "hold" phase at the end state
        durs.append(np.inf)
        p0.append(prof.p[7])
        v0.append(prof.v[7])
        a0.append(prof.a[7])
        jj.append(0.0)
        starts = np.concatenate([[0.0], np.cumsum(durs[:-1])])
        idx = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(durs) - 1)
        dt = t - starts[idx]
        pa, va, aa, ja = np.array(p0)[idx], np.array(v0)[idx], np.array(a0)[idx], np.array(jj)[idx]
        pos[i] = pa + dt * (va + dt * (aa / 2.0 + dt * ja / 6.0))
        vel[i] = va + dt * (aa + dt * ja / 2.0)
        acc[i] = aa + dt * ja
    # the end state is rest at the target: pin the last sample exactly
    pos[:, -1] = [profiles[i].p[7] for i in range(n)]
    vel[:, -1] = 0.0
    return pos, vel, acc


def line_input(length: float, v_max: float, a_max: float, j_max: float, *, v_in: float = 0.0, v_out: float = 0.0,
               a_min: float | None = None) -> Any:
    """The one ruckig set-up of a motion along a line (one degree of freedom, the path length): from 0 at
    speed `v_in` to `length` at `v_out`, at zero acceleration at both ends, under these limits (`a_min`: a
    slower deceleration). Straight-line moves (`move_reference`) and the jerk-limited path's line pieces
    (planner/motion/jerkpath.py) use it."""
    rk = ruckig_module()
    inp = rk.InputParameter(1)
    inp.current_position, inp.current_velocity, inp.current_acceleration = [0.0], [v_in], [0.0]
    inp.target_position, inp.target_velocity, inp.target_acceleration = [length], [v_out], [0.0]
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = [v_max], [a_max], [j_max]
    if a_min is not None:
        inp.min_acceleration = [-a_min]
    return inp


def from_state(position: FloatArray, velocity: FloatArray, acceleration: FloatArray, vlim: FloatArray,
               alim: FloatArray, jlim: FloatArray, *, target_position: FloatArray | None = None,
               target_velocity: FloatArray | None = None, time_scale: float = 1.0,
               ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The one ruckig set-up of a motion from a state (user units), all axes arriving together at
    acceleration 0: stops (to rest, the velocity interface), changes (to `target_position` at rest) and
    velocity ramps (to `target_velocity`). Samples at every ms of the motion played `time_scale` times slower,
    the first pinned to the given state."""
    n = position.size
    rk = ruckig_module()
    inp = ruckig_input(n, vlim, alim, jlim)
    if target_position is None:
        inp.control_interface = rk.ControlInterface.Velocity
    else:
        inp.target_position = [float(x) for x in target_position]
    inp.current_position = [float(x) for x in position]
    inp.current_velocity = [float(x) for x in velocity]
    inp.current_acceleration = [float(x) for x in acceleration]
    inp.target_velocity = [0.0] * n if target_velocity is None else [float(x) for x in target_velocity]
    inp.target_acceleration = [0.0] * n
    pos, vel, acc = solve_sampled(inp, n, time_scale)
    pos[:, 0] = position
    vel[:, 0] = velocity
    return pos, vel, acc


def counts_reference(pos: FloatArray, vel: FloatArray, acc: FloatArray, cpu: FloatArray) -> Reference:
    """ruckig's samples at every ms (user units) as a `Reference` in counts (acceleration continuous)."""
    c = cpu[:, None]
    a = acc * c / 1.0e6  # continuous (jerk-limited): the same on both sides of every tick
    return Reference(pos * c, vel * c / 1000.0, a, a, np.zeros(0, dtype=np.int64))


def line_limits(
    delta: FloatArray, vlim: FloatArray, alim: FloatArray, jlim: FloatArray
) -> tuple[float, float, float, float]:
    """Length L of the line in time-normalised units (max |delta| / v) and the limits of s in [0, L]
    (q = start + delta * s / L): per derivative, the tightest of the axes' limits over their share."""
    length = float(np.max(np.abs(delta) / vlim))
    share = np.abs(delta) / length  # dq_j / ds
    moving = share > 0.0
    with np.errstate(over="ignore"):  # an axis moving a denormal amount bounds nothing (inf); the longest bounds
        v = float(np.min(vlim[moving] / share[moving]))
        a = float(np.min(alim[moving] / share[moving]))
        j = float(np.min(jlim[moving] / share[moving]))
    return length, v, a, j


def move_reference(
    start: FloatArray,
    target: FloatArray,
    vlim: FloatArray,
    alim: FloatArray,
    jlim: FloatArray,
    cpu: FloatArray,
    *,
    time_scale: float = 1.0,
    max_duration_s: float = 900.0,
    info: dict[str, float] | None = None,
    dlim: FloatArray | None = None,
) -> Reference:
    """Rest-to-rest, jerk-limited move from `start` to `target` (user units) along the straight line.

    `dlim`: a deceleration limit per axis other than `alim` (a job's ramps, seed 002): ruckig brakes with
    its `min_acceleration` (along the line, s only grows: speeding up is positive, braking negative).

    `info` receives `straight_line` (1.0, or 0.0 when the line failed and all axes were only
    time-synchronised) and `line_optimal_s` (the continuous duration of the profile before rounding).
    """
    if np.all(start == target):
        if info is not None:
            info["straight_line"], info["line_optimal_s"] = 1.0, 0.0
        return hold(start * cpu, 1)
    delta = target - start
    length, v, a, j = line_limits(delta, vlim, alim, jlim)
    inp = line_input(length, v, a, j, a_min=None if dlim is None else line_limits(delta, vlim, dlim, jlim)[2])
    try:
        traj = solve_ruckig(inp, 1)
    except PlanningError:
        return _time_synchronised(start, target, vlim, alim, jlim, cpu, time_scale, max_duration_s, info, dlim)
    optimal = float(traj.duration)
    duration_ms = max(int(np.ceil(optimal * time_scale * 1000.0 - 1e-6)), 1)
    if duration_ms > max_duration_s * 1000.0:
        raise PlanningError(
            TOO_LARGE,
            f"the move lasts {duration_ms / 1000:.1f} s, more than the limit of {max_duration_s:g} s",
            path="target",
        )
    # played slower by `stretch` (>= 1): velocity / stretch, acceleration / stretch^2, jerk / stretch^3
    stretch = duration_ms * CYCLE_S / optimal
    t = np.arange(duration_ms + 1, dtype=np.float64) * CYCLE_S / stretch
    t[-1] = optimal
    s, sd, sdd = sample_at(traj, 1, t)
    share = delta / length
    pos = start[:, None] + share[:, None] * s
    vel = share[:, None] * sd / stretch
    acc = share[:, None] * sdd / stretch**2
    pos[:, -1] = target
    vel[:, -1] = 0.0
    hints = np.round(phase_times(traj) * stretch / CYCLE_S).astype(np.int64)
    if info is not None:
        info["straight_line"] = 1.0
        info["line_optimal_s"] = optimal
    ref = counts_reference(pos, vel, acc, cpu)
    return Reference(ref.positions, ref.velocities, ref.acc_left, ref.acc_right, ref.breaks, hints)


def _time_synchronised(
    start: FloatArray,
    target: FloatArray,
    vlim: FloatArray,
    alim: FloatArray,
    jlim: FloatArray,
    cpu: FloatArray,
    time_scale: float,
    max_duration_s: float,
    info: dict[str, float] | None,
    dlim: FloatArray | None = None,
) -> Reference:
    """The fallback: every axis its own profile, all arriving together (leaves the straight line)."""
    n = start.size
    inp = ruckig_input(n, vlim, alim, jlim)
    if dlim is not None:  # an axis moving down speeds up with negative acceleration, brakes with positive
        up = target >= start
        inp.max_acceleration = [float(x) for x in np.where(up, alim, dlim)]
        inp.min_acceleration = [float(-x) for x in np.where(up, dlim, alim)]
    inp.current_position = [float(x) for x in start]
    inp.current_velocity = [0.0] * n
    inp.current_acceleration = [0.0] * n
    inp.target_position = [float(x) for x in target]
    inp.target_velocity = [0.0] * n
    inp.target_acceleration = [0.0] * n
    traj = solve_ruckig(inp, n)
    if info is not None:
        info["straight_line"] = 0.0
        info["line_optimal_s"] = float(traj.duration)
    if time_scale > 1.0:
        inp.minimum_duration = float(np.ceil(traj.duration * time_scale * 1000.0 - 1e-6)) / 1000.0
        traj = solve_ruckig(inp, n)
    duration_ms = round(traj.duration * 1000.0)
    if duration_ms > max_duration_s * 1000.0:
        raise PlanningError(
            TOO_LARGE,
            f"the move lasts {traj.duration:.1f} s, more than the limit of {max_duration_s:g} s",
            path="target",
        )
    if duration_ms < 1:
        return hold(target * cpu, 1)
    pos, vel, acc = sample_profiles(traj, n, duration_ms)
    pos[:, -1] = target
    return counts_reference(pos, vel, acc, cpu)


def stop_reference(
    position: FloatArray,
    velocity: FloatArray,
    acceleration: FloatArray,
    vlim: FloatArray,
    alim: FloatArray,
    jlim: FloatArray,
    cpu: FloatArray,
    *,
    time_scale: float = 1.0,
) -> Reference:
    """Jerk-limited stop to rest from (position, velocity, acceleration), all axes stopping together."""
    ruckig_module()  # imported (and its absence reported) even for a stop from rest
    if np.all(velocity == 0.0) and np.all(acceleration == 0.0):
        return hold(position * cpu, 1)
    pos, vel, acc = from_state(position, velocity, acceleration, vlim, alim, jlim, time_scale=time_scale)
    return counts_reference(pos, vel, acc, cpu)
