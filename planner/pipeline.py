"""The stages every planner shares after its reference: axes and wire scales, encoding, measurement.

Theory of operation. A planner (plan.py, travel.py, stop.py) builds a `Reference` in counts;
`encode_with_retries` turns it into knots (other placements, then slower replays of a planned motion);
`build_trajectory` measures the reconstruction against the plan and the limits. This module imports no
planner of a job kind, so each of them can import it without a cycle. Errors are PlanningError.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from planner.config import AxisConfig, CellConfig
from planner.encoding.encoder import EncodingFailed, EncodingNeedsTime, encode
from planner.encoding.reconstruction import AxisScales, Knots, Reconstruction, acceleration_excess, planned_demand
from planner.errors import ENCODING_RANGE, INFEASIBLE, PlanningError
from planner.limits import AxisLimits
from planner.motion.reference import FloatArray, IntArray, Reference
from planner.trajectory import AxisStats, CruiseState, PvtTrajectory

# attempts at encoding a planned motion: the placements (3, or 4 with a path's smooth plan), then slower
# replays (`encode_with_retries`). Measured on 2700 random paths of 2-200 counts between waypoints
# (benchmarks/bench_planner.py's path-small corpus): with 6, 5.5 % of them were refused (1.46x slower at
# most); with 15 and the growing steps, none
MAX_SLOWDOWNS = 15

def axis_configs(axes: Sequence[str], cell: CellConfig) -> list[AxisConfig]:
    return [cell.axis(a) for a in axes]


def axis_scales(
    cfg: Sequence[AxisConfig], limits: AxisLimits, max_segment_ms: int | None = None
) -> AxisScales:
    cpu = np.array([c.counts_per_unit for c in cfg])
    return AxisScales(
        counts_per_ms_per_rpm=np.array([c.counts_per_rev / 60000.0 for c in cfg]),
        velocity_limit=limits.velocity * cpu / 1000.0,
        acceleration_limit=limits.acceleration * cpu / 1.0e6,
        acceleration_axis=limits.acceleration_axis * cpu / 1.0e6,
        drive_velocity=np.array([c.max_profile_velocity for c in cfg]) * cpu / 1000.0,
        drive_acceleration=np.array([c.max_acceleration for c in cfg]) * cpu / 1.0e6,
        # the drive's rounding of its demand where `pvt probe` found it truncates (else to nearest)
        toward_zero=np.array([c.probed.rounding == "toward_zero" for c in cfg]),
        max_segment_ms=max_segment_ms,
    )


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
    limits: AxisLimits,
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
                velocity_limit=float(limits.velocity[i]),
                drive_velocity_limit_rpm=float(c.max_profile_velocity_rpm),
                planned_peak_acceleration=float(env[i].max()) * 1.0e6 / cpu[i],
                peak_acceleration=(float(peak_acc[i].max()) if peak_acc.size else 0.0) * 1.0e6 / cpu[i],
                acceleration_limit=float(limits.acceleration[i]),
                axis_acceleration_limit=float(limits.acceleration_axis[i]),
                drive_acceleration_limit=float(c.max_acceleration),
                acceleration_excess=ex * 1.0e6 / cpu[i],
                acceleration_excess_share=ex / float(scales.acceleration_axis[i]),
                jerk_limit=float(limits.jerk[i]),
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
