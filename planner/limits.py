"""`AxisLimits`: the per-axis limits one motion is planned and checked with (user units, one entry per axis of
the job, in the job's axis order).

Who makes them: `planner.job.effective_limits` for a job (the cell's limits, the job's overrides and scales,
a move's seed 002 ramps), the stop planners (planner/motion/stop.py: the cell's limits, 0x607F as the
velocity bound a stop from full speed may briefly pass) and the cruise state of an endless move
(`CruiseState.limits`). Who reads them: the reference builders (velocity, acceleration, jerk; a move's two
ramps), `axis_scales` (the encoder's bounds, in counts per ms) and `build_trajectory` (what the measured
trajectory is compared with). A parameter object rather than a dict of seven keys: a misspelt limit is an
AttributeError at the line that misspells it, and mypy knows each field.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class AxisLimits:
    """Per-axis limits (user units/s, /s^2, /s^3). `velocity` and `acceleration` are the bounds the plan keeps
    and every check uses (scaled by the job's velocity and acceleration scales; `acceleration` is the larger
    of a move's two ramps); `acceleration_up` and `deceleration` are a move's ramps (speeding up, slowing
    down); `velocity_axis` and `acceleration_axis` are the axis' own limits before the job's scales, what "the
    axis limit" means in the encoding checks."""

    velocity: FloatArray
    acceleration: FloatArray
    jerk: FloatArray
    velocity_axis: FloatArray
    acceleration_axis: FloatArray
    acceleration_up: FloatArray
    deceleration: FloatArray

    @classmethod
    def of(cls, velocity: FloatArray, acceleration: FloatArray, jerk: FloatArray, *,
           velocity_axis: FloatArray | None = None, acceleration_axis: FloatArray | None = None) -> AxisLimits:
        """Limits with one acceleration for speeding up and slowing down, the axis' own limits the same as the
        plan's unless given."""
        v, a, j = np.asarray(velocity, float), np.asarray(acceleration, float), np.asarray(jerk, float)
        return cls(velocity=v, acceleration=a, jerk=j,
                   velocity_axis=v if velocity_axis is None else np.asarray(velocity_axis, float),
                   acceleration_axis=a if acceleration_axis is None else np.asarray(acceleration_axis, float),
                   acceleration_up=a, deceleration=a)

    def with_velocity(self, velocity: FloatArray) -> AxisLimits:
        """The same limits with another velocity bound (a stop, a ramp from a moving state: 0x607F)."""
        return dataclasses.replace(self, velocity=np.asarray(velocity, float))
