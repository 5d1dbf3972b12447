"""Jerk-limited motions with ruckig: point-to-point moves (all axes arriving together) and stops.

Theory of operation. ruckig computes, per axis, a profile of up to 7 constant-jerk phases (plus a
brake pre-profile when the start state is outside the limits). We read those phases straight from
`Trajectory.profiles` and evaluate them for all ms at once (vectorised), instead of calling
`at_time` per sample. Durations are discretised to whole ms (`DurationDiscretization.Discrete` with a
1 ms cycle), so the motion ends exactly on a tick; all axes are time-synchronised
(`Synchronization.Time`): they start and stop together. A jerk-limited profile has continuous
acceleration, so the reference has no acceleration steps (its jerk switches fall between ticks and
cost the encoder only short segments around them).

Never intermediate waypoints: ruckig's community edition would call a remote API for them
(DESIGN.md, network rules). Failures (ruckig's Result codes or exceptions) become
PlanningError(INFEASIBLE) carrying the return code.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from planner.errors import INFEASIBLE, TOO_LARGE, PlanningError
from planner.reference import FloatArray, Reference, hold

CYCLE_S = 0.001


def _ruckig() -> Any:
    import ruckig

    return ruckig


def _solve(inp: Any, n: int) -> Any:
    rk = _ruckig()
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


def _input(n: int, vlim: FloatArray, alim: FloatArray, jlim: FloatArray) -> Any:
    rk = _ruckig()
    inp = rk.InputParameter(n)
    inp.max_velocity = [float(x) for x in vlim]
    inp.max_acceleration = [float(x) for x in alim]
    inp.max_jerk = [float(x) for x in jlim]
    inp.synchronization = rk.Synchronization.Time
    inp.duration_discretization = rk.DurationDiscretization.Discrete
    return inp


def sample_profiles(traj: Any, n: int, duration_ms: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Position, velocity, acceleration of every axis at every ms 0..duration_ms (user units, per s)."""
    t = np.arange(duration_ms + 1, dtype=np.float64) * CYCLE_S
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


def _reference(pos: FloatArray, vel: FloatArray, acc: FloatArray, cpu: FloatArray) -> Reference:
    c = cpu[:, None]
    a = acc * c / 1.0e6  # continuous (jerk-limited): the same on both sides of every tick
    return Reference(pos * c, vel * c / 1000.0, a, a, np.zeros(0, dtype=np.int64))


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
) -> Reference:
    """Rest-to-rest, time-synchronised, jerk-limited move from `start` to `target` (user units)."""
    n = start.size
    if np.all(start == target):
        return hold(start * cpu, 1)
    inp = _input(n, vlim, alim, jlim)
    inp.current_position = [float(x) for x in start]
    inp.current_velocity = [0.0] * n
    inp.current_acceleration = [0.0] * n
    inp.target_position = [float(x) for x in target]
    inp.target_velocity = [0.0] * n
    inp.target_acceleration = [0.0] * n
    traj = _solve(inp, n)
    if time_scale > 1.0:
        inp.minimum_duration = float(np.ceil(traj.duration * time_scale * 1000.0 - 1e-6)) / 1000.0
        traj = _solve(inp, n)
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
    return _reference(pos, vel, acc, cpu)


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
    rk = _ruckig()
    n = position.size
    if np.all(velocity == 0.0) and np.all(acceleration == 0.0):
        return hold(position * cpu, 1)
    inp = _input(n, vlim, alim, jlim)
    inp.control_interface = rk.ControlInterface.Velocity
    inp.current_position = [float(x) for x in position]
    inp.current_velocity = [float(x) for x in velocity]
    inp.current_acceleration = [float(x) for x in acceleration]
    inp.target_velocity = [0.0] * n
    inp.target_acceleration = [0.0] * n
    traj = _solve(inp, n)
    if time_scale > 1.0:
        inp.minimum_duration = float(np.ceil(traj.duration * time_scale * 1000.0 - 1e-6)) / 1000.0
        traj = _solve(inp, n)
    duration_ms = max(round(traj.duration * 1000.0), 1)
    pos, vel, acc = sample_profiles(traj, n, duration_ms)
    pos[:, 0] = position
    vel[:, 0] = velocity
    return _reference(pos, vel, acc, cpu)
