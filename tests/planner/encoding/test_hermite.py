"""The drive's interpolation (seed 000, 4.2.3) against a hand-computed example."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from planner.encoding import hermite


def test_seed_coefficients_two_point_example() -> None:
    # Two PVT points: from (P[n-1], V[n-1]) = (1000 counts, 2 counts/ms) to (P[n], V[n]) = (1100, 3) in
    # T = 40 ms. By hand, with dP = 100:
    #   d = P[n] = 1100,  c = V[n] = 3
    #   b = T^-2 (-3 dP + T (2 V[n] + V[n-1])) = (-300 + 40 * 8) / 1600 = 20 / 1600 = 0.0125
    #   a = T^-3 (-2 dP + T (V[n] + V[n-1])) = (-200 + 40 * 5) / 64000 = 0
    # The seed's extracted text prints b = T^-2 (3 dP + T (V[n] + 2 V[n-1])) = (300 + 280) / 1600 = 0.3625
    # and a = T^-3 (2 dP + T (V[n] + V[n-1])) = 400 / 64000 = 0.00625: with tau = t - t0 in [-T, 0]
    # that polynomial gives P(-T) = -400 + 580 - 120 + 1100 = 1160, not P[n-1] = 1000 (the minus signs
    # were lost when the PDF became text; see planner/encoding/hermite.py). The corrected form is the unique
    # cubic through both points with both velocities, which is what the seed defines in words.
    a, b, c, d = hermite.coefficients(1000, 2.0, 1100, 3.0, 40)
    assert (a, b, c, d) == pytest.approx((0.0, 0.0125, 3.0, 1100.0))
    seed_text_b = (3 * 100 + 40 * (3.0 + 2 * 2.0)) / 40**2
    seed_text_a = (2 * 100 + 40 * (3.0 + 2.0)) / 40**3
    p_text = seed_text_a * (-40) ** 3 + seed_text_b * (-40) ** 2 + 3.0 * (-40) + 1100
    assert p_text == pytest.approx(1160.0)  # the literal text misses P[n-1]
    # interpolation conditions of the corrected polynomial
    p0, v0, _ = hermite.evaluate((a, b, c, d), -40.0)
    p1, v1, _ = hermite.evaluate((a, b, c, d), 0.0)
    assert (p0, v0, p1, v1) == pytest.approx((1000.0, 2.0, 1100.0, 3.0))
    # a = 0 here: the motion is a parabola, constant acceleration 2b = 0.025 counts/ms^2
    assert hermite.evaluate((a, b, c, d), -17.0)[2] == pytest.approx(0.025)
    # the drive's demand at every ms: P(k - T) rounded half away from zero
    demand = hermite.segment_demand(1000, 2.0, 1100, 3.0, 40)
    expect = [hermite.round_counts(1100 + 3.0 * (k - 40) + 0.0125 * (k - 40) ** 2) for k in range(1, 41)]
    assert demand == expect
    assert demand[-1] == 1100


def test_second_example_with_cubic_term() -> None:
    # (0, 0) -> (10, 0) in T = 10 ms: the smoothstep. a = -2*10/1000 = -0.02, b = -3*10/100 = -0.3
    a, b, c, d = hermite.coefficients(0, 0.0, 10, 0.0, 10)
    assert (a, b, c, d) == pytest.approx((-0.02, -0.3, 0.0, 10.0))
    assert hermite.evaluate((a, b, c, d), -5.0)[0] == pytest.approx(5.0)  # symmetric: half way at half time
    assert hermite.evaluate((a, b, c, d), -10.0)[2] == pytest.approx(0.6)  # 6 dP / T^2 at the start
    assert hermite.round_counts(-2.5) == -3 and hermite.round_counts(2.5) == 3  # half away from zero


@given(
    p0=st.integers(-(2**31), 2**31 - 1),
    p1=st.integers(-(2**31), 2**31 - 1),
    v0=st.floats(-500, 500),
    v1=st.floats(-500, 500),
    t=st.integers(1, 255),
)
def test_interpolation_conditions(p0: int, p1: int, v0: float, v1: float, t: int) -> None:
    coeffs = hermite.coefficients(p0, v0, p1, v1, t)
    pa, va, _ = hermite.evaluate(coeffs, -float(t))
    pb, vb, _ = hermite.evaluate(coeffs, 0.0)
    scale = max(1.0, abs(p0), abs(p1))
    assert pa == pytest.approx(p0, abs=1e-6 * scale) and pb == pytest.approx(p1, abs=1e-6 * scale)
    assert va == pytest.approx(v0, abs=1e-6 * scale / t) and vb == pytest.approx(v1, abs=1e-6 * scale / t)


@given(
    st.lists(
        st.tuples(st.integers(-(10**6), 10**6), st.floats(-50, 50), st.integers(1, 255)),
        min_size=1,
        max_size=8,
    )
)
def test_reconstruct_matches_segment_demand(rows: list[tuple[int, float, int]]) -> None:
    p = np.array([0] + [r[0] for r in rows], dtype=np.float64)
    v = np.array([0.0] + [r[1] for r in rows])
    dt = np.array([r[2] for r in rows], dtype=np.int64)
    pos, _vel, _acc = hermite.reconstruct(p, v, dt)
    got = hermite.round_counts_array(pos)
    want = [0]
    for k in range(dt.size):
        want += hermite.segment_demand(int(p[k]), v[k], int(p[k + 1]), v[k + 1], int(dt[k]))
    assert got.tolist() == want
