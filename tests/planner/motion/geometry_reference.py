"""The blended geometry's NumPy formulation (planner/motion/geometry.py at 60b5382, before its loops were compiled): the
reference the kernels are compared with (tests/planner/motion/test_geometry.py). Kept only as that reference."""

from __future__ import annotations

import numpy as np

from planner.motion.geometry import (
    _CHUNK,
    _F1,
    _F2,
    _FS,
    _G1,
    _G2,
    _GS,
    _P1,
    _P2,
    _T,
    REVERSAL_COS,
    RHOS,
    _shape_coefficients,
)
from planner.motion.reference import FloatArray


def blend_duration_ms(
    u1: FloatArray, u2: FloatArray, half_length: FloatArray, rho: FloatArray, vlim: FloatArray, alim: FloatArray
) -> FloatArray:
    """A lower bound of the time each blend takes (ms): along it, no faster than its curvature lets
    every joint's centripetal acceleration stay within its limit (and never above full speed).

    A blend much shorter in time than the encoder's shortest segment swings the joints' accelerations
    faster than any sequence of drive segments can follow within one count; planner.plan makes those
    corners exact stops (`MIN_BLEND_SEGMENTS`).
    """
    out = np.zeros(half_length.size)
    for lo in range(0, half_length.size, _CHUNK):
        sl = slice(lo, min(lo + _CHUNK, half_length.size))
        f, g = _shape_coefficients(np.where(rho[sl] > 0, rho[sl], RHOS[-1]))
        ell = half_length[sl][:, None, None]
        b1 = ell * ((f @ _P1.T)[:, :, None] * u1[sl][:, None, :] + (g @ _P1.T)[:, :, None] * u2[sl][:, None, :])
        b2 = ell * ((f @ _P2.T)[:, :, None] * u1[sl][:, None, :] + (g @ _P2.T)[:, :, None] * u2[sl][:, None, :])
        speed = np.linalg.norm(b1, axis=2)  # |dz/dt| of the Bezier parameter
        tangent = b1 / np.maximum(speed, 1e-300)[:, :, None]
        normal = b2 - np.einsum("ctk,ctk->ct", b2, tangent)[:, :, None] * tangent
        curv = normal / np.maximum(speed, 1e-150)[:, :, None] ** 2  # curvature vector in z (per z unit)
        # joint j: vlim_j * curv_j * zeta^2 <= alim_j, zeta in z units per s (at most 1: full speed)
        need = (np.abs(curv) * (vlim / alim)[None, None, :]).max(axis=2)
        zeta = np.minimum(1.0, 1.0 / np.sqrt(np.maximum(need, 1e-300)))
        out[sl] = 1000.0 * np.trapezoid(speed / zeta, _T, axis=1)
    return out


def _size(
    cos: FloatArray, a11: FloatArray, a12: FloatArray, a22: FloatArray, half: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Half-length l, shape rho and scaled deviation of the blends of a chunk of corners."""
    fs, gs = _FS[None], _GS[None]  # (1, R, T)
    b11, b12, b22 = a11[:, None, None], a12[:, None, None], a22[:, None, None]
    # y-offset of the blend point from c is p = f Y1 + g Y2 (l = 1)
    pp = fs * fs * b11 + 2.0 * fs * gs * b12 + gs * gs * b22
    dist_c = np.sqrt(np.maximum(pp, 0.0)).min(axis=2)  # closest approach to the corner
    # distance to leg 1 {-lam Y1} and leg 2 {lam Y2}, lam in [0, 1]
    p_y1 = fs * b11 + gs * b12
    lam1 = np.clip(-p_y1 / np.maximum(b11, 1e-300), 0.0, 1.0)
    d1 = pp + 2.0 * lam1 * p_y1 + lam1 * lam1 * b11
    p_y2 = fs * b12 + gs * b22
    lam2 = np.clip(p_y2 / np.maximum(b22, 1e-300), 0.0, 1.0)
    d2 = pp - 2.0 * lam2 * p_y2 + lam2 * lam2 * b22
    dist_legs = np.sqrt(np.maximum(np.minimum(d1, d2), 0.0)).max(axis=2)
    dev1 = np.maximum(dist_c, dist_legs)  # (C, R) at l = 1
    length = np.minimum(1.0 / np.maximum(dev1, 1e-300), half[:, None])
    # curvature in z (u1, u2 unit, u1.u2 = cos): kappa = |f'g'' - g'f''| sin / |B'|^3
    c = cos[:, None, None]
    sin = np.sqrt(np.maximum(1.0 - cos * cos, 0.0))[:, None, None]
    speed2 = _F1[None] ** 2 + 2.0 * _F1[None] * _G1[None] * c + _G1[None] ** 2
    cross = np.abs(_F1 * _G2 - _G1 * _F2)[None] * sin
    with np.errstate(divide="ignore", invalid="ignore"):
        kappa = np.where(speed2 > 1e-24, cross / np.maximum(speed2, 1e-300) ** 1.5, np.inf)
    kmax = kappa.max(axis=2)  # at l = 1
    radius = np.where(np.isfinite(kmax) & (kmax > 0), length / np.where(kmax > 0, kmax, 1.0), 0.0)
    best = np.argmax(radius, axis=1)
    reversal = cos <= REVERSAL_COS
    # a reversal turns back along the same line whatever the shape: take the middle one
    best = np.where(reversal, RHOS.size - 1, best)
    rows = np.arange(cos.size)
    hl = length[rows, best]
    return hl, RHOS[best], dev1[rows, best] * hl
