"""plan_stop: a jerk-limited stop of all axes from any state, encoded like every other motion.

The streamer cancels by appending a stop from the state at the end of its queue (`PvtTrajectory.knot_state`);
ruckig's velocity interface brings every axis to rest, time-synchronised (the axes stop together). Knot 0
is exactly the given wire state. A stop is never refused for the software limits (0x607D still holds on the
drive). `plan_change` goes from the same state to a new target at rest (POSITION_LIMIT, INFEASIBLE;
`overrun_axes`: seed 002's TARGET_OVERRUN). `plan_emergency_stop` uses each axis' `emergency_deceleration`
reached within EMERGENCY_RISE_MS, not a step (docs/formats.md says why 20 ms), doubled on axes too coarse
to encode it (`info["emergency_rise_ms"]`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from planner.config import AxisConfig, CellConfig
from planner.errors import AXIS_COUNT, INFEASIBLE, NONFINITE, POSITION_LIMIT, PlanningError
from planner.limits import AxisLimits
from planner.motion.reference import FloatArray, Reference
from planner.pipeline import axis_configs, axis_scales, build_trajectory, encode_with_retries
from planner.trajectory import PvtTrajectory

EMERGENCY_RISE_MS = 20.0  # ms from zero to the full emergency deceleration (sets the emergency jerk)
EMERGENCY_RISE_STEP = 2.0  # the next, gentler rise time when the encoder cannot reproduce a steeper one


def plan_stop(
    cell: CellConfig,
    axis_names: Sequence[str],
    positions: Sequence[float],
    velocities: Sequence[float],
    accelerations: Sequence[float],
    *,
    tolerance_counts: int = 1,
) -> PvtTrajectory:
    """Stop every axis in `axis_names` from (position, velocity, acceleration) in user units (/s, /s^2)."""
    cfg = axis_configs(tuple(axis_names), cell)
    return _stop(
        cell, axis_names, positions, velocities, accelerations, np.array([c.acceleration for c in cfg]),
        np.array([c.jerk for c in cfg]), tolerance_counts=tolerance_counts, kind="stop",
    )


def plan_emergency_stop(
    cell: CellConfig,
    axis_names: Sequence[str],
    positions: Sequence[float],
    velocities: Sequence[float],
    accelerations: Sequence[float],
    *,
    tolerance_counts: int = 1,
) -> PvtTrajectory:
    """plan_stop at each axis' emergency deceleration (`AxisConfig.emergency_stop_deceleration`) and the
    steepest jerk the encoder reproduces (module docstring): seed 002's emergency stop, "the motor is
    stopped within this time"."""
    cfg = axis_configs(tuple(axis_names), cell)
    decel = np.array([c.emergency_stop_deceleration for c in cfg])
    floor = np.array([c.jerk for c in cfg])
    rise = EMERGENCY_RISE_MS
    while True:
        # the steepest jerk the encoder reproduces: a coarse axis (few counts per unit, a large rpm step)
        # needs a gentler one; never gentler than the axis' own jerk limit
        jerk = np.maximum(floor, decel / (rise / 1000.0))
        try:
            traj = _stop(cell, axis_names, positions, velocities, accelerations, decel, jerk,
                         tolerance_counts=tolerance_counts, kind="emergency_stop")
        except PlanningError as e:
            if e.code != INFEASIBLE or np.all(jerk <= floor):
                raise
            rise *= EMERGENCY_RISE_STEP
            continue
        traj.info["emergency_rise_ms"] = rise
        return traj


def _stop(
    cell: CellConfig,
    axis_names: Sequence[str],
    positions: Sequence[float],
    velocities: Sequence[float],
    accelerations: Sequence[float],
    deceleration: FloatArray,
    jerk: FloatArray,
    *,
    tolerance_counts: int,
    kind: str,
) -> PvtTrajectory:
    names = tuple(axis_names)
    cfg = axis_configs(names, cell)
    n = len(cfg)
    p = _vec(positions, "positions", n)
    v = _vec(velocities, "velocities", n)
    a = _vec(accelerations, "accelerations", n)
    cpu = np.array([c.counts_per_unit for c in cfg])
    # a stop that starts while accelerating at full speed briefly goes faster than the axis limit
    # (it must first bring the acceleration to zero): the hard bound it is checked against is 0x607F
    limits = AxisLimits.of(np.array([c.max_profile_velocity for c in cfg]), deceleration, jerk,
                           velocity_axis=np.array([c.velocity for c in cfg]))
    scales = axis_scales(cfg, limits)
    conv = scales.counts_per_ms_per_rpm
    p0 = np.round(p * cpu).astype(np.int64)
    v0 = np.round(v * cpu / 1000.0 / conv).astype(np.int64)
    # plan from the wire values exactly
    p_exact = p0 / cpu
    v_exact = v0 * conv * 1000.0 / cpu

    info: dict[str, float] = {}

    def build(f: float, smooth: bool = False) -> Reference:
        from planner.motion.jerk import stop_reference

        vlim = np.maximum(limits.velocity_axis, np.abs(v_exact))
        alim = np.maximum(limits.acceleration, np.abs(a))
        return stop_reference(p_exact, v_exact, a, vlim, alim, limits.jerk, cpu, time_scale=f)

    ref, knots, rec = encode_with_retries(
        build,
        scales,
        int(tolerance_counts),
        retime=True,
        axes=names,
        start_positions=p0,
        start_velocities_rpm=v0,
        info_out=info,
    )
    return build_trajectory(kind, names, cfg, ref, knots, rec, scales, int(tolerance_counts), limits, info)


def plan_stop_from_wire(
    cell: CellConfig,
    axis_names: Sequence[str],
    positions_counts: Sequence[int],
    velocities_rpm: Sequence[int],
    accelerations_counts_per_ms2: Sequence[float] | None = None,
    *,
    tolerance_counts: int = 1,
) -> PvtTrajectory:
    """plan_stop with the state in drive units (counts, rpm, counts/ms^2), as the streamer holds it."""
    p, v, a = _from_wire(cell, axis_names, positions_counts, velocities_rpm, accelerations_counts_per_ms2)
    return plan_stop(cell, axis_names, p, v, a, tolerance_counts=tolerance_counts)


def plan_emergency_stop_from_wire(
    cell: CellConfig,
    axis_names: Sequence[str],
    positions_counts: Sequence[int],
    velocities_rpm: Sequence[int],
    accelerations_counts_per_ms2: Sequence[float] | None = None,
    *,
    tolerance_counts: int = 1,
) -> PvtTrajectory:
    """plan_emergency_stop with the state in drive units (counts, rpm, counts/ms^2), as plan_stop_from_wire."""
    p, v, a = _from_wire(cell, axis_names, positions_counts, velocities_rpm, accelerations_counts_per_ms2)
    return plan_emergency_stop(cell, axis_names, p, v, a, tolerance_counts=tolerance_counts)


@dataclass(frozen=True)
class ChangePlan:
    """A planned change: the trajectory from the given state to the new target (knot 0 is that state to the
    count and the rpm), and the axes that brake past their new target and come back (TARGET_OVERRUN)."""

    trajectory: PvtTrajectory
    overrun_axes: tuple[str, ...]
    overrun_counts: tuple[int, ...]  # per overrun axis: how far past its target it goes (counts)


def plan_change(
    cell: CellConfig,
    axis_names: Sequence[str],
    positions: Sequence[float],
    velocities: Sequence[float],
    accelerations: Sequence[float],
    target: Sequence[float],
    *,
    tolerance_counts: int = 1,
    velocity_limit: Sequence[float] | None = None,
    acceleration_limit: Sequence[float] | None = None,
    jerk_limit: Sequence[float] | None = None,
) -> ChangePlan:
    """Every axis from (position, velocity, acceleration) to `target` at rest, all arriving together (user
    units, /s, /s^2). Limits default to the cell's per-axis velocity, acceleration and jerk."""
    names = tuple(axis_names)
    cfg = axis_configs(names, cell)
    n = len(cfg)
    p = _vec(positions, "positions", n)
    v = _vec(velocities, "velocities", n)
    a = _vec(accelerations, "accelerations", n)
    goal = _vec(target, "target", n)
    cpu = np.array([c.counts_per_unit for c in cfg])
    vlim = _vec(velocity_limit, "velocity_limit", n) if velocity_limit is not None else np.array(
        [c.velocity for c in cfg])
    alim = _vec(acceleration_limit, "acceleration_limit", n) if acceleration_limit is not None else np.array(
        [c.acceleration for c in cfg])
    jlim = _vec(jerk_limit, "jerk_limit", n) if jerk_limit is not None else np.array([c.jerk for c in cfg])
    _check_target(goal, cfg, names)
    # as a stop: braking from above vlim
    limits = AxisLimits.of(np.array([c.max_profile_velocity for c in cfg]), alim, jlim, velocity_axis=vlim)
    scales = axis_scales(cfg, limits)
    conv = scales.counts_per_ms_per_rpm
    p0 = np.round(p * cpu).astype(np.int64)
    v0 = np.round(v * cpu / 1000.0 / conv).astype(np.int64)
    p_exact = p0 / cpu
    v_exact = v0 * conv * 1000.0 / cpu
    goal = np.round(goal * cpu) / cpu  # the target on whole counts, as every plan's end
    info: dict[str, float] = {}

    def build(f: float, smooth: bool = False) -> Reference:
        return _change_reference(p_exact, v_exact, a, goal, np.maximum(vlim, np.abs(v_exact)),
                                 np.maximum(alim, np.abs(a)), jlim, cpu, time_scale=f)

    ref, knots, rec = encode_with_retries(
        build, scales, int(tolerance_counts), retime=True, axes=names, start_positions=p0,
        start_velocities_rpm=v0, info_out=info,
    )
    _check_swing(ref.positions, cfg, names)
    traj = build_trajectory("move", names, cfg, ref, knots, rec, scales, int(tolerance_counts), limits, info)
    over: list[str] = []
    by: list[int] = []
    for j, name in enumerate(names):
        row = ref.positions[j]
        end = float(goal[j] * cpu[j])
        # past the target in its direction of travel (it must brake beyond it and come back), or the
        # change's own motion crosses the target before it settles there
        side = float(np.sign(float(p0[j]) - end))
        heading = float(np.sign(float(v_exact[j])))
        if side != 0.0 and heading == side:
            past = float(np.max((row - end) * side))
        else:
            ahead = side if side != 0.0 else -heading
            past = float(np.max((row - end) * -ahead)) if ahead != 0.0 else 0.0
        if past > max(1.0, float(tolerance_counts)):
            over.append(name)
            by.append(round(past))
    return ChangePlan(traj, tuple(over), tuple(by))


def plan_change_from_wire(
    cell: CellConfig,
    axis_names: Sequence[str],
    positions_counts: Sequence[int],
    velocities_rpm: Sequence[int],
    accelerations_counts_per_ms2: Sequence[float] | None,
    target: Sequence[float],
    *,
    tolerance_counts: int = 1,
    velocity_limit: Sequence[float] | None = None,
    acceleration_limit: Sequence[float] | None = None,
    jerk_limit: Sequence[float] | None = None,
) -> ChangePlan:
    """plan_change with the state in drive units (counts, rpm, counts/ms^2) and the target in user units."""
    p, v, a = _from_wire(cell, axis_names, positions_counts, velocities_rpm, accelerations_counts_per_ms2)
    return plan_change(cell, axis_names, p, v, a, target, tolerance_counts=tolerance_counts,
                       velocity_limit=velocity_limit, acceleration_limit=acceleration_limit, jerk_limit=jerk_limit)


def _from_wire(
    cell: CellConfig,
    axis_names: Sequence[str],
    positions_counts: Sequence[int],
    velocities_rpm: Sequence[int],
    accelerations_counts_per_ms2: Sequence[float] | None,
) -> tuple[list[float], list[float], list[float]]:
    cfg = axis_configs(tuple(axis_names), cell)
    cpu = np.array([c.counts_per_unit for c in cfg])
    conv = np.array([c.counts_per_rev / 60000.0 for c in cfg])
    p = np.asarray(positions_counts, dtype=np.float64) / cpu
    v = np.asarray(velocities_rpm, dtype=np.float64) * conv * 1000.0 / cpu
    a = (
        np.zeros(len(cfg))
        if accelerations_counts_per_ms2 is None
        else np.asarray(accelerations_counts_per_ms2, dtype=np.float64) * 1.0e6 / cpu
    )
    return p.tolist(), v.tolist(), a.tolist()


def _change_reference(
    position: FloatArray,
    velocity: FloatArray,
    acceleration: FloatArray,
    target: FloatArray,
    vlim: FloatArray,
    alim: FloatArray,
    jlim: FloatArray,
    cpu: FloatArray,
    *,
    time_scale: float = 1.0,
) -> Reference:
    """ruckig's position interface from the given state to the target at rest, time-synchronised."""
    from planner.motion.jerk import counts_reference, from_state

    pos, vel, acc = from_state(position, velocity, acceleration, vlim, alim, jlim, target_position=target,
                               time_scale=time_scale)
    pos[:, -1] = target
    return counts_reference(pos, vel, acc, cpu)


def _check_target(goal: FloatArray, cfg: Sequence[AxisConfig], names: Sequence[str]) -> None:
    for j, c in enumerate(cfg):
        if not c.position_min <= float(goal[j]) <= c.position_max:
            raise PlanningError(
                POSITION_LIMIT,
                f"target[{j}] of axis {names[j]!r} is {float(goal[j]):g}, outside the software position limits "
                f"[{c.position_min:g}, {c.position_max:g}]",
                path=f"target[{j}]",
                detail={"axis": names[j], "target": float(goal[j])},
            )


def _check_swing(positions: FloatArray, cfg: Sequence[AxisConfig], names: Sequence[str]) -> None:
    """A change at speed may brake past its target (or the limit) before it can come back: refuse it when the
    way there leaves the software limits."""
    for j, c in enumerate(cfg):
        row = positions[j] / c.counts_per_unit
        low, high = float(row.min()), float(row.max())
        half = 0.5 / c.counts_per_unit
        if low < c.position_min - half or high > c.position_max + half:
            raise PlanningError(
                INFEASIBLE,
                f"axis {names[j]!r} cannot reach its new target without leaving the software position limits "
                f"[{c.position_min:g}, {c.position_max:g}]: braking from where it is goes to "
                f"{low if low < c.position_min else high:.6g}",
                path=f"target[{j}]",
                detail={"axis": names[j], "min": low, "max": high},
            )


def _vec(x: Sequence[float], name: str, n: int) -> FloatArray:
    a = np.asarray(x, dtype=np.float64)
    if a.shape != (n,):
        raise PlanningError(AXIS_COUNT, f"{name} has {a.size} values for {n} axes", path=name)
    if not np.all(np.isfinite(a)):
        raise PlanningError(NONFINITE, f"{name} contains NaN or infinity", path=name)
    return a
