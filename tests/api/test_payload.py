"""Strict bounded decoding of submissions (payload.py): every payload-level bad-input row, and fuzz."""

from __future__ import annotations

import math
import struct

import msgpack
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from streamer.api.errors import MotionError
from streamer.api.payload import (
    PayloadLimits,
    body_hash,
    decode_submission,
    encode_submission,
    pack,
    plain,
)

JOB = {"kind": "path", "axes": ["j1", "j2", "j3"], "waypoints": [[0.0, 0.0, 0.0], [0.1, 0.2, 0.3]]}


def code_of(data: bytes, limits: PayloadLimits | None = None) -> MotionError:
    with pytest.raises(MotionError) as info:
        decode_submission(data, limits or PayloadLimits())
    return info.value


def test_valid_job_decodes_with_and_without_job_id() -> None:
    sub = decode_submission(pack(JOB))
    assert sub.job_id is None and sub.body == JOB and sub.kind == "path"
    sub = decode_submission(encode_submission(JOB, "job-1"))
    assert sub.job_id == "job-1" and sub.body == JOB


@pytest.mark.parametrize(
    "data, code",
    [
        (b"", "MALFORMED_PAYLOAD"),
        (b"\xc1", "MALFORMED_PAYLOAD"),  # never-used msgpack byte: not msgpack
        (b"hello world", "MALFORMED_PAYLOAD"),
        (pack(JOB)[:-3], "MALFORMED_PAYLOAD"),  # truncated
        (pack(JOB) + b"\x00", "MALFORMED_PAYLOAD"),  # trailing bytes
        (b"\x81\xa4kind" + b"\x91" * 40 + b"\x01", "MALFORMED_PAYLOAD"),  # nested too deep
        (b"\x91" * 200_000 + b"\x01", "MALFORMED_PAYLOAD"),  # deeper than the unpacker's stack
        (b"\xa2\xff\xfe", "MALFORMED_PAYLOAD"),  # invalid UTF-8
        (pack([1, 2, 3]), "SCHEMA"),  # not a map
        (pack({"axes": ["j1"]}), "SCHEMA"),  # missing kind
    ],
)
def test_malformed_and_shape_rows(data: bytes, code: str) -> None:
    assert code_of(data).code == code


def test_size_limit_is_checked_before_decoding() -> None:
    err = code_of(b"\xc1" * 101, PayloadLimits(max_bytes=100))  # would be MALFORMED if decoded
    assert err.code == "TOO_LARGE" and "101 bytes" in err.message
    assert code_of(b"\x00" * (4 * 1024 * 1024 + 1)).code == "TOO_LARGE"  # the default 4 MiB


def test_more_waypoints_than_the_limit_is_too_large() -> None:
    job = {"kind": "path", "axes": ["j1"], "waypoints": [[0]] * 100_001}
    err = code_of(pack(job))
    assert err.code == "TOO_LARGE" and err.path == "waypoints" and "100001" in err.message
    decode_submission(
        pack({"kind": "path", "axes": ["j1"], "waypoints": [[0]] * 100_000})
    )  # the limit itself


def test_non_string_and_duplicate_keys_are_schema_errors_with_path() -> None:
    err = code_of(b"\x82\xa4kind\xa4path\x01\x02")  # {"kind": "path", 1: 2}
    assert err.code == "SCHEMA" and "non-string key 1" in err.message
    err = code_of(b"\x82\xa4kind\xa4path\x91\x01\x02")  # a list as a key
    assert err.code == "SCHEMA"
    err = code_of(b"\x82\xa4kind\xa4path\x81\x01\x02\x03")  # a map as a key
    assert err.code == "SCHEMA"
    err = code_of(b"\x83\xa4kind\xa4path\xa1a\x01\xa1a\x02")  # duplicate "a"
    assert err.code == "SCHEMA" and err.path == "a" and "twice" in err.message
    nested = pack({"kind": "move", "x": 0})[:-3] + b"\xa1x\x81\x01\x02"  # {"kind": "move", "x": {1: 2}}
    err = code_of(nested)
    assert err.code == "SCHEMA" and err.path == "x"


@pytest.mark.parametrize(
    "value, code, words",
    [
        (float("nan"), "NONFINITE", "waypoints[1][2] of axis 'j3' is NaN"),
        (float("inf"), "NONFINITE", "waypoints[1][2] of axis 'j3' is inf"),
        (float("-inf"), "NONFINITE", "waypoints[1][2] of axis 'j3' is -inf"),
        (True, "TYPE", "waypoints[1][2] of axis 'j3' is a bool"),
        (2**64 - 1, "TYPE", "waypoints[1][2] of axis 'j3' is the integer 18446744073709551615"),
        (-(2**63), "TYPE", "outside +-2**53"),
        (b"\x00\x01", "TYPE", "binary"),
        (msgpack.ExtType(3, b"xx"), "TYPE", "extension"),
    ],
)
def test_value_rows_name_axis_and_value(value: object, code: str, words: str) -> None:
    job = {"kind": "path", "axes": ["j1", "j2", "j3"], "waypoints": [[0, 0, 0], [0, 0, value]]}
    err = code_of(msgpack.packb(job, use_bin_type=True))
    assert err.code == code
    assert err.path == "waypoints[1][2]"
    assert words in err.message


def test_float32_nan_and_target_axis_naming() -> None:
    raw = pack({"kind": "move", "axes": ["j1", "j2"], "target": [0.0, 0.0]})
    nan32 = b"\xca" + struct.pack(">f", math.nan)
    raw = raw[:-9] + nan32  # replace the last float64 0.0 with a float32 NaN
    err = code_of(raw)
    assert err.code == "NONFINITE" and err.message == "target[1] of axis 'j2' is NaN"


def test_job_id_rules() -> None:
    assert code_of(pack({**JOB, "job_id": 7})).code == "TYPE"
    for bad in ("", "a/b", "x*", "$*", "a" * 65, "..", "with space"):
        err = code_of(pack({**JOB, "job_id": bad}))
        assert err.code in ("SCHEMA", "TOO_LARGE") and err.path == "job_id", bad
    assert decode_submission(pack({**JOB, "job_id": "A-z_0.9"})).job_id == "A-z_0.9"


def test_string_and_map_limits() -> None:
    assert code_of(pack({**JOB, "name": "x" * 5000})).code == "TOO_LARGE"
    assert code_of(pack({**JOB, **{f"k{i}": 0 for i in range(300)}})).code == "TOO_LARGE"


def test_body_hash_is_canonical() -> None:
    a = {"kind": "move", "axes": ["j1"], "target": [1], "mode": "absolute"}
    b = {"mode": "absolute", "target": [1.0], "axes": ["j1"], "kind": "move"}
    assert body_hash(a) == body_hash(b)
    assert body_hash(a) != body_hash({**a, "target": [1.0000001]})


def test_plain_makes_wire_safe_values() -> None:
    class Thing:
        pass

    out = plain({"a": float("nan"), "b": (1, 2), 3: Thing(), "c": {"d": float("inf")}})
    assert out["a"] is None and out["b"] == [1, 2] and isinstance(out["3"], str) and out["c"]["d"] is None
    pack(out)


@given(st.binary(max_size=300))
def test_any_bytes_decode_or_reject_with_a_code(data: bytes) -> None:
    try:
        sub = decode_submission(data)
    except MotionError as err:
        assert err.code in {"MALFORMED_PAYLOAD", "TOO_LARGE", "SCHEMA", "TYPE", "NONFINITE"}
    else:
        assert isinstance(sub.body, dict) and "kind" in sub.body


values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**64), max_value=2**64 - 1)
    | st.floats()
    | st.text(max_size=8)
    | st.binary(max_size=4),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=6), children, max_size=4)
    ),
    max_leaves=20,
)


@given(
    st.dictionaries(
        st.sampled_from(["kind", "axes", "waypoints", "job_id", "target", "x"]), values, max_size=5
    )
)
def test_any_msgpack_map_decodes_or_rejects_with_a_code(obj: dict[str, object]) -> None:
    try:
        data = msgpack.packb(obj, use_bin_type=True)
    except (OverflowError, ValueError):
        return  # not representable in msgpack (ints beyond 64 bits)
    try:
        sub = decode_submission(data)
    except MotionError as err:
        assert err.code in {"MALFORMED_PAYLOAD", "TOO_LARGE", "SCHEMA", "TYPE", "NONFINITE"}
        assert err.message
    else:
        assert sub.body.get("kind") is not None or "kind" in sub.body


def test_any_bytes_into_the_whole_job_decoder(demo_cell: object) -> None:
    """decode_job (payload + the planner's job_from_dict): a job or a coded rejection, never INTERNAL."""
    pytest.importorskip("planner.job")
    from streamer.api.payload import decode_job

    valid = pack({"kind": "move", "axes": ["j1", "j2"], "target": [0.1, 0.2]})

    @settings(max_examples=300, deadline=None, database=None)
    @given(st.one_of(st.binary(max_size=200), st.binary(max_size=8).map(lambda b: valid[:-2] + b)))
    def one(data: bytes) -> None:
        try:
            decode_job(data, demo_cell)
        except MotionError as err:
            assert err.code != "INTERNAL", err

    one()
