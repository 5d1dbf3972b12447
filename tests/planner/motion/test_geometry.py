"""planner/motion/geometry.py's compiled loops against the formulations they replaced: the blends' sizes and shapes
(to the bit), the time a blend takes at least (to 1e-12: the kernel sums the trapezoids in order, NumPy
pairwise), and the path's values and derivatives (scipy's PPoly, to the bit), on random corners of 1-8
axes, reversals and near-straight corners included."""

from __future__ import annotations

import geometry_reference as numpy_ref
import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from scipy.interpolate import PPoly

from planner.motion import geometry


def _corners(rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    n = int(rng.integers(1, 9))
    k = int(rng.integers(1, 12))
    u1 = rng.normal(size=(k, n))
    u2 = rng.normal(size=(k, n))
    kind = rng.random(k)
    u2[kind < 0.15] = -u1[kind < 0.15]  # reversals
    u2[(kind >= 0.15) & (kind < 0.25)] = u1[(kind >= 0.15) & (kind < 0.25)] + 1e-7  # nearly straight on
    u1 /= np.linalg.norm(u1, axis=1)[:, None]
    u2 /= np.linalg.norm(u2, axis=1)[:, None]
    scale = rng.uniform(0.1, 10.0, n)
    y1, y2 = u1 * scale, u2 * scale
    cos = np.clip(np.einsum("ij,ij->i", u1, u2), -1.0, 1.0)
    return (cos, np.einsum("ij,ij->i", y1, y1), np.einsum("ij,ij->i", y1, y2), np.einsum("ij,ij->i", y2, y2),
            rng.uniform(0.001, 2.0, k), u1, u2)


@given(st.integers(0, 2**32 - 1))
def test_blend_sizes_and_durations_are_the_numpy_ones(seed: int) -> None:
    rng = np.random.default_rng(seed)
    cos, a11, a12, a22, half, u1, u2 = _corners(rng)
    hl, rho, dev = geometry._size(cos, a11, a12, a22, half)
    hl_ref, rho_ref, dev_ref = numpy_ref._size(cos, a11, a12, a22, half)
    assert np.array_equal(hl, hl_ref) and np.array_equal(rho, rho_ref) and np.array_equal(dev, dev_ref)
    n = u1.shape[1]
    vlim, alim = rng.uniform(0.5, 3.0, n), rng.uniform(1.0, 20.0, n)
    rho = np.where(rng.random(rho.size) < 0.2, 0.0, rho)  # an exact stop's shape: the default one
    got = geometry.blend_duration_ms(u1, u2, hl, rho, vlim, alim)
    want = numpy_ref.blend_duration_ms(u1, u2, hl, rho, vlim, alim)
    assert np.allclose(got, want, rtol=1e-12, atol=0.0)


@given(st.integers(0, 2**32 - 1))
def test_the_path_and_its_derivatives_are_scipys(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n, pieces = int(rng.integers(1, 7)), int(rng.integers(1, 9))
    breaks = np.concatenate([[0.0], np.cumsum(rng.uniform(0.01, 0.5, pieces))])
    coefficients = rng.normal(size=(6, pieces, n))
    path = geometry.PiecewisePath(breaks, coefficients, np.zeros(pieces, dtype=np.int64), n)
    s = np.concatenate([rng.uniform(-0.1, breaks[-1] + 0.1, 50), breaks])
    spline = PPoly(coefficients, breaks)
    for order in range(3):
        assert np.array_equal(path(s, order), spline.derivative(order)(np.clip(s, 0.0, breaks[-1])))
    ordered = np.sort(np.clip(s, 0.0, breaks[-1]))
    sd = rng.uniform(0.0, 2.0, ordered.size)
    q, v, q1, curved = path.trace(ordered, sd)
    assert np.array_equal(q, path(ordered, 0)) and np.array_equal(q1, path(ordered, 1))
    assert np.array_equal(v, q1 * sd[:, None]) and not curved.any()
