"""`AxisLimits`: the per-axis limits one motion is planned and checked with (user units, in job axis order).

Made by `planner.job.effective_limits` (cell limits, the job's overrides, scales and ramps), the stop
planners and a cruise's `CruiseState.limits`; read by the reference builders, `axis_scales` and
`build_trajectory`. A parameter object, not a dict: a misspelt limit fails where it is misspelt.
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
