"""Fuzzing that issue 7 section 3 asks for and the other suites do not already do.

Already elsewhere (not duplicated here):
- any bytes into the job decoder -> a job or a coded rejection: tests/api/test_payload.py
  (`test_any_bytes_decode_or_reject_with_a_code`, `test_any_bytes_into_the_whole_job_decoder`);
- any (COB-ID, DLC 0-8, data) into the TPDO/EMCY/heartbeat parsers -> parsed or ProtocolError:
  tests/bus/test_bus_codec.py (`test_frame_to_event_parses_or_raises_protocol_error`, the total
  decoder tests);
- the stateful test over the streamer core (rules sync, drop, duplicate, emcy, heartbeat loss, submit,
  cancel; invariants: nothing sent after a fault, modelled FIFO fill in [0, 64], frames only to the
  job's axes): tests/streamer/core/test_stateful.py.
Added here: job-shaped maps (not just bytes) through the whole decoder, planner validation included;
any frame into a running simulated drive; any frame into the master side of the virtual runtime
mid-job.
"""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from reliability_kit import cell3

from bus.cob import RPDO1_BASE, RPDO2_BASE
from bus.codec import Frame, decode_emcy
from bus.sim.epos import EposDrive
from planner.config import CellConfig
from streamer.api.errors import MotionError
from streamer.api.payload import decode_job, pack

number = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.integers(-(2**63), 2**63 - 1),
    st.sampled_from([0, 0.1, -0.5, 1e300, -1e-300, 2**53 + 1]),
    st.text(max_size=3),
    st.none(),
    st.booleans(),
)
row = st.lists(number, min_size=0, max_size=4)
axes = st.lists(st.sampled_from(["j1", "j2", "j3", "j4", "j7", "", "J1", 1]), min_size=0, max_size=4)
job_maps = st.fixed_dictionaries(
    {"kind": st.sampled_from(["path", "move", "timed", "pvt", "jog", 3])},
    optional={
        "axes": axes,
        "waypoints": st.lists(row, max_size=5),
        "target": row,
        "start": row,
        "mode": st.sampled_from(["absolute", "relative", "sideways", None]),
        "times": row,
        "positions": st.lists(row, max_size=5),
        "velocities": st.lists(row, max_size=5),
        "tolerance_counts": number,
        "velocity_scale": st.one_of(number, row),
        "acceleration_scale": st.one_of(number, row),
        "limits": st.dictionaries(st.sampled_from(["j1", "j2", "x", "velocity"]),
                                  st.dictionaries(st.sampled_from(["velocity", "acceleration", "jerk", "y"]),
                                                  number, max_size=3), max_size=2),
        "job_id": st.one_of(st.text(max_size=12), number),
        "description": st.text(max_size=20),
        "surprise": number,
    },
)


@settings(max_examples=150, deadline=None)
@given(job_maps)
def test_job_shaped_maps_become_a_job_or_a_coded_rejection(body: dict[str, object]) -> None:
    try:
        data = pack(body)
    except (OverflowError, ValueError, TypeError):
        return  # not representable on the wire at all
    try:
        _, job = decode_job(data, cell3())
    except MotionError as err:
        assert err.code != "INTERNAL", err
        assert err.code and err.message
    else:
        assert list(job.axes) and all(a in {"j1", "j2", "j3"} for a in job.axes)


def _running_drive(cell: CellConfig) -> EposDrive:
    axis = cell.axes[1]
    m = EposDrive(axis.node_id, axis, cell.drive)
    m.power_on(0.0)
    m.configure(cell.sync_period_ms, t=0.0)
    for cw in (0x0006, 0x000F):
        m.sdo_write(0x6040, 0, cw, 0.0)
    m.sdo_write(0x60C4, 6, 0, 0.0)
    m.sdo_write(0x60C4, 6, 1, 0.0)
    return m


frames = st.tuples(st.integers(0, 0x7FF), st.binary(min_size=0, max_size=8))


@given(st.lists(frames, min_size=1, max_size=20))
def test_any_frames_into_a_simulated_drive_never_raise(sequence: list[tuple[int, bytes]]) -> None:
    cell = cell3()
    m = _running_drive(cell)
    node = m.node_id
    t = 0.001
    for cob_id, data in sequence:
        t += 0.001
        out = m.on_frame(cob_id, data, t)
        for f in out:
            assert isinstance(f, Frame) and 0 <= len(f.data) <= 8
        wrong_length = (cob_id == RPDO2_BASE + node and len(data) != 8) or (
            cob_id == RPDO1_BASE + node and len(data) != 2)
        if wrong_length and m.counters.pdo_length_errors == 1 and out:
            emcy = [decode_emcy(f.data) for f in out if f.cob_id == 0x80 + node]
            assert emcy and emcy[0].code == (0x8210 if len(data) < (8 if cob_id & 0x100 else 2) else 0x8220)
    out = m.on_sync(t + 0.01) + m.advance(t + 0.02)
    assert all(isinstance(f, Frame) for f in out)
    assert not math.isnan(m.position_actual_exact)


@pytest.mark.parametrize("seed", range(3))
def test_any_frames_on_the_bus_during_a_job_never_crash_the_runtime(seed: int) -> None:
    """Random frames (any COB-ID, DLC 0-8) from a foreign sender mid-job: the job ends in a terminal
    state with an outcome (often a fault: they hit the drives' RPDOs, NMT, SYNC...), nothing raises."""
    import random

    from reliability_kit import Rig, demo_traj

    from streamer.core import JobState
    from streamer.runtime.virtual import ForeignTraffic

    rng = random.Random(seed)
    noise = sorted(((rng.uniform(0.5, 2.5), Frame(rng.randrange(0x800),
                                                  bytes(rng.randrange(256) for _ in range(rng.randrange(9)))))
                    for _ in range(300)), key=lambda x: x[0])
    rig = Rig(demo_traj(), foreign=ForeignTraffic(noise))
    rig.run(max_s=20.0)
    assert rig.core.state in (JobState.DONE, JobState.FAILED, JobState.CANCELLED)
    assert rig.core.outcome is not None
