"""plan_job: a validated `Job` on a cell -> `PvtTrajectory` (plan, encode, verify, measure).

Theory of operation. Each job kind has a reference builder (path.py: toppra along the job's geometry,
geometry.py's blended segments by default; jerk.py: ruckig along the straight line for moves;
timed.py: the user's timing) that yields the planned motion of every axis at every ms in counts. The
encoder (encoder.py) turns it into knots and proves the drive's reconstruction; the statistics in the
trajectory are measured on that reconstruction. Where the encoder finds the motion too fast for the
wire's resolution (sub-count moves: one count of quantisation is then a large share of the motion),
planned kinds (path, move, stop) are played slower and encoded again; user timings (timed, pvt) are
rejected instead. Start and end positions are snapped to whole counts first: the drive stands on
whole counts, and the plan must start exactly where the drive is.

A path along straight segments uses its `path_tolerance` minus what the encoding may add
(`lines_geometry`), so the drive's own motion stays within it; a spline path is checked against the
software limits and refused at its peak excursion. `info` says how the motion follows its geometry
(blended corners and exact stops; for moves, whether along the line and how far from it).

Errors are PlanningError with stable codes; no toppra/ruckig/numpy exception escapes.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from planner.config import AxisConfig, CellConfig
from planner.cyclic import with_cyclic_stats
from planner.encoder import (
    ACC_EXCESS_LIMIT,
    AxisScales,
    EncodingFailed,
    EncodingNeedsTime,
    Knots,
    Reconstruction,
    acceleration_excess,
    encode,
    load_kernels,
    planned_demand,
    reconstruct,
    segment_bounds,
)
from planner.errors import ENCODING_RANGE, INFEASIBLE, LIMITS, POSITION_LIMIT, TOO_LARGE, PlanningError
from planner.job import (
    MAX_DURATION_S,
    Job,
    MoveData,
    PathData,
    PvtData,
    TimedData,
    check_relative_target,
    effective_limits,
    jerk_limited,
    path_tolerance,
)
from planner.reference import FloatArray, IntArray, Reference
from planner.trajectory import AxisStats, PvtTrajectory

if TYPE_CHECKING:
    from planner.geometry import PiecewisePath
    from planner.path import ChainSpec
    from planner.travel import CruiseState

# attempts at encoding a planned motion: the placements (3, or 4 with a path's smooth plan), then slower
# replays (`encode_with_retries`). Measured on 2700 random paths of 2-200 counts between waypoints
# (benchmarks/bench_planner.py's path-small corpus): with 6, 5.5 % of them were refused (1.46x slower at
# most); with 15 and the growing steps, none
MAX_SLOWDOWNS = 15
TINY_PATH_COUNTS = 1.0  # a path whose every axis spans less than this is planned as a straight move
MIN_BLEND_SEGMENTS = 3.0  # a blend shorter than this many shortest segments is an exact stop (geometry)
BLEND_SHARE = 0.8  # of the free path tolerance: the blends; the rest, the chain (lines_geometry)
MIN_SWITCH_PIECE_MS = 10  # shorter profile pieces between two switches are merged (see path.Profile)


def axis_configs(axes: Sequence[str], cell: CellConfig) -> list[AxisConfig]:
    return [cell.axis(a) for a in axes]


def axis_scales(
    cfg: Sequence[AxisConfig], limits: dict[str, FloatArray], max_segment_ms: int | None = None
) -> AxisScales:
    cpu = np.array([c.counts_per_unit for c in cfg])
    return AxisScales(
        counts_per_ms_per_rpm=np.array([c.counts_per_rev / 60000.0 for c in cfg]),
        velocity_limit=limits["velocity"] * cpu / 1000.0,
        acceleration_limit=limits["acceleration"] * cpu / 1.0e6,
        acceleration_axis=limits["acceleration_axis"] * cpu / 1.0e6,
        drive_velocity=np.array([c.max_profile_velocity for c in cfg]) * cpu / 1000.0,
        drive_acceleration=np.array([c.max_acceleration for c in cfg]) * cpu / 1.0e6,
        # the drive's rounding of its demand where `pvt probe` found it truncates (else to nearest)
        toward_zero=np.array([c.probed.rounding == "toward_zero" for c in cfg]),
        max_segment_ms=max_segment_ms,
    )


def snap(x: FloatArray, cpu: FloatArray) -> FloatArray:
    """User-unit positions moved to the nearest whole count (the drive stands on whole counts)."""
    out: FloatArray = np.round(x * cpu) / cpu
    return out


def plan_job(
    job: Job,
    cell: CellConfig,
    *,
    start: Sequence[float] | None = None,
    last_target: Sequence[float | None] | None = None,
    last_direction: Sequence[int] | None = None,
    max_segment_ms: int | None = None,
) -> PvtTrajectory:
    """Plan, encode and verify `job` on `cell`.

    `start`: where the axes stand now (user units, one per job axis). A move starts there (relative
    moves are relative to it); path, timed and pvt jobs start at their first row, which must then be
    within `tolerance_counts` of it (the first row is replaced by `start` so knot 0 is the drive's
    position). Without `start`, a move starts at its `start` field, else at 0. `last_target` and
    `last_direction` serve the additive and modulo_current modes (planner/travel.py). A velocity move is
    planned open-ended from rest there (`travel.plan_velocity`, which also takes a moving start).
    `max_segment_ms` bounds the PVT segments (a job with a short lead: `StreamerSettings.segment_cap_ms`).
    """
    d0 = job.data
    if isinstance(d0, MoveData) and d0.mode == "velocity":
        from planner.travel import MotionState, plan_velocity

        rest = None
        if start is not None:
            cpu0 = np.array([cell.axis(a).counts_per_unit for a in job.axes])
            rest = MotionState.at_rest(np.round(_start_vector(start, job.axes) * cpu0).astype(np.int64).tolist())
        return plan_velocity(job, cell, rest)
    cfg = axis_configs(job.axes, cell)
    n = len(cfg)
    shape = ["spline"]  # spline path jobs: "pchip" for the one-axis fallback below
    limits = effective_limits(job, cell)
    cpu = np.array([c.counts_per_unit for c in cfg])
    if max_segment_ms is not None and not 1 <= max_segment_ms <= 255:
        raise PlanningError(LIMITS, f"max_segment_ms is {max_segment_ms}; it must be a whole ms in 1..255",
                            path="max_segment_ms")
    scales = axis_scales(cfg, limits, max_segment_ms)
    tol = job.tolerance_counts
    here = None if start is None else _start_vector(start, job.axes)
    min_seg = segment_bounds(scales, float(tol))[0]
    info: dict[str, float] = {}
    if max_segment_ms is not None:  # the bound in force (raised to what the acceleration budget allows)
        info["max_segment_ms"] = float(segment_bounds(scales, float(tol))[1])
    d = job.data
    smooth_differs = False  # build(f, True) is another plan (toppra paths; see encode_with_retries)

    build: Callable[[float, bool], Reference]
    if isinstance(d, PathData):
        wp = np.array(d.waypoints, dtype=np.float64)
        if here is not None:
            _check_start(here, wp[0], cpu, tol, job.axes, "waypoints[0]")
            wp[0] = here
        wp = _merge_close(wp, cpu)
        wp[0], wp[-1] = snap(wp[0], cpu), snap(wp[-1], cpu)
        _check_duration_bound(np.abs(np.diff(wp, axis=0)).sum(axis=0), limits["velocity"])
        extent = (wp.max(axis=0) - wp.min(axis=0)) * cpu
        if wp.shape[0] < 2 or float(extent.max()) < TINY_PATH_COUNTS:
            first, last = wp[0], wp[-1]

            def build(f: float, smooth: bool = False) -> Reference:
                from planner.jerk import move_reference

                return move_reference(
                    first,
                    last,
                    limits["velocity"],
                    limits["acceleration"],
                    limits["jerk"],
                    cpu,
                    time_scale=f,
                    max_duration_s=MAX_DURATION_S,
                )
        else:
            runs = None
            chain = None
            if d.geometry == "lines":
                runs, chain = lines_geometry(
                    wp,
                    cpu,
                    limits["velocity"],
                    limits["acceleration"],
                    path_tolerance(job, cell),
                    tol,
                    segment_bounds(scales, tol),
                    (np.array([c.position_min for c in cfg]), np.array([c.position_max for c in cfg])),
                    info,
                )

            jerk = jerk_limited(job, cell)
            if jerk:
                info["jerk_limited"] = 1.0
            smooth_differs = not jerk  # a jerk-limited plan has no smoother variant

            def build(f: float, smooth: bool = False) -> Reference:
                from planner.path import SplineGeometry, plan_path

                if jerk:
                    from planner.jerkpath import plan_jerk_path

                    ref, path_info = plan_jerk_path(
                        runs if runs is not None else [SplineGeometry(wp, limits["velocity"], shape[0])],
                        cpu,
                        limits["velocity"],
                        limits["acceleration"],
                        limits["jerk"],
                        time_scale=f,
                        max_duration_s=MAX_DURATION_S,
                    )
                    info.update(path_info)
                    info["jerk_stops"] = 0.0
                    if runs is not None:
                        # along the segments: stopping at every corner with jerk-limited moves, where faster
                        from planner.jerkpath import stop_at_corners

                        stops = stop_at_corners(wp, cpu, limits["velocity"], limits["acceleration"],
                                                limits["jerk"], time_scale=f, max_duration_s=MAX_DURATION_S)
                        if stops.duration_ms < ref.duration_ms:
                            info["jerk_stops"] = 1.0
                            return stops
                    return ref
                # the smooth retry (the encoder failed on short pieces): a chain without short segments
                spec = None if chain is None else dataclasses.replace(chain, short=not smooth)
                ref, path_info = plan_path(
                    runs if runs is not None else [SplineGeometry(wp, limits["velocity"], shape[0])],
                    cpu,
                    limits["velocity"],
                    limits["acceleration"],
                    time_scale=f,
                    min_piece_ms=max(MIN_SWITCH_PIECE_MS, min_seg)
                    if smooth
                    else min(MIN_SWITCH_PIECE_MS, min_seg),
                    max_duration_s=MAX_DURATION_S,
                    chain=spec,
                )
                info.update(path_info)
                return ref
    elif isinstance(d, MoveData):
        origin = here if here is not None else (np.array(d.start) if d.start is not None else np.zeros(n))
        _check_within(origin, cfg, job.axes, "start")
        if d.mode == "relative":
            check_relative_target(origin, d.target, job.axes, cfg, "current position" if here is not None else "start")
        if d.mode in ("absolute", "relative"):
            target = origin + np.array(d.target) if d.mode == "relative" else np.array(d.target)
        else:  # additive, modulo: what the target means (planner/travel.py)
            from planner.travel import resolve_target

            target = resolve_target(job, cell, origin, last_target, last_direction=last_direction)
        _check_within(target, cfg, job.axes, "target")
        a, b = snap(origin, cpu), snap(target, cpu)
        _check_duration_bound(np.abs(b - a), limits["velocity"])

        def build(f: float, smooth: bool = False) -> Reference:
            from planner.jerk import move_reference

            return move_reference(
                a,
                b,
                limits["velocity"],
                limits["acceleration_up"],
                limits["jerk"],
                cpu,
                time_scale=f,
                max_duration_s=MAX_DURATION_S,
                info=info,
                dlim=limits["deceleration"] if d.ramps is not None else None,
            )
    elif isinstance(d, TimedData):
        pos = np.array(d.positions, dtype=np.float64)
        if here is not None:
            _check_start(here, pos[0], cpu, tol, job.axes, "positions[0]")
            pos[0] = here
        pos[0], pos[-1] = snap(pos[0], cpu), snap(pos[-1], cpu)
        times = np.array(d.times)

        def build(f: float, smooth: bool = False) -> Reference:
            from planner.timed import check_user_timing, timed_reference

            ref = timed_reference(times, pos, cpu)
            check_user_timing(ref, scales.velocity_limit, scales.acceleration_limit, job.axes, cpu)
            return ref
    else:
        assert isinstance(d, PvtData)
        pos = np.array(d.positions, dtype=np.float64)
        vel = np.array(d.velocities, dtype=np.float64)
        for row, name in ((0, "first"), (-1, "last")):
            if np.any(vel[row] != 0.0):
                j = int(np.argmax(vel[row] != 0.0))
                k = 0 if row == 0 else vel.shape[0] - 1
                raise PlanningError(
                    INFEASIBLE,
                    f"velocities[{k}][{j}] of axis {job.axes[j]!r} is {vel[row, j]:g}; the "
                    f"{name} PVT row must be at rest (the drive starts and ends at "
                    f"velocity 0)",
                    path=f"velocities[{k}][{j}]",
                )
        if here is not None:
            _check_start(here, pos[0], cpu, tol, job.axes, "positions[0]")
            pos[0] = here
        pos[0], pos[-1] = snap(pos[0], cpu), snap(pos[-1], cpu)
        from planner.timed import check_user_timing, pvt_reference

        pvt_ref, _rows_ms = pvt_reference(np.array(d.times), pos, vel, cpu)
        # the rows' own Hermite may exceed the limits; quantisation adds up to the 5 % excess budget
        check_user_timing(
            pvt_ref,
            scales.velocity_limit * 1.005,
            scales.acceleration_limit,
            job.axes,
            cpu,
            acc_slack=ACC_EXCESS_LIMIT,
        )

        def build(f: float, smooth: bool = False) -> Reference:
            return pvt_ref

    retime = isinstance(d, PathData | MoveData)
    ref, knots, rec = encode_with_retries(
        build,
        scales,
        tol,
        retime=retime,
        axes=job.axes,
        info_out=info,
        uniform_fallback=True,
        smooth_differs=smooth_differs,
    )
    try:
        _check_reference_positions(ref, cfg, job.axes)
    except PlanningError as e:
        spline = isinstance(d, PathData) and d.geometry == "spline"
        if not (spline and n == 1 and e.code == POSITION_LIMIT and shape[0] == "spline"):
            raise
        # one axis, and the C2 spline overshot its waypoints out of the limits: the shape-preserving
        # path cannot (it stays between consecutive waypoints); slower, but a plan instead of a refusal
        shape[0] = "pchip"
        info["path_shape_pchip"] = 1.0
        ref, knots, rec = encode_with_retries(
            build, scales, tol, retime=retime, axes=job.axes, info_out=info, smooth_differs=smooth_differs
        )
        _check_reference_positions(ref, cfg, job.axes)
    if isinstance(d, MoveData):
        info["line_deviation_counts"] = line_deviation_counts(rec.position, ref.positions[:, 0], ref.positions[:, -1])
    if info.get("jerk_limited", 0.0) == 1.0:
        # the knot values re-chosen so that the drive's acceleration stays continuous (planner/continuity.py)
        from planner.continuity import smooth_values

        smoothed = smooth_values(ref, knots, scales, float(tol), limits["jerk"] * cpu / 1.0e9)
        if smoothed is not knots:
            knots, rec = smoothed, reconstruct(smoothed, scales)
    traj = build_trajectory(job.kind, job.axes, cfg, ref, knots, rec, scales, tol, limits, info)
    # axes whose drives take one set point per SYNC: their own interpolation must follow within tolerance
    return with_cyclic_stats(traj, cfg, cell.sync_period_ms, cell.axes)


def encode_with_retries(
    build: Callable[[float, bool], Reference],
    scales: AxisScales,
    tol: int,
    *,
    retime: bool,
    times_ms: IntArray | None = None,
    axes: Sequence[str] = (),
    start_positions: IntArray | None = None,
    start_velocities_rpm: IntArray | None = None,
    info_out: dict[str, float] | None = None,
    uniform_fallback: bool = False,
    end_velocities_rpm: IntArray | None = None,
    smooth_differs: bool = False,
) -> tuple[Reference, Knots, Reconstruction]:
    """Build the reference and encode it; planned motions are slowed down when quantisation needs it.

    The order of the retries: the conservative and then the long placement (encoder `variant` 1, 2) on
    the plan as built; with `smooth_differs` (path jobs, whose `build(f, True)` is another plan: a chain
    without short segments on a profile with its switch pieces merged more widely, which its repairs
    often make a few % slower), the long placement is tried on that smooth plan only after it failed on
    the first one; then slower replays of the smooth plan, each by the factor the encoder asks for
    (at least 5 %), raised to the power 1, 2, 3, ... every third replay.

    `info_out` receives `time_scale` (1.0 unless the motion had to be played slower),
    `encode_variant` (1 or 2 when the encoder needed its conservative or long placement) and
    `smooth_plan` (1 when the smooth plan was needed).
    """
    if info_out is None:
        info_out = {}
    factor = 1.0
    last = ""
    variant = 0
    smooth = False
    slowdowns = 0
    ref = build(factor, False)
    # the placements (3, or 4 with the smooth plan), then the slower replays (MAX_SLOWDOWNS in all)
    for _attempt in range(MAX_SLOWDOWNS + (1 if smooth_differs else 0)):
        try:
            knots, rec = encode(
                ref,
                scales,
                tolerance=float(tol),
                times_ms=times_ms,
                start_positions=start_positions,
                start_velocities_rpm=start_velocities_rpm,
                variant=variant,
                uniform_fallback=uniform_fallback,
                end_velocities_rpm=end_velocities_rpm,
            )
            info_out["time_scale"] = factor
            info_out["encode_variant"] = float(variant)
            if smooth_differs:
                info_out["smooth_plan"] = float(smooth)
            return ref, knots, rec
        except EncodingNeedsTime as e:
            where = f" on axis {axes[e.axis]!r}" if 0 <= e.axis < len(axes) else ""
            last = e.message + where
            if variant < 2:
                # other placements first: conservative on the same plan, then long segments (on the
                # same plan first where the smooth one differs: a path chain's few short segments are
                # often only too short for the default placement), then on the smooth plan
                variant += 1
                if variant == 1 or smooth_differs:
                    continue
            if not smooth:
                smooth = True
                ref = build(factor, True)
                continue
            if not retime:
                raise PlanningError(
                    INFEASIBLE, f"the drive cannot reproduce this timing: {last}", detail={"stage": "encode"}
                ) from None
            # small steps first (the least slow-down that passes), longer ones after every third: the
            # acceleration excess of a motion of a few counts is not monotone in the slow-down (measured:
            # 5.7 % of the limit at 1.0x, 8.3 % at 1.2x, 18.9 % at 1.21x, 5.1 % at 1.6x, none at 2.36x)
            slowdowns += 1
            factor *= max(e.factor, 1.05) ** (1 + (slowdowns - 1) // 3)
            ref = build(factor, True)
        except EncodingFailed as e:
            where = f" on axis {axes[e.axis]!r}" if 0 <= e.axis < len(axes) else ""
            if smooth_differs and not smooth and "int32" not in e.message:
                # a path's first plan: what one placement misses (a few knots too close together for
                # the quantisation), the next one or the smooth plan may not
                last = e.message + where
                if variant < 2:
                    variant += 1
                else:
                    smooth = True
                    ref = build(factor, True)
                continue
            code = ENCODING_RANGE if "int32" in e.message else INFEASIBLE
            raise PlanningError(code, f"{e.message}{where}", detail={"stage": "encode"}) from None
    raise PlanningError(
        INFEASIBLE,
        f"could not encode the motion within the limits even {factor:.2f}x slower: {last}",
        detail={"stage": "encode"},
    )


def reconstruction_jerk(knots: Knots, rec: Reconstruction) -> tuple[FloatArray, FloatArray]:
    """Per axis the largest |jerk| inside the drive's segments (each cubic's constant jerk, counts/ms^3)
    and the largest |step| of its acceleration at an interior knot (counts/ms^2)."""
    n = rec.acc_start.shape[0]
    if rec.acc_start.shape[1] == 0:
        return np.zeros(n), np.zeros(n)
    dt = np.diff(knots.times_ms).astype(np.float64)
    jerk = np.abs(rec.acc_end - rec.acc_start) / dt[None, :]
    steps = np.abs(rec.acc_start[:, 1:] - rec.acc_end[:, :-1])
    step_max = steps.max(axis=1) if steps.shape[1] else np.zeros(n)
    out: tuple[FloatArray, FloatArray] = (jerk.max(axis=1), step_max)
    return out


def planned_jerk(ref: Reference) -> FloatArray:
    """Per axis the plan's largest |jerk| (counts/ms^3): its change of acceleration over every ms, steps
    included (a step is a jerk over the tick)."""
    if ref.positions.shape[1] < 2:
        return np.zeros(ref.n_axes)
    over_ms = np.abs(ref.acc_left[:, 1:] - ref.acc_right[:, :-1])
    at_ms = np.abs(ref.acc_right - ref.acc_left)
    out: FloatArray = np.maximum(over_ms.max(axis=1), at_ms.max(axis=1))
    return out


def build_trajectory(
    kind: str,
    axes: Sequence[str],
    cfg: Sequence[AxisConfig],
    ref: Reference,
    knots: Knots,
    rec: Reconstruction,
    scales: AxisScales,
    tol: int,
    limits: dict[str, FloatArray],
    info: dict[str, float],
    open_end: CruiseState | None = None,
) -> PvtTrajectory:
    cpu = np.array([c.counts_per_unit for c in cfg])
    want = planned_demand(ref, scales.toward_zero)
    dev = np.abs(rec.demand - want).max(axis=1)
    dev_plan = np.abs(rec.demand - ref.positions).max(axis=1)
    excess = acceleration_excess(ref, knots, rec)
    peak_acc = np.maximum(np.abs(rec.acc_start), np.abs(rec.acc_end))
    env = ref.acc_envelope()
    conv = scales.counts_per_ms_per_rpm
    seg_jerk, knot_step = reconstruction_jerk(knots, rec)
    plan_jerk = planned_jerk(ref)
    stats = []
    for i, c in enumerate(cfg):
        vpk = float(np.abs(rec.velocity[i]).max())
        ex = max(float(excess[i].max()), 0.0) if excess.size else 0.0
        stats.append(
            AxisStats(
                name=c.name,
                node_id=c.node_id,
                max_deviation_counts=int(dev[i]),
                max_deviation_from_plan_counts=float(dev_plan[i]),
                peak_velocity=vpk * 1000.0 / cpu[i],
                peak_velocity_rpm=vpk / conv[i],
                velocity_limit=float(limits["velocity"][i]),
                drive_velocity_limit_rpm=float(c.max_profile_velocity_rpm),
                planned_peak_acceleration=float(env[i].max()) * 1.0e6 / cpu[i],
                peak_acceleration=(float(peak_acc[i].max()) if peak_acc.size else 0.0) * 1.0e6 / cpu[i],
                acceleration_limit=float(limits["acceleration"][i]),
                axis_acceleration_limit=float(limits["acceleration_axis"][i]),
                drive_acceleration_limit=float(c.max_acceleration),
                acceleration_excess=ex * 1.0e6 / cpu[i],
                acceleration_excess_share=ex / float(scales.acceleration_axis[i]),
                jerk_limit=float(limits["jerk"][i]),
                planned_peak_jerk=float(plan_jerk[i]) * 1.0e9 / cpu[i],
                peak_jerk=float(seg_jerk[i]) * 1.0e9 / cpu[i],
                knot_acceleration_step=float(knot_step[i]) * 1.0e6 / cpu[i],
            )
        )
    return PvtTrajectory(
        kind=kind,
        axis_names=tuple(axes),
        node_ids=tuple(c.node_id for c in cfg),
        dt_ms=np.diff(knots.times_ms),
        positions=knots.positions,
        velocities=knots.velocities_rpm,
        counts_per_unit=cpu,
        counts_per_rev=np.array([float(c.counts_per_rev) for c in cfg]),
        tolerance_counts=tol,
        plan=ref,
        stats=tuple(stats),
        info=dict(info),
        open_end=open_end,
    )


def _start_vector(start: Sequence[float], axes: Sequence[str]) -> FloatArray:
    a = np.asarray(start, dtype=np.float64)
    if a.shape != (len(axes),):
        raise PlanningError("AXIS_COUNT", f"start has {a.size} values for {len(axes)} axes", path="start")
    if not np.all(np.isfinite(a)):
        raise PlanningError("NONFINITE", "start contains NaN or infinity", path="start")
    return a


def _check_start(
    here: FloatArray, first: FloatArray, cpu: FloatArray, tol: int, axes: Sequence[str], name: str
) -> None:
    off = np.abs(np.round(here * cpu) - np.round(first * cpu))
    if np.any(off > tol):
        j = int(np.argmax(off))
        raise PlanningError(
            INFEASIBLE,
            f"{name}[{j}] of axis {axes[j]!r} is {first[j]:g} but the axis stands at "
            f"{here[j]:g} ({off[j]:.0f} counts away): the job must start where the "
            f"axes are",
            path=f"{name}[{j}]",
        )


def _check_within(x: FloatArray, cfg: Sequence[AxisConfig], axes: Sequence[str], name: str) -> None:
    for j, c in enumerate(cfg):
        if not c.position_min <= x[j] <= c.position_max:
            raise PlanningError(
                POSITION_LIMIT,
                f"{name}[{j}] of axis {axes[j]!r} is {x[j]:g}, outside the software "
                f"position limits [{c.position_min:g}, {c.position_max:g}]",
                path=f"{name}[{j}]",
            )


def _merge_close(wp: FloatArray, cpu: FloatArray) -> FloatArray:
    """Drop waypoints within half a count (every axis) of the previous kept one; keep the last waypoint.

    The drive cannot tell such waypoints apart, and a spline through near-duplicates swings wildly.
    """
    keep = [0]
    for i in range(1, wp.shape[0]):
        if np.any(np.abs(wp[i] - wp[keep[-1]]) * cpu >= 0.5):
            keep.append(i)
    if keep[-1] != wp.shape[0] - 1:
        if len(keep) > 1:
            keep[-1] = wp.shape[0] - 1  # the end is where the job says it is
        else:
            keep.append(wp.shape[0] - 1)
    out: FloatArray = wp[keep].copy()
    return out


def _check_duration_bound(travel: FloatArray, velocity: FloatArray) -> None:
    """No motion beats travel / velocity on any axis: refuse a job whose lower bound is already over the
    duration limit before planning it (a velocity_scale of 1e-300 would otherwise reach toppra)."""
    bound = float(np.max(travel / velocity))
    if not bound <= MAX_DURATION_S:
        raise PlanningError(TOO_LARGE, f"the motion takes at least {bound:.4g} s at the allowed velocities, more "
                                       f"than the limit of {MAX_DURATION_S:g} s", path="velocity_scale",
                            detail={"duration_s_lower_bound": bound})


def _check_reference_positions(ref: Reference, cfg: Sequence[AxisConfig], axes: Sequence[str]) -> None:
    """The planned motion must stay inside the software limits (a spline can swing out between its
    waypoints; the straight segments and their blends cannot). The error names the peak excursion: the
    farthest the motion goes beyond a limit, on the axis where that is largest (share of its travel)."""
    worst: tuple[float, int, int, float] | None = None  # (share beyond, axis, tick, value in user units)
    for j, c in enumerate(cfg):
        lo, hi = c.position_min * c.counts_per_unit, c.position_max * c.counts_per_unit
        row = ref.positions[j]
        beyond = np.maximum(lo - row, row - hi)
        k = int(np.argmax(beyond))
        if beyond[k] > 0.5:
            share = float(beyond[k]) / (hi - lo)
            if worst is None or share > worst[0]:
                worst = (share, j, k, float(row[k]) / c.counts_per_unit)
    if worst is None:
        return
    _share, j, k, value = worst
    c = cfg[j]
    row = ref.positions[j] / c.counts_per_unit
    low, high = float(row.min()), float(row.max())
    raise PlanningError(
        POSITION_LIMIT,
        f"the planned motion of axis {axes[j]!r} swings out to {value:.6g} at t = {k / 1000:.3f} s "
        f"(it spans [{low:.6g}, {high:.6g}]), outside the software position limits "
        f"[{c.position_min:g}, {c.position_max:g}]: the spline through the waypoints bulges there "
        f"(geometry = \"lines\", the default, keeps to the straight segments)",
        path="waypoints",
        detail={"axis": axes[j], "time_s": k / 1000.0, "peak": value, "min": low, "max": high},
    )


def lines_geometry(
    wp: FloatArray,
    cpu: FloatArray,
    vlim: FloatArray,
    alim: FloatArray,
    path_tolerance: FloatArray,
    tolerance_counts: int,
    segments: tuple[int, int],
    box: tuple[FloatArray, FloatArray],
    info: dict[str, float],
) -> tuple[list[PiecewisePath], ChainSpec]:
    """The straight segments with blended corners (planner/geometry.py) for a path job, and how the
    plan becomes a Hermite chain (planner/chain.py).

    What the encoding may add (the drive's rounded demand within `tolerance_counts` of the rounded
    plan, half a count of rounding, half a count of snapping the end points) is taken off the path
    tolerance first, so the drive itself stays within it; an axis whose tolerance does not exceed that
    is exact (its corners are stops). Of the rest, `BLEND_SHARE` goes to the blends and the remainder
    to the chain's deviation from the exact profile.
    """
    from planner.geometry import blended_runs
    from planner.path import ChainSpec

    margin = (tolerance_counts + 1.0) / cpu
    free = path_tolerance - margin
    runs, corners = blended_runs(
        wp, vlim, np.where(free > 0.0, BLEND_SHARE * free, free), alim, MIN_BLEND_SEGMENTS * segments[0]
    )
    info["blended_corners"] = float(sum(1 for c in corners if c.half_length > 0))
    info["exact_stops"] = float(sum(1 for c in corners if c.half_length < 0))
    # an exact axis only moves on straight runs, where the chain is exact: a tiny budget for the noise
    budget = np.where(free > 0.0, (1.0 - BLEND_SHARE) * free, 0.05 / cpu)
    # the chain stays inside the limits (half a count of the plan's rounding is allowed outside them)
    lower, upper = box[0] - 0.4 / cpu, box[1] + 0.4 / cpu
    return runs, ChainSpec(budget, segments[0], segments[1], lower, upper)


def line_deviation_counts(positions: FloatArray, start: FloatArray, end: FloatArray) -> float:
    """Largest distance (counts, on any axis) of `positions` (n, M+1) from the segment start -> end."""
    d = end - start
    dd = float(d @ d)
    if dd == 0.0:
        return float(np.abs(positions - start[:, None]).max())
    rel = positions - start[:, None]
    lam = np.clip((d @ rel) / dd, 0.0, 1.0)
    return float(np.abs(rel - d[:, None] * lam[None, :]).max())


# a cell and jobs small enough to plan in milliseconds that take every compiled kernel (warm_up)
_WARM_AXIS = {"node_id": 1, "counts_per_unit": 65189.86, "counts_per_rev": 8192, "velocity": 2.0,
              "acceleration": 8.0, "jerk": 80.0, "position_min": -3.0, "position_max": 3.0,
              "max_profile_velocity_rpm": 8000, "max_acceleration": 12.0}
_WARM_JOBS = (
    {"kind": "path", "axes": ["a", "b"], "waypoints": [[0.0, 0.0], [0.3, 0.1], [0.1, 0.4], [0.0, 0.0]]},
    {"kind": "path", "axes": ["a"], "waypoints": [[0.0], [0.2]]},
    {"kind": "move", "axes": ["a", "b"], "start": [0.0, 0.0], "target": [0.3, -0.2]},
    {"kind": "timed", "axes": ["a"], "times": [0.0, 0.4, 0.43, 0.8], "positions": [[0.0], [0.1], [0.104], [0.0]]},
)


def warm_up(progress: Callable[[int, int, str], None] | None = None) -> None:
    """Load the compiled kernels (planner/jit.py: compiled once per machine, a few seconds, then loaded from
    the cache in about a second) and import the solvers, by planning a few small jobs, and keep freed heap
    memory for the next plans (`jit.keep_heap`): e.g. when a service starts, so that the first job's
    planning time is the planning. `progress(done, total, what)`, when given, is called before each step
    and once at the end (done == total), e.g. to show a first run's compiling as it goes."""
    from planner.config import cell_from_dict
    from planner.jit import keep_heap
    from planner.job import job_from_dict

    keep_heap()

    cell = cell_from_dict({"cell": {"name": "warm-up"},
                           "axis": [{"name": "a", **_WARM_AXIS}, {"name": "b", **_WARM_AXIS, "node_id": 2}]})
    jobs: tuple[dict[str, Any], ...] = _WARM_JOBS
    total = len(jobs) + 1
    for k, job in enumerate(jobs):
        if progress is not None:
            progress(k, total, f"{job['kind']} job, {len(job['axes'])} axes")
        traj = plan_job(job_from_dict(job, cell), cell)
    if progress is not None:
        progress(total - 1, total, "the kernels a small plan does not reach")
    load_kernels(traj.plan)
    if progress is not None:
        progress(total, total, "done")
