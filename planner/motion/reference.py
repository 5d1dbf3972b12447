"""The planned motion of every axis, sampled at every millisecond in drive units (the encoder's input).

Theory of operation. Every planner ends in a `Reference`: positions in counts (unrounded), velocities in
counts/ms, accelerations in counts/ms^2, at every integer ms 0..M. The drive interpolates at 1 ms ticks
and the encoder checks exactly those ticks, so 1 kHz samples are all it needs. Accelerations are kept on
both sides of every tick (`acc_left`, `acc_right`): planners put acceleration steps on whole ms (`breaks`)
since a Hermite segment can only follow a step at a knot. `hints` are the plan's own structure (ruckig
phase boundaries, a job's rows), where the encoder starts placing knots.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def _readonly(a: NDArray[np.generic]) -> NDArray[np.generic]:
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Reference:
    """Planned positions (counts), velocities (counts/ms), accelerations (counts/ms^2) at every ms."""

    positions: FloatArray  # (n_axes, M+1)
    velocities: FloatArray  # (n_axes, M+1)
    acc_left: FloatArray  # (n_axes, M+1): acceleration on (m-1, m); [:, 0] repeats acc_right[:, 0]
    acc_right: FloatArray  # (n_axes, M+1): acceleration on (m, m+1); [:, M] repeats acc_left[:, M]
    breaks: IntArray  # ms in 1..M-1 where the acceleration may jump (sorted, unique)
    hints: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # ms in 1..M-1

    def __post_init__(self) -> None:
        p = np.ascontiguousarray(self.positions, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] < 1:
            raise ValueError(f"reference positions must be (n_axes, M+1), got shape {p.shape}")
        for name in ("positions", "velocities", "acc_left", "acc_right"):
            a = np.ascontiguousarray(getattr(self, name), dtype=np.float64)
            if a.shape != p.shape:
                raise ValueError(f"reference {name} has shape {a.shape}, expected {p.shape}")
            if not np.all(np.isfinite(a)):
                raise ValueError(f"reference {name} is not finite")
            object.__setattr__(self, name, _readonly(a))
        for name in ("breaks", "hints"):
            b = np.unique(np.asarray(getattr(self, name), dtype=np.int64))
            b = b[(b > 0) & (b < p.shape[1] - 1)]
            object.__setattr__(self, name, _readonly(b))

    @property
    def n_axes(self) -> int:
        return int(self.positions.shape[0])

    @property
    def duration_ms(self) -> int:
        return int(self.positions.shape[1] - 1)

    def axes_subset(self, axes: IntArray) -> Reference:
        """The same plan on some of its axes only (rows `axes`; already validated, so not again)."""
        out = object.__new__(Reference)
        for name in ("positions", "velocities", "acc_left", "acc_right"):
            object.__setattr__(out, name, _readonly(getattr(self, name)[axes]))
        object.__setattr__(out, "breaks", self.breaks)
        object.__setattr__(out, "hints", self.hints)
        return out

    def acc_envelope(self) -> FloatArray:
        """max(|acc_left|, |acc_right|) at every ms: the planned acceleration magnitude there (read-only:
        computed once, several stages ask for it)."""
        return self._envelope

    @functools.cached_property
    def _envelope(self) -> FloatArray:
        out: FloatArray = _readonly(np.maximum(np.abs(self.acc_left), np.abs(self.acc_right)))  # type: ignore[assignment]
        return out

    def at(self, t_ms: FloatArray) -> FloatArray:
        """Positions (counts) at arbitrary times (ms), (n_axes, len(t)): cubic Hermite between samples.

        Between two 1 ms samples the planned motion is smooth, so this is exact to well below a count.
        Times outside [0, M] are clamped (the motion is at rest before and after).
        """
        t = np.clip(np.asarray(t_ms, dtype=np.float64), 0.0, float(self.duration_ms))
        if self.duration_ms == 0:
            return np.repeat(self.positions[:, :1], t.size, axis=1)
        k = np.minimum(np.floor(t).astype(np.int64), self.duration_ms - 1)
        s = t - k
        h00 = (1 + 2 * s) * (1 - s) ** 2
        h10 = s * (1 - s) ** 2
        h01 = s * s * (3 - 2 * s)
        h11 = s * s * (s - 1)
        p, v = self.positions, self.velocities
        out: FloatArray = p[:, k] * h00 + v[:, k] * h10 + p[:, k + 1] * h01 + v[:, k + 1] * h11
        return out


def hold(positions_counts: FloatArray, duration_ms: int = 1) -> Reference:
    """A reference that stands still at `positions_counts` for `duration_ms` (a valid no-op motion)."""
    p = np.repeat(np.asarray(positions_counts, dtype=np.float64)[:, None], duration_ms + 1, axis=1)
    z = np.zeros_like(p)
    return Reference(p, z, z, z, np.zeros(0, dtype=np.int64))
