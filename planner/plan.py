"""plan_job: a validated `Job` on a cell -> `PvtTrajectory` (plan, encode, verify, measure).

Theory of operation. Each job kind has a reference builder (path.py along geometry.py's blended
segments or a spline; jerk.py's ruckig line for moves; timed.py for the user's timing) giving every
axis at every ms in counts; the encoder turns it into knots and proves the drive's reconstruction, on
which the trajectory's statistics are measured. Where quantisation needs more time, planned kinds are
played slower and encoded again; user timings are rejected instead. Start and end are snapped to whole
counts first: the drive stands on whole counts. A blended path gets its `path_tolerance` minus what the
encoding may add (`lines_geometry`). Errors are PlanningError with stable codes; no toppra, ruckig or
numpy exception escapes.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from planner.config import AxisConfig, CellConfig
from planner.encoding.cyclic import with_cyclic_stats
from planner.encoding.encoder import ACC_EXCESS_LIMIT, load_kernels, segment_bounds
from planner.encoding.reconstruction import AxisScales, Knots, Reconstruction, reconstruct
from planner.errors import INFEASIBLE, LIMITS, POSITION_LIMIT, SCHEMA, TOO_LARGE, PlanningError
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
from planner.motion.reference import FloatArray, Reference
from planner.pipeline import axis_configs, axis_scales, build_trajectory, encode_with_retries
from planner.trajectory import PvtTrajectory

if TYPE_CHECKING:
    from planner.motion.geometry import PiecewisePath
    from planner.motion.path import ChainSpec

TINY_PATH_COUNTS = 1.0  # a path whose every axis spans less than this is planned as a straight move
MIN_BLEND_SEGMENTS = 3.0  # a blend shorter than this many shortest segments is an exact stop (geometry)
BLEND_SHARE = 0.8  # of the free path tolerance: the blends; the rest, the chain (lines_geometry)
MIN_SWITCH_PIECE_MS = 10  # shorter profile pieces between two switches are merged (see path.Profile)


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
    `last_direction` serve the additive and modulo_current modes (planner/motion/travel.py). A velocity move is
    planned open-ended from rest there (`travel.plan_velocity`, which also takes a moving start).
    `max_segment_ms` bounds the PVT segments (a job with a short lead: `StreamerSettings.segment_cap_ms`).
    """
    d0 = job.data
    if isinstance(d0, MoveData) and d0.mode == "velocity":
        from planner.motion.travel import MotionState, plan_velocity

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
        _check_duration_bound(np.abs(np.diff(wp, axis=0)).sum(axis=0), limits.velocity)
        extent = (wp.max(axis=0) - wp.min(axis=0)) * cpu
        if wp.shape[0] < 2 or float(extent.max()) < TINY_PATH_COUNTS:
            first, last = wp[0], wp[-1]

            def build(f: float, smooth: bool = False) -> Reference:
                from planner.motion.jerk import move_reference

                return move_reference(
                    first,
                    last,
                    limits.velocity,
                    limits.acceleration,
                    limits.jerk,
                    cpu,
                    time_scale=f,
                    max_duration_s=MAX_DURATION_S,
                )
        else:
            runs = None
            chain = None
            jerk = jerk_limited(job, cell)
            fastest = d.jerk_timing == "fastest"
            if fastest and not jerk:
                raise PlanningError(SCHEMA, "jerk_timing applies to a jerk-limited path, and this one is not "
                                    "(set jerk_limited = true)", path="jerk_timing")
            box = (np.array([c.position_min for c in cfg]), np.array([c.position_max for c in cfg]))
            if d.geometry == "lines":
                from planner.motion.jerkpath import PLAN_JERK_SHARE

                runs, chain = lines_geometry(
                    wp,
                    cpu,
                    limits.velocity,
                    limits.acceleration,
                    path_tolerance(job, cell),
                    tol,
                    segment_bounds(scales, tol),
                    box,
                    info,
                    jerk=limits.jerk * PLAN_JERK_SHARE if jerk else None,
                )

            if jerk:
                info["jerk_limited"] = 1.0
            smooth_differs = not jerk  # a jerk-limited plan has no smoother variant

            def build(f: float, smooth: bool = False) -> Reference:
                from planner.motion.path import SplineGeometry, plan_path

                if jerk:
                    from planner.motion.jerkpath import plan_jerk_path

                    ref, path_info = plan_jerk_path(
                        runs if runs is not None else [SplineGeometry(wp, limits.velocity, shape[0])],
                        cpu,
                        limits.velocity,
                        limits.acceleration,
                        limits.jerk,
                        time_scale=f,
                        max_duration_s=MAX_DURATION_S,
                        fastest=fastest,
                    )
                    info.update(path_info)
                    info["jerk_stops"] = 0.0
                    if runs is not None:
                        # along the segments: jerk-limited moves from waypoint to waypoint, each stop at a
                        # corner cut short within the tolerance where that is faster (the tolerance less
                        # what the encoding may add, as for the blends); where faster than the blends
                        from planner.motion.stop_moves import stop_moves

                        moves_info: dict[str, float] = {}
                        free = np.maximum(path_tolerance(job, cell) - encoding_margin(tol, cpu), 0.0)
                        moves = stop_moves(wp, cpu, limits.velocity, limits.acceleration, limits.jerk,
                                           tolerance=free, box=box, time_scale=f,
                                           max_duration_s=MAX_DURATION_S, info=moves_info)
                        if moves.duration_ms < ref.duration_ms:
                            info["jerk_stops"] = 1.0
                            info.update(moves_info)
                            return moves
                    return ref
                # the smooth retry (the encoder failed on short pieces): a chain without short segments
                spec = None if chain is None else dataclasses.replace(chain, short=not smooth)
                ref, path_info = plan_path(
                    runs if runs is not None else [SplineGeometry(wp, limits.velocity, shape[0])],
                    cpu,
                    limits.velocity,
                    limits.acceleration,
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
        else:  # additive, modulo: what the target means (planner/motion/travel.py)
            from planner.motion.travel import resolve_target

            target = resolve_target(job, cell, origin, last_target, last_direction=last_direction)
        _check_within(target, cfg, job.axes, "target")
        a, b = snap(origin, cpu), snap(target, cpu)
        _check_duration_bound(np.abs(b - a), limits.velocity)

        def build(f: float, smooth: bool = False) -> Reference:
            from planner.motion.jerk import move_reference

            return move_reference(
                a,
                b,
                limits.velocity,
                limits.acceleration_up,
                limits.jerk,
                cpu,
                time_scale=f,
                max_duration_s=MAX_DURATION_S,
                info=info,
                dlim=limits.deceleration if d.ramps is not None else None,
            )
    elif isinstance(d, TimedData):
        pos = np.array(d.positions, dtype=np.float64)
        if here is not None:
            _check_start(here, pos[0], cpu, tol, job.axes, "positions[0]")
            pos[0] = here
        pos[0], pos[-1] = snap(pos[0], cpu), snap(pos[-1], cpu)
        times = np.array(d.times)

        def build(f: float, smooth: bool = False) -> Reference:
            from planner.motion.timed import check_user_timing, timed_reference

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
        from planner.motion.timed import check_user_timing, pvt_reference

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
        # the knot values re-chosen so that the drive's acceleration stays continuous (planner/encoding/continuity.py)
        jerk_counts = limits.jerk * cpu / 1.0e9
        knots, rec = _smoothest(ref, knots, rec, scales, float(tol), jerk_counts, info)
    traj = build_trajectory(job.kind, job.axes, cfg, ref, knots, rec, scales, tol, limits, info)
    # axes whose drives take one set point per SYNC: their own interpolation must follow within tolerance
    return with_cyclic_stats(traj, cfg, cell.sync_period_ms, cell.axes)


def _smoothest(
    ref: Reference, knots: Knots, rec: Reconstruction, scales: AxisScales, tol: float, jerk: FloatArray,
    info: dict[str, float],
) -> tuple[Knots, Reconstruction]:
    """A jerk-limited plan's knots: of the encoder's placements (its default, conservative and long ones,
    `encoder.encode` variants 0-2), each with its values re-chosen for a continuous acceleration
    (continuity.smooth_values), the one whose drive keeps the jerk bound best (`worst_ratio`), its knot
    times then moved where that lowers the worst knot further (continuity.refine_times). Which placement
    wins depends on where short segments fall beside long ones: a knot between 20 and 135 ms moves its
    step by 6/T^2 per count of the short one's neighbour. `info["jerk_placement"]`: the variant (`knots` are
    the encoding's, of its `info["encode_variant"]`)."""
    from planner.encoding.continuity import refine_times, smooth_values, worst_ratio
    from planner.encoding.encoder import EncodingFailed, EncodingNeedsTime, encode

    best = smooth_values(ref, knots, scales, tol, jerk)
    score = worst_ratio(best, scales, jerk)
    first = int(info.get("encode_variant", 0.0))  # the placement the encoding took (the default, or one after)
    info["jerk_placement"] = float(first)
    for variant in (0, 1, 2):
        if score <= 1.0:
            break
        if variant == first:
            continue
        try:
            other, _rec = encode(ref, scales, tolerance=tol, variant=variant, uniform_fallback=True,
                                 start_positions=knots.positions[:, 0].copy(),
                                 start_velocities_rpm=knots.velocities_rpm[:, 0].copy())
        except (EncodingNeedsTime, EncodingFailed):
            continue
        other = smooth_values(ref, other, scales, tol, jerk)
        other_score = worst_ratio(other, scales, jerk)
        if other_score < score:
            best, score, info["jerk_placement"] = other, other_score, float(variant)
    best = refine_times(ref, best, scales, tol, jerk)
    if best is knots:
        return knots, rec
    return best, reconstruct(best, scales)


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


def encoding_margin(tolerance_counts: int, cpu: FloatArray) -> FloatArray:
    """What the encoding may add to a path's deviation (user units per axis): the drive's rounded demand within
    `tolerance_counts` of the rounded plan, half a count of rounding, half a count of snapping the end points."""
    return (tolerance_counts + 1.0) / cpu


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
    *,
    jerk: FloatArray | None = None,
) -> tuple[list[PiecewisePath], ChainSpec]:
    """The straight segments with blended corners (planner/motion/geometry.py) for a path job, and how the
    plan becomes a Hermite chain (planner/encoding/chain.py).

    What the encoding may add (the drive's rounded demand within `tolerance_counts` of the rounded
    plan, half a count of rounding, half a count of snapping the end points) is taken off the path
    tolerance first, so the drive itself stays within it; an axis whose tolerance does not exceed that
    is exact (its corners are stops). Of the rest, `BLEND_SHARE` goes to the blends and the remainder
    to the chain's deviation from the exact profile. With `jerk` (a jerk-limited plan: the jerk each
    joint may use), the blends are shaped for their constant-speed crossing (geometry.corner_blends).
    That plan has no chain, but giving the blends its share too made them meet on short segments, where
    one speed holds for both, and the plan slower (docs/formats.md, "jerk_limited").
    """
    from planner.motion.geometry import blended_runs
    from planner.motion.path import ChainSpec

    free = path_tolerance - encoding_margin(tolerance_counts, cpu)
    runs, corners = blended_runs(
        wp, vlim, np.where(free > 0.0, BLEND_SHARE * free, free), alim, MIN_BLEND_SEGMENTS * segments[0], jerk
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
    {"kind": "path", "axes": ["a", "b"], "waypoints": [[0.0, 0.0], [0.3, 0.1], [0.1, 0.4], [0.0, 0.0]],
     "jerk_limited": False},
    {"kind": "path", "axes": ["a"], "waypoints": [[0.0], [0.2]], "jerk_limited": False},
    {"kind": "path", "axes": ["a", "b"], "waypoints": [[0.0, 0.0], [0.3, 0.1], [0.1, 0.4]], "jerk_limited": True},
    {"kind": "path", "axes": ["a", "b"], "waypoints": [[0.0, 0.0], [0.3, 0.1], [0.1, 0.4]], "jerk_limited": True,
     "geometry": "spline"},
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


def compile_all(out: Callable[[str], None] = print) -> int:
    """Compile (or load) every kernel the planner's plans take, reporting each compiled one with its count and
    the time so far (`python -m planner.plan`; `make test` runs it first). Returns how many were compiled."""
    import importlib
    import pkgutil
    from pathlib import Path

    from planner.jit import KERNELS, compiling

    for info in pkgutil.walk_packages([str(Path(__file__).parent)], prefix="planner."):  # every kernel registered
        importlib.import_module(info.name)
    t0, seen = time.monotonic(), set[str]()

    def done(name: str) -> None:
        seen.add(name)
        out(f"  compiled {len(seen):>2} of {len(KERNELS)} kernels after {time.monotonic() - t0:4.0f} s: {name}")

    with compiling(done):
        warm_up()
    took = time.monotonic() - t0
    if seen:
        out(f"  the planner's kernels: {len(seen)} of {len(KERNELS)} compiled (any other loaded from the cache or "
            f"compiled when a plan first needs it), in {took:.0f} s")
    else:
        out(f"  the planner's kernels: every one loaded from the cache, in {took:.1f} s")
    return len(seen)


if __name__ == "__main__":
    print("compiling the planner's kernels (once per machine; cached for every later process)",
          flush=True)
    from planner.plan import compile_all as _compile_all  # this file runs as __main__: the kernels are planner's

    _compile_all(lambda line: print(line, flush=True))
