"""Every row of the bad-input table, through Zenoh: each answered with its code, nothing executed.

The planner-level rows go through the FakeBackend here (its magic `tolerance_counts` values raise the
planner's codes), which checks the service's mapping; test_e2e.py repeats them with the real planner.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import msgpack
import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from planner.config import CellConfig, load_cell
from streamer.api import keys
from streamer.api.payload import pack
from streamer.api.service import JobService
from streamer.api.store import JobStore
from streamer.api.zenoh_config import build_config
from tests.api.conftest import free_port
from tests.api.fakes import FakeBackend, timed_job
from tests.api.helpers import raw_get, raw_session, wait_for

ROOT = Path(__file__).resolve().parents[2]
PATH_JOB = {"kind": "path", "axes": ["j1", "j2", "j3"], "waypoints": [[0.0, 0.0, 0.0], [0.1, 0.2, 0.3]]}


def with_value(value: object) -> bytes:
    job = {"kind": "path", "axes": ["j1", "j2", "j3"], "waypoints": [[0, 0, 0], [0, 0, 0], [0, 0, value]]}
    return msgpack.packb(job, use_bin_type=True)


def tol(code: int) -> bytes:
    return pack({**PATH_JOB, "tolerance_counts": code})


# (row label, payload, code, path, words that must be in the message)
ROWS: list[tuple[str, bytes, str, str | None, str]] = [
    ("not msgpack", b"\xc1\xc1\xc1", "MALFORMED_PAYLOAD", None, "msgpack"),
    ("truncated", pack(PATH_JOB)[:-5], "MALFORMED_PAYLOAD", None, "truncated"),
    ("trailing bytes", pack(PATH_JOB) + b"\x01", "MALFORMED_PAYLOAD", None, "trailing"),
    (
        "nested too deep",
        pack({**PATH_JOB, "x": 0})[:-1] + b"\x91" * 30 + b"\x00",
        "MALFORMED_PAYLOAD",
        None,
        "deep",
    ),
    ("over the size limit", b"\x00" * (4 * 1024 * 1024 + 1), "TOO_LARGE", None, "4194305 bytes"),
    (
        "more waypoints than the limit",
        pack({"kind": "path", "axes": ["j1"], "waypoints": [[0]] * 100_001}),
        "TOO_LARGE",
        "waypoints",
        "100001",
    ),
    ("missing field", pack({"kind": "path", "axes": ["j1"]}), "SCHEMA", "waypoints", "waypoints"),
    ("missing kind", pack({"axes": ["j1"]}), "SCHEMA", "kind", "kind"),
    ("unknown field", pack({**PATH_JOB, "speed": 3}), "SCHEMA", "speed", "speed"),
    ("non-string key", b"\x84" + pack(PATH_JOB)[1:] + b"\x07\x07", "SCHEMA", None, "non-string key 7"),
    ("string in waypoints", with_value("fast"), "TYPE", "waypoints[2][2]", "'fast'"),
    ("bool as number", with_value(True), "TYPE", "waypoints[2][2]", "axis 'j3' is a bool"),
    ("huge int", with_value(2**63), "TYPE", "waypoints[2][2]", "9223372036854775808"),
    ("NaN", with_value(math.nan), "NONFINITE", "waypoints[2][2]", "waypoints[2][2] of axis 'j3' is NaN"),
    ("infinity", with_value(-math.inf), "NONFINITE", "waypoints[2][2]", "of axis 'j3' is -inf"),
    (
        "rows of unequal length",
        pack({**PATH_JOB, "waypoints": [[0, 0, 0], [1, 1]]}),
        "AXIS_COUNT",
        "waypoints[1]",
        "2 values for 3 axes",
    ),
    (
        "axis count not matching axes",
        pack({"kind": "move", "axes": ["j1", "j2"], "target": [0.1]}),
        "AXIS_COUNT",
        "target",
        "1 values for 2 axes",
    ),
    ("unknown axis", pack({**PATH_JOB, "axes": ["j1", "j2", "j9"]}), "AXIS_ID", "axes[2]", "'j9'"),
    ("duplicate axis", pack({**PATH_JOB, "axes": ["j1", "j2", "j1"]}), "AXIS_ID", "axes[2]", "'j1'"),
    ("degenerate", tol(907), "DEGENERATE", None, "j1"),
    ("non monotonic", tol(905), "NON_MONOTONIC", None, "j1"),
    ("limits", tol(906), "LIMITS", None, "j1"),
    ("position limit", tol(904), "POSITION_LIMIT", None, "j1"),
    ("limits exceed drive", tol(903), "LIMITS_EXCEED_DRIVE", None, "j1"),
    ("infeasible", tol(901), "INFEASIBLE", None, "j1"),
    ("encoding range", tol(902), "ENCODING_RANGE", None, "j1"),
]


class Bench:
    def __init__(self, tmp: Path, cell: CellConfig):
        self.port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.session = zenoh.open(build_config(listen=[self.endpoint]))
        self.backend = FakeBackend(cell, default_duration_s=0.05)
        self.store = JobStore(tmp / "bad.db", synchronous="NORMAL")
        self.service = JobService(self.session, self.backend, self.store).start()
        self.client = raw_session(self.endpoint)

    def close(self) -> None:
        self.client.close()
        self.service.close()
        self.store.close()
        self.session.close()


@pytest.fixture(scope="module")
def bench(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Bench]:
    b = Bench(tmp_path_factory.mktemp("bad"), load_cell(ROOT / "configs" / "demo.toml"))
    yield b
    b.close()


@pytest.mark.parametrize("label, payload, code, path, words", ROWS, ids=[r[0] for r in ROWS])
def test_bad_input_row(
    bench: Bench, label: str, payload: bytes, code: str, path: str | None, words: str
) -> None:
    kind, msg = raw_get(bench.client, keys.submit("demo"), payload)
    assert kind == "err", (label, msg)
    assert set(msg) >= {"code", "path", "message"}
    assert msg["code"] == code, (label, msg)
    if path is not None:
        assert msg["path"] == path, (label, msg)
    assert words in msg["message"], (label, msg)
    assert bench.backend.executed == [] and bench.store.count() == 0


def test_put_rows_are_rejected_on_the_events_key(bench: Bench) -> None:
    from tests.api.helpers import Collector

    for i, (label, payload, code, _path, _words) in enumerate(ROWS[5:]):
        if label in ("non-string key",):
            continue
        body = msgpack.unpackb(payload, strict_map_key=False)
        body["job_id"] = f"put-bad-{i}"
        col = Collector(bench.client, keys.job_events("demo", f"put-bad-{i}"))
        bench.client.put(keys.submit("demo"), msgpack.packb(body, use_bin_type=True))
        msg = col.until(lambda m: True, timeout=10)
        col.close()
        assert msg["type"] == "rejected" and msg["error"]["code"] == code, (label, msg)
    assert bench.backend.executed == [] and bench.store.count() == 0


# -- Hypothesis: 1,000 arbitrary payloads, each answered with an error -------------------------------
JUNK_KINDS = st.sampled_from(["", "paths", "MOVE", "timed ", "pvt2", "x"]) | st.integers() | st.none()
leaf = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**63), max_value=2**64 - 1)
    | st.floats()
    | st.text(max_size=6)
    | st.binary(max_size=4)
)
tree = st.recursive(
    leaf,
    lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=5), c, max_size=4),
    max_leaves=16,
)
random_maps = st.dictionaries(
    st.sampled_from(["axes", "waypoints", "target", "times", "positions", "rows", "mode", "job_id", "zz"]),
    tree,
    max_size=5,
).flatmap(lambda d: st.just(d) | JUNK_KINDS.map(lambda k: {**d, "kind": k}))


def _packable(obj: object) -> bytes | None:
    try:
        return msgpack.packb(obj, use_bin_type=True)
    except (OverflowError, ValueError, TypeError):
        return None


valid = pack(timed_job(0.05))
mutations = st.one_of(
    st.integers(min_value=1, max_value=len(valid) - 1).map(lambda n: valid[:n]),  # truncated
    st.binary(min_size=1, max_size=8).map(lambda b: valid + b),  # trailing bytes
    st.sampled_from(["times", "positions", "axes", "kind"]).map(
        lambda f: pack({k: v for k, v in timed_job(0.05).items() if k != f})
    ),  # a field missing
    tree.map(lambda v: _packable({**timed_job(0.05), "positions": [[0.0], [v]]})),  # a bad value
    st.text(min_size=1, max_size=8)
    .filter(lambda k: k not in ("name", "tolerance_counts", "job_id"))
    .map(lambda k: pack({**timed_job(0.05), k: 1})),  # an unknown field
)
payloads = st.one_of(
    st.binary(max_size=200),
    random_maps.map(_packable),
    tree.map(_packable),
    mutations,
).filter(lambda p: p is not None)


def test_thousand_arbitrary_payloads_each_get_an_error_then_a_valid_job_runs(bench: Bench) -> None:
    codes: dict[str, int] = {}

    @settings(
        max_examples=1000,
        deadline=None,
        database=None,
        derandomize=True,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much, HealthCheck.data_too_large],
    )
    @given(payloads)
    def one(payload: bytes) -> None:
        if payload == valid:
            return
        # a bad value may happen to be a valid number: those jobs are legitimately accepted
        kind, msg = raw_get(bench.client, keys.submit("demo"), payload)
        if kind == "ok":
            body = msgpack.unpackb(payload, strict_map_key=False)
            assert isinstance(body, dict) and body.get("kind") == "timed", (payload, msg)
            value = body["positions"][1][0]
            assert isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
            return
        assert kind == "err", (payload, msg)
        assert isinstance(msg["code"], str) and msg["code"] != "INTERNAL", msg
        codes[msg["code"]] = codes.get(msg["code"], 0) + 1

    one()
    assert sum(codes.values()) >= 950, codes  # (a few mutations are valid jobs, legitimately accepted)
    assert {"MALFORMED_PAYLOAD", "SCHEMA", "TYPE"} <= set(codes), codes
    kind, msg = raw_get(
        bench.client,
        keys.submit("demo"),
        pack({**timed_job(0.05, name="after-fuzz"), "job_id": "after-fuzz"}),
    )
    assert kind == "ok", msg
    wait_for(
        lambda: raw_get(bench.client, keys.job("demo", "after-fuzz"))[1]["state"] == "done",
        timeout=10,
        what="the valid job after the fuzz to finish",
    )
    assert "after-fuzz" in bench.backend.executed
