"""The 0x20C1 record codec: round trip and loud failure on out-of-range values."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from planner.encoding.record import (
    POSITION_MAX,
    POSITION_MIN,
    TIME_MAX_MS,
    VELOCITY_MAX,
    VELOCITY_MIN,
    PvtRecord,
    pack,
    unpack,
)
from planner.errors import ENCODING_RANGE, EncodingRangeError

positions = st.integers(POSITION_MIN, POSITION_MAX)
velocities = st.integers(VELOCITY_MIN, VELOCITY_MAX)
times = st.integers(0, TIME_MAX_MS)


@given(positions, velocities, times)
def test_round_trip(p: int, v: int, t: int) -> None:
    raw = pack(PvtRecord(p, v, t))
    assert len(raw) == 8
    assert unpack(raw) == PvtRecord(p, v, t)
    assert pack(unpack(raw)) == raw


@given(st.binary(min_size=8, max_size=8))
def test_decode_encode(raw: bytes) -> None:
    assert pack(unpack(raw)) == raw


def test_layout() -> None:
    assert pack(PvtRecord(1, -1, 10)) == bytes([1, 0, 0, 0, 0xFF, 0xFF, 0xFF, 10])


out_of_range = st.one_of(
    st.tuples(
        st.one_of(st.integers(max_value=POSITION_MIN - 1), st.integers(min_value=POSITION_MAX + 1)),
        velocities,
        times,
    ),
    st.tuples(
        positions,
        st.one_of(st.integers(max_value=VELOCITY_MIN - 1), st.integers(min_value=VELOCITY_MAX + 1)),
        times,
    ),
    st.tuples(
        positions, velocities, st.one_of(st.integers(max_value=-1), st.integers(min_value=TIME_MAX_MS + 1))
    ),
)


@given(out_of_range)
def test_out_of_range_raises(rec: tuple[int, int, int]) -> None:
    with pytest.raises(EncodingRangeError) as e:
        pack(rec)
    assert e.value.code == ENCODING_RANGE


@given(st.binary().filter(lambda b: len(b) != 8))
def test_wrong_length_raises(raw: bytes) -> None:
    with pytest.raises(EncodingRangeError):
        unpack(raw)


def test_floats_are_not_truncated() -> None:
    with pytest.raises(EncodingRangeError):
        pack((1.5, 0, 1))  # type: ignore[arg-type]
