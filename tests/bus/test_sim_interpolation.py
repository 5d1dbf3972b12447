"""The simulated drive interpolates exactly as seed 000 4.2.3 (and planner.encoding.hermite) says, at every ms."""

from __future__ import annotations

import math

from bus_testkit import VDrive, make_axis
from hypothesis import given
from hypothesis import strategies as st

from bus import cob, codec
from planner.encoding import hermite

# counts_per_rev = 60000: 1 rpm is exactly 1 count/ms, so the seed's coefficients are exact numbers
AXIS = make_axis(1, counts_per_unit=60000.0, counts_per_rev=60000, max_acceleration=10000.0,
                 acceleration=100.0, velocity=2.0, max_profile_velocity_rpm=5000.0)


def demands_per_ms(records: list[tuple[int, int, int]], total_ms: int) -> list[int]:
    """Run the drive with a 1 ms SYNC and collect 0x6062 from TPDO2 after every ms."""
    d = VDrive(AXIS, sync_period_ms=1)
    d.enable()
    for r in records:
        d.record(*r)
    d.cw(0x001F)
    d.sync()  # applies the controlword: ip mode active from here
    out = []
    for _ in range(total_ms):
        frames = d.sync()
        tpdo2 = next(f.data for f in frames if f.cob_id == cob.tpdo2_id(1))
        out.append(codec.decode_tpdo2(tpdo2).position_demand)
    assert d.model.counters.faults == 0
    return out


def test_known_pvt_pair_yields_the_seed_polynomial_at_every_ms() -> None:
    # From the standstill at 0 to P = 1000 counts, V = 150 rpm (= 150 counts/ms) in T = 10 ms:
    # d = 1000, c = 150, b = T^-2 (-3*1000 + 10*(2*150 + 0)) = 0, a = T^-3 (-2*1000 + 10*(150 + 0)) = -0.5
    # P(tau) = -0.5 tau^3 + 150 tau + 1000, tau = k - 10.
    assert hermite.coefficients(0, 0.0, 1000, 150.0, 10) == (-0.5, 0.0, 150.0, 1000.0)
    by_hand = [-0.5 * (k - 10) ** 3 + 150 * (k - 10) + 1000 for k in range(1, 11)]
    assert by_hand[0] == 14.5  # a half count: the drive rounds half away from zero
    expected = [math.floor(x + 0.5) for x in by_hand]
    got = demands_per_ms([(1000, 150, 10), (1000, 0, 10), (1000, 0, 0)], 20)
    assert got[:10] == expected
    assert got[:10] == hermite.segment_demand(0, 0.0, 1000, 150.0, 10)
    # second segment starts at (1000, 150 counts/ms) and ends at rest on the same position
    assert got[10:] == hermite.segment_demand(1000, 150.0, 1000, 0.0, 10)


def test_chained_segments_of_different_lengths() -> None:
    records = [(500, 100, 7), (2500, 120, 20), (3000, 0, 13), (3000, 0, 0)]
    got = demands_per_ms(records, 40)
    expected = (hermite.segment_demand(0, 0.0, 500, 100.0, 7)
                + hermite.segment_demand(500, 100.0, 2500, 120.0, 20)
                + hermite.segment_demand(2500, 120.0, 3000, 0.0, 13))
    assert got == expected


@given(
    p0=st.integers(-(2**31), 2**31 - 1),
    dp=st.integers(-200_000, 200_000),
    v0=st.floats(-3000.0, 3000.0, allow_nan=False),
    v1=st.floats(-3000.0, 3000.0, allow_nan=False),
    t=st.integers(1, 255),
)
def test_fast_segment_demand_is_bit_identical_to_the_per_tick_formula(p0: int, dp: int, v0: float, v1: float,
                                                                      t: int) -> None:
    """The drive's inner loop (hermite.demand_from_coefficients) is the seed polynomial, evaluated
    and rounded tick by tick exactly as hermite.evaluate and hermite.round_counts do."""
    p1 = max(-(2**31), min(2**31 - 1, p0 + dp))
    coeffs = hermite.coefficients(p0, v0, p1, v1, t)
    per_tick = [hermite.round_counts(hermite.evaluate(coeffs, k - t)[0]) for k in range(1, t + 1)]
    assert hermite.segment_demand(p0, v0, p1, v1, t) == per_tick


def test_demand_ends_exactly_on_each_record() -> None:
    records = [(1234, 50, 9), (-4321, -80, 31), (0, 0, 17), (0, 0, 0)]
    got = demands_per_ms(records, 57)
    assert got[8] == 1234 and got[39] == -4321 and got[56] == 0
