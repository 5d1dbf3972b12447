"""Travel commands (seed 002's positioning interface): what a move's target means, and endless travel.

Point-to-point modes become an absolute target (`resolve_target`): absolute, relative (from the actual
position), additive (from the last commanded target the streaming side keeps; None: from the actual
position), and modulo_short/plus/minus/current on axes with a `modulo_period` (seed 002: from the actual
position, a tolerance window, extra periods are turns). docs/formats.md ("move") has the rules; seed 002's
tables are tests/planner/motion/test_travel.py. Velocity mode: whole-rpm velocities, `plan_velocity` ramps and
cruises open-ended (`CruiseState`), `extend_velocity` gives each next chunk, cruise knots integers from one
anchor (no drift); a chunk that could no longer stop inside the software limits stops at the last ms that
fits (`info["position_limit_stop"]`), and a ramp that cannot is refused (POSITION_LIMIT).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from planner.config import AxisConfig, CellConfig
from planner.errors import (
    AXIS_COUNT,
    AXIS_ID,
    ENCODING_RANGE,
    INFEASIBLE,
    LIMITS,
    NONFINITE,
    POSITION_LIMIT,
    SCHEMA,
    PlanningError,
)
from planner.job import MODULO_MODES, Job, MoveData, check_relative_target, effective_limits
from planner.motion.reference import FloatArray, IntArray, Reference, hold
from planner.pipeline import axis_configs, axis_scales, build_trajectory, encode_with_retries
from planner.trajectory import DEFAULT_CHUNK_MS, RPM_MS, CruiseState, PvtTrajectory

MIN_CHUNK_MS = 100  # shorter cruise segments turn the knots' rounding (<= 1 count) into acceleration noise
MAX_CHUNK_MS = 60_000
LIMIT_MARGIN_COUNTS = 1.0  # a limit stop ends this far inside the software limits (the knots round)
STOP_RESERVE = 1.3  # a chunk stays open-ended only if a stop this much slower (longer) still fits from its end,
# so the limit stop may be played slower where the encoding needs it and still end inside the limits
CRUISE_SEGMENT_MS = 250  # cruise knots at most this far apart (<= 255, the PVT time field)


# ----------------------------------------------------------------------------------------------------
# position modes


def modulo_end(mode: str, actual: float, target: float, period: float, window: float, last_direction: int = 0) -> float:
    """The absolute end position of one modulo axis (seed 002, see the module docstring)."""
    turns = math.floor(target / period + 1e-12)
    m = target - turns * period
    if m < 0.0 or m >= period:  # float rounding at a period boundary
        m = 0.0
    eps = 1e-9 * period
    if mode == "modulo_short":
        d = (m - actual) % period
        if d > period / 2 + eps:
            d -= period
        return actual + d
    if mode == "modulo_current":
        direction = -1 if last_direction < 0 else 1
    elif mode == "modulo_plus":
        direction = 1
    elif mode == "modulo_minus":
        direction = -1
    else:
        raise PlanningError(SCHEMA, f"mode {mode!r} is not a modulo mode {list(MODULO_MODES)}", path="mode")
    nearest = m + round((actual - m) / period) * period
    if abs(actual - nearest) <= window + eps:
        base = nearest  # inside the tolerance window: the axis counts as standing at the modulo target
    elif direction > 0:
        base = m + math.ceil((actual - m) / period - 1e-12) * period
    else:
        base = m + math.floor((actual - m) / period + 1e-12) * period
    return base + direction * turns * period


def resolve_target(
    job: Job,
    cell: CellConfig,
    actual: Sequence[float] | FloatArray,
    last_target: Sequence[float | None] | None = None,
    *,
    last_direction: Sequence[int] | None = None,
) -> FloatArray:
    """The absolute target (user units, one per job axis) of a point-to-point move in any mode.

    `actual`: where the axes stand (or where the queue ends); `last_target`: the last commanded target
    per axis (None, or a None entry: no target yet, the actual position serves); `last_direction`: per
    axis the sign of the last commanded motion (`modulo_current`; 0 or None: positive). The result lies
    within the software limits (POSITION_LIMIT otherwise, naming what was written and from where).
    """
    d = job.data
    if not isinstance(d, MoveData):
        raise PlanningError(SCHEMA, f"a {job.kind} job has no target to resolve (move jobs only)", path="kind")
    if d.mode == "velocity":
        raise PlanningError(SCHEMA, "a velocity move has no target (plan it with plan_velocity)", path="mode")
    cfg = [cell.axis(a) for a in job.axes]
    n = len(cfg)
    here = _vector(actual, "actual", n)
    offset = np.array(d.target, dtype=np.float64)
    if d.mode == "absolute":
        target = offset.copy()
    elif d.mode == "relative":
        check_relative_target(here, offset, job.axes, cfg, "current position")
        target = here + offset
    elif d.mode == "additive":
        last = [None] * n if last_target is None else list(last_target)
        if len(last) != n:
            raise PlanningError(AXIS_COUNT, f"last_target has {len(last)} values for {n} axes", path="last_target")
        base = np.array([here[j] if last[j] is None else float(last[j]) for j in range(n)])  # type: ignore[arg-type]
        known = [v is not None for v in last]
        name = "last target" if all(known) else "current position" if not any(known) else "last target (or position)"
        check_relative_target(base, offset, job.axes, cfg, name)
        target = base + offset
    else:
        dirs = [0] * n if last_direction is None else list(last_direction)
        if len(dirs) != n:
            raise PlanningError(AXIS_COUNT, f"last_direction has {len(dirs)} values for {n} axes",
                                path="last_direction")
        target = np.array([
            modulo_end(d.mode, float(here[j]), float(offset[j]), c.modulo_period, c.modulo_tolerance, int(dirs[j]))
            for j, c in enumerate(cfg)
        ])
    for j, c in enumerate(cfg):
        if not c.position_min <= target[j] <= c.position_max:
            raise PlanningError(
                POSITION_LIMIT,
                f"target[{j}] of axis {job.axes[j]!r} ({d.mode} {float(offset[j]):g} from {float(here[j]):g}) is "
                f"{float(target[j]):g}, outside the software position limits [{c.position_min:g}, {c.position_max:g}]",
                path=f"target[{j}]",
                detail={"axis": job.axes[j], "target": float(target[j])},
            )
    return target


def _vector(x: Sequence[float | None] | Sequence[float] | FloatArray, name: str, n: int) -> FloatArray:
    a = np.asarray(x, dtype=np.float64)
    if a.shape != (n,):
        raise PlanningError(AXIS_COUNT, f"{name} has {a.size} values for {n} axes", path=name)
    if not np.all(np.isfinite(a)):
        raise PlanningError(NONFINITE, f"{name} contains NaN or infinity", path=name)
    return a


# ----------------------------------------------------------------------------------------------------
# velocity mode


@dataclass(frozen=True)
class MotionState:
    """The axes' state where a plan starts, in wire units as the streamer holds it: positions (counts)
    and velocities (rpm) of the last queued knot, and the drive's Hermite acceleration there (counts/ms^2)."""

    positions_counts: tuple[int, ...]
    velocities_rpm: tuple[int, ...]
    accelerations: tuple[float, ...] = ()  # counts/ms^2; () = 0 on every axis

    @classmethod
    def at_rest(cls, positions_counts: Sequence[int]) -> MotionState:
        return cls(tuple(int(p) for p in positions_counts), (0,) * len(positions_counts))

    @classmethod
    def from_knot(cls, traj: PvtTrajectory, k: int = -1) -> MotionState:
        """The state at knot k of `traj` (default: its end), as the streamer would report it."""
        k = k % traj.n_points
        _p, _v, acc = traj.knot_state(k)
        return cls(
            tuple(int(x) for x in traj.positions[:, k]),
            tuple(int(x) for x in traj.velocities[:, k]),
            tuple(float(x) for x in acc * traj.counts_per_unit / 1.0e6),
        )


def plan_velocity(
    job: Job, cell: CellConfig, start_state: MotionState | None = None, *, chunk_ms: int = DEFAULT_CHUNK_MS
) -> PvtTrajectory:
    """A velocity move: ramp from `start_state` (default: at rest at the job's `start`, else 0) to the
    job's velocities, then cruise `chunk_ms`; open-ended unless the position limits end it (see the module
    docstring). The streaming side extends it with `extend_velocity` while it runs."""

    d = job.data
    if not isinstance(d, MoveData) or d.velocity is None:
        raise PlanningError(SCHEMA, "plan_velocity needs a move job with mode 'velocity'", path="mode")
    _check_chunk(chunk_ms)
    cfg = axis_configs(job.axes, cell)
    n = len(cfg)
    cpu = np.array([c.counts_per_unit for c in cfg])
    conv = np.array([c.counts_per_rev / RPM_MS for c in cfg])  # counts/ms per rpm
    if start_state is None:
        origin = np.array(d.start) if d.start is not None else np.zeros(n)
        start_state = MotionState.at_rest(np.round(origin * cpu).astype(np.int64).tolist())
    p0 = np.array(start_state.positions_counts, dtype=np.int64)
    v0 = np.array(start_state.velocities_rpm, dtype=np.int64)
    a0 = np.array(start_state.accelerations or (0.0,) * n, dtype=np.float64)  # counts/ms^2
    for name, arr in (("positions_counts", p0), ("velocities_rpm", v0), ("accelerations", a0)):
        if arr.shape != (n,):
            raise PlanningError(AXIS_COUNT, f"start_state.{name} has {arr.size} values for {n} axes",
                                path=f"start_state.{name}")
    limits = effective_limits(job, cell)
    # the wire's resolution: whole rpm, toward zero (never above the velocity limit)
    v_rpm = np.trunc(np.asarray(d.velocity) * cpu / 1000.0 / conv).astype(np.int64)
    v_cpm = v_rpm * conv  # counts/ms
    moving = bool(np.any(v0 != 0) or np.any(a0 != 0.0))
    checks = limits
    if moving:  # a ramp from a moving state may briefly exceed the job's limit: 0x607F bounds it (as stops)
        checks = limits.with_velocity(np.maximum(limits.velocity, np.array([c.max_profile_velocity for c in cfg])))
    scales = axis_scales(cfg, checks)
    tol = job.tolerance_counts
    lo = np.array([c.position_min for c in cfg]) * cpu + LIMIT_MARGIN_COUNTS
    hi = np.array([c.position_max for c in cfg]) * cpu - LIMIT_MARGIN_COUNTS

    # per axis: speeding up plans with the acceleration, slowing down with the deceleration (seed 002's two
    # ramps), a reversal with the smaller one
    up = (v_rpm * v0 >= 0) & (np.abs(v_rpm) >= np.abs(v0))
    down = (v_rpm * v0 >= 0) & (np.abs(v_rpm) < np.abs(v0))
    slower = np.minimum(limits.acceleration_up, limits.deceleration)
    ramp_acc = np.where(up, limits.acceleration_up, np.where(down, limits.deceleration, slower))
    v_user = v_cpm * 1000.0 / cpu
    asked = np.asarray(d.velocity)
    decel, jerk = limits.deceleration, limits.jerk
    open_ended = bool(np.any(v_rpm != 0))
    info: dict[str, float] = {}
    # open-ended if a stop from the chunk's end still fits with STOP_RESERVE to spare (decided once, at the
    # plan's own timing: the end velocity the encoder pins depends on it)
    ramp = _velocity_ramp(p0 / cpu, v0 * conv * 1000.0 / cpu, a0 * 1.0e6 / cpu, v_user, ramp_acc, jerk, cpu)
    info["velocity_ramp_ms"] = float(ramp.duration_ms)
    if open_ended:
        reserve = _stop_distance(v_user, decel, jerk, cpu, STOP_RESERVE)
        open_ended = _latest_stop(ramp.positions[:, -1], v_cpm, reserve, lo, hi)[0] >= chunk_ms
    moving_to = bool(np.any(v_rpm != 0))

    def build(f: float, smooth: bool = False) -> Reference:
        """Ramp, cruise, and (closed at the limits) the stop, the ramp and stop played `f` times slower."""
        slow = ramp if f <= 1.0 else _velocity_ramp(p0 / cpu, v0 * conv * 1000.0 / cpu, a0 * 1.0e6 / cpu, v_user,
                                                    ramp_acc, jerk, cpu, time_scale=f)
        p_r = slow.positions[:, -1]
        if open_ended:
            return _concat(slow, _cruise(p_r, v_cpm, chunk_ms), None)
        if not moving_to:  # a ramp to rest (already at rest: hold still for 1 ms, a valid no-op)
            return slow if slow.duration_ms > 0 else hold(slow.positions[:, 0], 1)
        # the latest cruise ms after the ramp from which the stop still ends inside the limits
        latest, j = _latest_stop(p_r, v_cpm, _stop_distance(v_user, decel, jerk, cpu, f), lo, hi)
        if latest < 0:
            raise PlanningError(
                POSITION_LIMIT,
                f"velocity[{j}] of axis {job.axes[j]!r} is {float(asked[j]):g}/s: after its ramp, at "
                f"{p_r[j] / cpu[j]:g}, it cannot stop inside the software position limits "
                f"[{cfg[j].position_min:g}, {cfg[j].position_max:g}]",
                path=f"velocity[{j}]",
                detail={"axis": job.axes[j]},
            )
        info["position_limit_stop"] = 1.0
        info["limit_axis"] = float(j)
        cruise_ms = latest  # past the chunk where only the reserve closed it: this is the last chunk
        stop = _stop_from_cruise(p_r + v_cpm * cruise_ms, v_cpm, decel, jerk, cpu, time_scale=f)
        return _concat(slow, _cruise(p_r, v_cpm, cruise_ms) if cruise_ms > 0 else None, stop)

    _check_inside(build(1.0), cfg, job.axes, cpu, asked)

    ref, knots, rec = encode_with_retries(
        build, scales, tol, retime=True, axes=job.axes, start_positions=p0, start_velocities_rpm=v0, info_out=info,
        end_velocities_rpm=v_rpm if open_ended else None,
    )
    cruise = None
    if open_ended:
        cruise = CruiseState(
            cell=cell,
            axes=tuple(job.axes),
            anchor_counts=tuple(int(x) for x in knots.positions[:, -1]),
            velocity_rpm=tuple(int(x) for x in v_rpm),
            elapsed_ms=0,
            deceleration=tuple(float(x) for x in limits.deceleration),
            jerk=tuple(float(x) for x in limits.jerk),
            velocity_limit=tuple(float(x) for x in limits.velocity),
            acceleration_limit=tuple(float(x) for x in limits.acceleration),
            acceleration_axis=tuple(float(x) for x in limits.acceleration_axis),
            tolerance_counts=tol,
            chunk_ms=chunk_ms,
        )
    traj = build_trajectory(job.kind, job.axes, cfg, ref, knots, rec, scales, tol, checks, info, cruise)
    return _with_cyclic_stats(traj, cfg, cell)


def extend_velocity(traj_or_state: PvtTrajectory | CruiseState, chunk_ms: int | None = None) -> PvtTrajectory:
    """The next chunk of an open-ended velocity move: knot 0 is exactly the previous chunk's last knot;
    `chunk_ms` of cruise (default: the plan's), or up to the limit stop (closed) where the position
    limits come first (see the module docstring)."""
    from planner.encoding.encoder import ACC_EXCESS_LIMIT
    from planner.encoding.reconstruction import Knots, acceleration_excess, planned_demand, reconstruct

    st = traj_or_state.open_end if isinstance(traj_or_state, PvtTrajectory) else traj_or_state
    if st is None:
        raise PlanningError(SCHEMA, "the trajectory ends at rest: only an open-ended (velocity) plan is extended",
                            path="open_end")
    chunk = st.chunk_ms if chunk_ms is None else int(chunk_ms)
    _check_chunk(chunk)
    cfg = list(st.cfg)
    cpu = np.array([c.counts_per_unit for c in cfg])
    v_cpm = st.velocity_counts_per_ms()
    limits = st.limits()
    scales = axis_scales(cfg, limits)
    tol = st.tolerance_counts
    e0 = st.elapsed_ms
    anchor = np.array(st.anchor_counts, dtype=np.float64)
    lo = np.array([c.position_min for c in cfg]) * cpu + LIMIT_MARGIN_COUNTS
    hi = np.array([c.position_max for c in cfg]) * cpu - LIMIT_MARGIN_COUNTS
    reserve = _stop_distance(v_cpm * 1000.0 / cpu, np.array(st.deceleration), np.array(st.jerk), cpu, STOP_RESERVE)
    latest, axis = _latest_stop(anchor, v_cpm, reserve, lo, hi)  # in cruise ms since the anchor
    info: dict[str, float] = {"velocity_extension": 1.0, "cruise_elapsed_ms": float(e0)}
    p_first = np.array(st.position_at(e0), dtype=np.int64)
    v_first = np.array(st.velocity_rpm, dtype=np.int64)
    if latest >= e0 + chunk:
        parts = -(-chunk // CRUISE_SEGMENT_MS)
        times = np.round(np.linspace(0.0, chunk, parts + 1)).astype(np.int64)
        pos = np.array([st.position_at(e0 + int(t)) for t in times], dtype=np.int64).T
        vel = np.repeat(v_first[:, None], times.size, axis=1)
        ref = _cruise(anchor + v_cpm * e0, v_cpm, chunk)
        knots = Knots(times, pos, vel)
        rec = reconstruct(knots, scales)
        dev = np.abs(rec.demand - planned_demand(ref, scales.toward_zero))
        if (dev > tol).any():  # cannot happen by construction (module docstring); never send it if it did
            raise PlanningError(INFEASIBLE, f"cruise chunk deviates {int(dev.max())} counts "
                                f"from its plan (tolerance {tol})", path="tolerance_counts")
        # the knots' rounding (up to a count between two knots) makes 6 * count / T^2 of acceleration
        excess = acceleration_excess(ref, knots, rec).max(axis=1) / scales.acceleration_axis
        if (excess > ACC_EXCESS_LIMIT).any():
            j = int(np.argmax(excess))
            raise PlanningError(
                INFEASIBLE,
                f"cruise segments of {int(np.diff(times).min())} ms make {100 * excess[j]:.1f} % of axis "
                f"{st.axes[j]!r}'s acceleration limit of noise (rounding to whole counts): use longer chunks",
                path="chunk_ms",
            )
        traj = build_trajectory("move", st.axes, cfg, ref, knots, rec, scales, tol, limits, info,
                                dataclasses.replace(st, elapsed_ms=e0 + chunk, chunk_ms=chunk))
        return _with_cyclic_stats(traj, cfg, st.cell)
    # the limit stop: cruise from knot 0 exactly (a whole count: the plan must start on it) to the last ms
    # from which the stop fits, then brake; played slower where the encoding needs it, starting earlier
    # then, since a slower stop needs more room
    start = p_first.astype(np.float64)
    decel, jerk = np.array(st.deceleration), np.array(st.jerk)
    info["position_limit_stop"] = 1.0
    info["limit_axis"] = float(axis)

    def build(f: float, smooth: bool = False) -> Reference:
        stop = _stop_from_cruise(np.zeros(len(cfg)), v_cpm, decel, jerk, cpu, time_scale=f)
        latest_f, _axis = _latest_stop(start, v_cpm, stop.positions[:, -1], lo, hi)
        cruise_ms = max(latest_f, 0)
        stop = _stop_from_cruise(start + v_cpm * cruise_ms, v_cpm, decel, jerk, cpu, time_scale=f)
        return _concat(_cruise(start, v_cpm, cruise_ms), None, stop) if cruise_ms > 0 else stop

    ref, knots, rec = encode_with_retries(
        build, scales, tol, retime=True, axes=st.axes, start_positions=p_first, start_velocities_rpm=v_first,
        info_out=info,
    )
    traj = build_trajectory("move", st.axes, cfg, ref, knots, rec, scales, tol, limits, info)
    return _with_cyclic_stats(traj, cfg, st.cell)


def _with_cyclic_stats(traj: PvtTrajectory, cfg: Sequence[AxisConfig], cell: CellConfig) -> PvtTrajectory:
    """planner/encoding/cyclic.py's stats of the axes fed one set point per SYNC. An open-ended chunk does not end at
    rest (what `cyclic.assess` assumes of a plan's end): its set points are sampled from the plan carried
    on at the cruise velocity for two more periods, and the drive's deviation is measured up to the
    chunk's end."""
    from planner.encoding.cyclic import (
        INTERPOLATIONS,
        deviation,
        interpolation_of,
        sample,
        wire_problem,
        with_cyclic_stats,
    )

    if traj.open_end is None or all(interpolation_of(c) is None for c in cfg):
        return with_cyclic_stats(traj, cfg, cell.sync_period_ms, cell.axes)
    period = cell.sync_period_ms
    in_job = {c.name for c in cfg}
    for c in cfg:  # as with_cyclic_stats: a multiplexed frame carries every axis of its group
        left_out = [a.name for a in cell.axes if c.mux_group and a.mux_group == c.mux_group and a.name not in in_job]
        if left_out:
            raise PlanningError(AXIS_ID, f"axis {c.name!r} shares multiplexed frame (mux_group {c.mux_group}) with "
                                f"{left_out}: a job must include every axis of the group", path="axes",
                                detail={"axis": c.name, "mux_group": c.mux_group, "missing": left_out})
    ref = traj.plan
    m = ref.duration_ms
    extra = np.arange(1, 2 * period + 1, dtype=np.float64)
    stats = list(traj.stats)
    for i, c in enumerate(cfg):
        interp = interpolation_of(c)
        if interp is None:
            continue
        v_end = ref.velocities[i, -1]
        pos = np.concatenate([ref.positions[i], ref.positions[i, -1] + v_end * extra])
        vel = np.concatenate([ref.velocities[i], np.full(extra.size, v_end)])
        sp = sample(pos, vel, period, pv=interp == "pv")
        problem = wire_problem(c, sp)
        if problem is not None:
            raise PlanningError(ENCODING_RANGE, problem[0], path=f"axis[{c.name}]", detail=problem[1])
        whole, raw = deviation(pos, sp, interp, until_ms=m)
        alternatives = {
            other: deviation(pos, sample(pos, vel, period, pv=other == "pv"), other, until_ms=m)[0]
            for other in INTERPOLATIONS if other != interp
        } if c.profile == "xtrapuls-ip" else {}
        if whole > traj.tolerance_counts:
            raise PlanningError(
                INFEASIBLE,
                f"axis {c.name!r}: its drive's own {interp} interpolation at a {period} ms SYNC period deviates "
                f"{whole} counts from the velocity move's plan (tolerance {traj.tolerance_counts})",
                path=f"axis[{c.name}]",
                detail={"axis": c.name, "deviation_counts": whole, "interpolation": interp,
                        "sync_period_ms": period, "alternatives": alternatives},
            )
        stats[i] = dataclasses.replace(stats[i], max_deviation_counts=whole, max_deviation_from_plan_counts=raw,
                                       interpolation=interp, setpoint_period_ms=period,
                                       interpolation_alternatives=alternatives)
    return dataclasses.replace(traj, stats=tuple(stats))


def _check_chunk(chunk_ms: int) -> None:
    if not (isinstance(chunk_ms, int) and MIN_CHUNK_MS <= chunk_ms <= MAX_CHUNK_MS):
        raise PlanningError(LIMITS, f"chunk_ms must be a whole number of ms in {MIN_CHUNK_MS}..{MAX_CHUNK_MS}, got "
                            f"{chunk_ms!r}", path="chunk_ms")


def _velocity_ramp(
    p: FloatArray, v: FloatArray, a: FloatArray, target: FloatArray, alim: FloatArray, jlim: FloatArray,
    cpu: FloatArray, *, time_scale: float = 1.0,
) -> Reference:
    """Jerk-limited ramp (user units) from (p, v, a) to velocity `target` at acceleration 0, all axes
    arriving together (ruckig's velocity interface, time-synchronised, whole ms)."""
    from planner.motion.jerk import counts_reference, from_state

    if np.all(v == target) and np.all(a == 0.0):
        return _line(p * cpu, target * cpu / 1000.0, 0)
    pos, vel, acc = from_state(p, v, a, np.maximum(np.abs(target), np.abs(v)) + 1.0, np.maximum(alim, np.abs(a)),
                               jlim, target_velocity=target, time_scale=time_scale)
    vel[:, -1] = target  # sample_profiles pins a rest end; this ramp ends cruising
    acc[:, -1] = 0.0
    return counts_reference(pos, vel, acc, cpu)


def _line(start_counts: FloatArray, v_cpm: FloatArray, duration_ms: int) -> Reference:
    t = np.arange(duration_ms + 1, dtype=np.float64)
    pos = start_counts[:, None] + v_cpm[:, None] * t[None, :]
    vel = np.repeat(v_cpm[:, None], t.size, axis=1)
    z = np.zeros_like(pos)
    return Reference(pos, vel, z, z, np.zeros(0, dtype=np.int64))


def _cruise(start_counts: FloatArray, v_cpm: FloatArray, duration_ms: int) -> Reference:
    return _line(np.asarray(start_counts, dtype=np.float64), v_cpm, duration_ms)


def _stop_distance(
    v: FloatArray, dlim: FloatArray, jlim: FloatArray, cpu: FloatArray, time_scale: float = 1.0
) -> FloatArray:
    """Counts each axis travels in the (time-synchronised) stop from cruising at `v` (user units/s)."""
    stop = _stop_from_cruise(np.zeros(v.size), v * cpu / 1000.0, dlim, jlim, cpu, time_scale=time_scale)
    out: FloatArray = stop.positions[:, -1].copy()
    return out


def _stop_from_cruise(
    p_counts: FloatArray, v_cpm: FloatArray, dlim: FloatArray, jlim: FloatArray, cpu: FloatArray, *,
    time_scale: float = 1.0,
) -> Reference:
    """The stop from cruising at `v_cpm` (counts/ms) at `p_counts`: jerk-limited at the deceleration."""
    from planner.motion.jerk import stop_reference

    if np.all(v_cpm == 0.0):
        return hold(p_counts, 1)
    v = v_cpm * 1000.0 / cpu
    return stop_reference(p_counts / cpu, v, np.zeros(v.size), np.abs(v) + 1.0, dlim, jlim, cpu, time_scale=time_scale)


def _latest_stop(
    p_counts: FloatArray, v_cpm: FloatArray, dist: FloatArray, lo: FloatArray, hi: FloatArray
) -> tuple[int, int]:
    """The latest whole ms of cruise from `p_counts` after which the stop still ends inside [lo, hi], and the
    axis that sets it (MAX int when no axis moves toward a limit)."""
    best, axis = 2**62, 0
    for j in range(v_cpm.size):
        if v_cpm[j] == 0.0:
            continue
        bound = hi[j] if v_cpm[j] > 0 else lo[j]
        e = math.floor((bound - p_counts[j] - dist[j]) / v_cpm[j])
        if e < best:
            best, axis = e, j
    return best, axis


def _concat(first: Reference, middle: Reference | None, last: Reference | None) -> Reference:
    """Pieces that meet end to start (shared sample dropped), and a break where the acceleration may step."""
    parts = [r for r in (first, middle, last) if r is not None and r.duration_ms > 0] or [first]
    pos = [parts[0].positions]
    vel = [parts[0].velocities]
    al = [parts[0].acc_left]
    ar = [parts[0].acc_right]
    breaks: list[IntArray] = [parts[0].breaks]
    hints: list[IntArray] = [parts[0].hints]
    offset = parts[0].duration_ms
    for r in parts[1:]:
        ar[-1] = ar[-1].copy()
        ar[-1][:, -1] = r.acc_right[:, 0]  # the acceleration right of the joint is the next piece's
        pos.append(r.positions[:, 1:])
        vel.append(r.velocities[:, 1:])
        al.append(r.acc_left[:, 1:])
        ar.append(r.acc_right[:, 1:])
        breaks.append(np.concatenate([[offset], r.breaks + offset]).astype(np.int64))
        hints.append(np.concatenate([[offset], r.hints + offset]).astype(np.int64))
        offset += r.duration_ms
    return Reference(np.hstack(pos), np.hstack(vel), np.hstack(al), np.hstack(ar),
                     np.concatenate(breaks).astype(np.int64), np.concatenate(hints).astype(np.int64))


def _check_inside(ref: Reference, cfg: Sequence[AxisConfig], axes: Sequence[str], cpu: FloatArray,
                  velocity: FloatArray) -> None:
    """The ramp (a reversal swings out before it comes back) stays inside the software limits."""
    for j, c in enumerate(cfg):
        row = ref.positions[j] / cpu[j]
        k = int(np.argmax(np.maximum(c.position_min - row, row - c.position_max)))
        if not c.position_min - 0.5 / cpu[j] <= row[k] <= c.position_max + 0.5 / cpu[j]:
            raise PlanningError(
                POSITION_LIMIT,
                f"velocity[{j}] of axis {axes[j]!r} is {float(velocity[j]):g}/s: its ramp reaches {row[k]:g} at "
                f"t = {k / 1000:.3f} s, outside the software position limits [{c.position_min:g}, {c.position_max:g}]",
                path=f"velocity[{j}]",
                detail={"axis": axes[j]},
            )
