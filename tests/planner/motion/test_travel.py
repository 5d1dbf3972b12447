"""Travel commands (planner/motion/travel.py, seed 002): position modes, modulo vectors, velocity mode, ramps,
emergency stop, and the cell's travel settings."""

from __future__ import annotations

import copy
import itertools
from fractions import Fraction
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from planner_checks import CONFIGS, assert_invariants

from planner.config import CellConfig, cell_from_dict, load_cell
from planner.encoding import hermite
from planner.encoding.encoder import ACC_EXCESS_LIMIT
from planner.errors import PlanningError
from planner.job import effective_limits, job_from_dict, job_to_dict
from planner.motion.stop import plan_emergency_stop_from_wire, plan_stop_from_wire
from planner.motion.travel import (
    CruiseState,
    MotionState,
    extend_velocity,
    modulo_end,
    plan_velocity,
    resolve_target,
)
from planner.plan import plan_job
from planner.trajectory import PvtTrajectory

DEG_CPU = 8192 * 10 / 360.0  # a rotary table: 10:1 gear, degrees

ROTARY: dict[str, Any] = {
    "cell": {"name": "rotary", "sync_period_ms": 10},
    "axis": [
        {"name": "c", "unit": "deg", "node_id": 1, "counts_per_unit": DEG_CPU, "counts_per_rev": 8192,
         "velocity": 360.0, "acceleration": 1440.0, "jerk": 14400.0, "position_min": -100000.0,
         "position_max": 100000.0, "max_profile_velocity_rpm": 8000, "max_acceleration": 2000.0,
         "modulo_period": 360.0, "modulo_tolerance": 1.0},
        {"name": "b", "unit": "deg", "node_id": 2, "counts_per_unit": 8192 * 50 / 360.0, "counts_per_rev": 8192,
         "velocity": 90.0, "acceleration": 360.0, "jerk": 3600.0, "position_min": -20000.0,
         "position_max": 20000.0, "max_profile_velocity_rpm": 8000, "max_acceleration": 500.0,
         "modulo_period": 360.0, "modulo_tolerance": 1.0},
    ],
}


@pytest.fixture(scope="module")
def rotary() -> CellConfig:
    return cell_from_dict(ROTARY)


def _rotary_with(**axis0: Any) -> dict[str, Any]:
    data = copy.deepcopy(ROTARY)
    data["axis"][0].update(axis0)
    return data


# ----------------------------------------------------------------------------------------------------
# seed 002's modulo tables ("Examples of modulo positioning"): mode, absolute start, modulo target,
# relative travel path, absolute end (modulo factor 360°, tolerance window 1°)

LESS_THAN_ONE_TURN = [  # the seed's first table; its 0° cells were lost in the text, restored from the sums
    ("modulo_plus", 90.0, 0.0, 270.0, 360.0),
    ("modulo_plus", 90.0, 360.0, 630.0, 720.0),
    ("modulo_plus", 90.0, 720.0, 990.0, 1080.0),
    ("modulo_minus", 90.0, 0.0, -90.0, 0.0),
    ("modulo_minus", 90.0, 360.0, -450.0, -360.0),
    ("modulo_minus", 90.0, 720.0, -810.0, -720.0),
    ("modulo_short", 90.0, 0.0, -90.0, 0.0),
]

FULL_TURNS = [  # the seed's second table ("outside TF": the start is outside the tolerance window)
    ("modulo_plus", 90.00, 90.00, 0.00, 90.00),
    ("modulo_plus", 90.90, 90.00, -0.90, 90.00),
    ("modulo_plus", 91.10, 90.00, 358.90, 450.00),
    ("modulo_plus", 89.10, 90.00, 0.90, 90.00),
    ("modulo_plus", 88.90, 90.00, 1.10, 90.00),
    ("modulo_plus", 90.00, 450.00, 360.00, 450.00),
    ("modulo_plus", 90.90, 450.00, 359.10, 450.00),
    ("modulo_plus", 91.10, 450.00, 718.90, 810.00),
    ("modulo_plus", 89.10, 450.00, 360.90, 450.00),
    ("modulo_plus", 88.90, 450.00, 361.10, 450.00),
    ("modulo_plus", 90.00, 810.00, 720.00, 810.00),
    ("modulo_plus", 90.90, 810.00, 719.10, 810.00),
    ("modulo_plus", 91.10, 810.00, 1078.90, 1170.00),
    ("modulo_plus", 89.10, 810.00, 720.90, 810.00),
    ("modulo_plus", 88.90, 810.00, 721.10, 810.00),
    ("modulo_minus", 90.00, 90.00, 0.00, 90.00),
    ("modulo_minus", 90.90, 90.00, -0.90, 90.00),
    ("modulo_minus", 91.10, 90.00, -1.10, 90.00),
    ("modulo_minus", 89.10, 90.00, 0.90, 90.00),
    ("modulo_minus", 88.90, 90.00, -358.90, -270.00),
    ("modulo_minus", 90.00, 450.00, -360.00, -270.00),
    ("modulo_minus", 90.90, 450.00, -360.90, -270.00),
    ("modulo_minus", 91.10, 450.00, -361.10, -270.00),
    ("modulo_minus", 89.10, 450.00, -359.10, -270.00),
    ("modulo_minus", 88.90, 450.00, -718.90, -630.00),
    ("modulo_minus", 90.00, 810.00, -720.00, -630.00),
    ("modulo_minus", 90.90, 810.00, -720.90, -630.00),
    ("modulo_minus", 91.10, 810.00, -721.10, -630.00),
    ("modulo_minus", 89.10, 810.00, -719.10, -630.00),
    ("modulo_minus", 88.90, 810.00, -1078.90, -990.00),
]


@pytest.mark.parametrize(("mode", "start", "target", "path", "end"), LESS_THAN_ONE_TURN + FULL_TURNS)
def test_seed_002_modulo_vectors(rotary: CellConfig, mode: str, start: float, target: float, path: float,
                                 end: float) -> None:
    assert modulo_end(mode, start, target, 360.0, 1.0) == pytest.approx(end, abs=1e-9)
    assert modulo_end(mode, start, target, 360.0, 1.0) - start == pytest.approx(path, abs=1e-9)
    # the same through a job on a modulo axis, and planned: the drive ends there (snapped to counts)
    job = job_from_dict({"kind": "move", "axes": ["c"], "mode": mode, "target": [target]}, rotary)
    assert resolve_target(job, rotary, [start])[0] == pytest.approx(end, abs=1e-9)
    traj = plan_job(job, rotary, start=[start])
    assert traj.positions[0, -1] == round(end * DEG_CPU)
    assert traj.positions[0, 0] == round(start * DEG_CPU)
    # the modulo end position is the target's modulo position
    assert (end % 360.0) == pytest.approx(target % 360.0, abs=1e-9)


def test_modulo_without_the_window_and_current_direction() -> None:
    # window 0 (the seed's _EXT start types ignore it): 90.9 -> 90 in the plus direction is a full turn less 0.9
    assert modulo_end("modulo_plus", 90.9, 90.0, 360.0, 0.0) == pytest.approx(450.0)
    assert modulo_end("modulo_plus", 90.0, 90.0, 360.0, 0.0) == 90.0  # "No motion occurs if ... identical"
    # modulo_current: the last direction of rotation (none known: positive)
    minus, plus = modulo_end("modulo_minus", 88.9, 90.0, 360.0, 1.0), modulo_end("modulo_plus", 91.1, 90.0, 360.0, 1.0)
    assert modulo_end("modulo_current", 88.9, 90.0, 360.0, 1.0, -1) == minus
    assert modulo_end("modulo_current", 91.1, 90.0, 360.0, 1.0, 1) == plus
    assert modulo_end("modulo_current", 91.1, 90.0, 360.0, 1.0) == pytest.approx(450.0)
    # the shortest way, also from far out and across zero; half a period goes the positive way
    assert modulo_end("modulo_short", 3605.0, 350.0, 360.0, 1.0) == pytest.approx(3590.0)
    assert modulo_end("modulo_short", -10.0, 20.0, 360.0, 1.0) == pytest.approx(20.0)
    assert modulo_end("modulo_short", 0.0, 180.0, 360.0, 1.0) == pytest.approx(180.0)


def test_modulo_current_through_the_planner(rotary: CellConfig) -> None:
    job = job_from_dict({"kind": "move", "axes": ["c", "b"], "mode": "modulo_current", "target": [90.0, 0.0]},
                        rotary)
    assert resolve_target(job, rotary, [88.9, 10.0], last_direction=[-1, 1]).tolist() == pytest.approx([-270.0, 360.0])
    traj = plan_job(job, rotary, start=[88.9, 10.0], last_direction=[-1, 1])
    assert traj.positions[:, -1].tolist() == [round(-270.0 * DEG_CPU), round(360.0 * rotary.axes[1].counts_per_unit)]


def test_modulo_errors_name_the_axis_and_value(rotary: CellConfig, cell: CellConfig) -> None:
    with pytest.raises(PlanningError) as e:
        job_from_dict({"kind": "move", "axes": ["c", "b"], "mode": "modulo_short", "target": [10.0, 360.0]}, rotary)
    assert e.value.code == "MODULO_RANGE" and e.value.path == "target[1]"
    assert "'b'" in e.value.message and "360" in e.value.message and "basic period" in e.value.message
    with pytest.raises(PlanningError) as e:
        job_from_dict({"kind": "move", "axes": ["c"], "mode": "modulo_plus", "target": [-90.0]}, rotary)
    assert e.value.code == "MODULO_RANGE" and "'c'" in e.value.message and "-90" in e.value.message
    with pytest.raises(PlanningError) as e:  # the demo's joints are not modulo axes
        job_from_dict({"kind": "move", "axes": ["j1"], "mode": "modulo_plus", "target": [1.0]}, cell)
    assert e.value.code == "SCHEMA" and e.value.path == "mode" and "'j1'" in e.value.message
    # a modulo target past the software limits is refused when it is resolved
    job = job_from_dict({"kind": "move", "axes": ["b"], "mode": "modulo_plus", "target": [360.0 * 60]}, rotary)
    with pytest.raises(PlanningError) as e:
        resolve_target(job, rotary, [0.0])
    assert e.value.code == "POSITION_LIMIT" and "'b'" in e.value.message and "21600" in e.value.message


# ----------------------------------------------------------------------------------------------------
# absolute, relative, additive


def test_absolute_and_relative(cell: CellConfig) -> None:
    absolute = job_from_dict({"kind": "move", "axes": ["j1", "j2"], "target": [0.5, -0.5]}, cell)
    relative = job_from_dict({"kind": "move", "axes": ["j1", "j2"], "mode": "relative", "target": [0.5, -0.5]}, cell)
    assert resolve_target(absolute, cell, [0.2, 0.3], [1.0, 1.0]).tolist() == [0.5, -0.5]
    assert resolve_target(relative, cell, [0.2, 0.3], [1.0, 1.0]).tolist() == pytest.approx([0.7, -0.2])


def test_additive_after_a_stop_at_an_arbitrary_position(cell: CellConfig) -> None:
    """Seed 002, why ADDITIVE exists: after an emergency stop the position is arbitrary; the last target
    is a sound base."""
    axes = ["j1", "j2"]
    first = job_from_dict({"kind": "move", "axes": axes, "target": [1.0, -0.8]}, cell)
    last_target = resolve_target(first, cell, [0.0, 0.0])
    move = plan_job(first, cell, start=[0.0, 0.0])
    k = move.n_segments // 2  # an emergency stop from the middle of the move
    stop = plan_emergency_stop_from_wire(cell, axes, move.positions[:, k], move.velocities[:, k])
    here = stop.positions[:, -1] / stop.counts_per_unit
    assert not np.allclose(here, last_target, atol=0.05)  # it stopped somewhere in between
    additive = job_from_dict({"kind": "move", "axes": axes, "mode": "additive", "target": [0.25, 0.5]}, cell)
    relative = job_from_dict({"kind": "move", "axes": axes, "mode": "relative", "target": [0.25, 0.5]}, cell)
    assert resolve_target(additive, cell, here, list(last_target)).tolist() == pytest.approx([1.25, -0.3])
    step = np.array([0.25, 0.5])
    assert resolve_target(relative, cell, here, list(last_target)).tolist() == pytest.approx((here + step).tolist())
    traj = plan_job(additive, cell, start=here.tolist(), last_target=list(last_target))
    assert traj.positions[:, -1].tolist() == np.round(np.array([1.25, -0.3]) * traj.counts_per_unit).tolist()
    assert np.array_equal(traj.positions[:, 0], stop.positions[:, -1])
    # no target yet (None): the actual position serves, per axis
    assert resolve_target(additive, cell, here, [None, -0.8]).tolist() == pytest.approx([here[0] + 0.25, -0.3])
    assert resolve_target(additive, cell, here).tolist() == pytest.approx((here + step).tolist())
    # the end outside the limits is refused naming the offset and its base
    big = job_from_dict({"kind": "move", "axes": axes, "mode": "additive", "target": [2.5, 0.0]}, cell)
    with pytest.raises(PlanningError) as e:
        resolve_target(big, cell, here, [1.0, -0.8])
    assert e.value.code == "POSITION_LIMIT" and "+2.5" in e.value.message and "last target" in e.value.message


# ----------------------------------------------------------------------------------------------------
# ramps


def test_ramps_become_accelerations_from_the_speed_range(cell: CellConfig) -> None:
    job = job_from_dict({"kind": "move", "axes": ["j1", "j4"], "target": [2.0, 0.0],
                         "ramps": {"accel_ms": 500, "decel_ms": [1000, 400]}}, cell)
    lim = effective_limits(job, cell)
    # j1: 2 rad/s (its velocity limit) in 0.5 s = 4 rad/s^2 up, in 1 s = 2 down; j4: 3 rad/s in 0.5 / 0.4 s
    assert lim.acceleration_up.tolist() == pytest.approx([4.0, 6.0])
    assert lim.deceleration.tolist() == pytest.approx([2.0, 7.5])
    traj = plan_job(job, cell, start=[0.0, 0.0])
    assert_invariants(traj, cell)
    acc = np.maximum(traj.plan.acc_left[0], traj.plan.acc_right[0]) * 1.0e6 / traj.counts_per_unit[0]
    dec = np.minimum(traj.plan.acc_left[0], traj.plan.acc_right[0]) * 1.0e6 / traj.counts_per_unit[0]
    assert acc.max() == pytest.approx(4.0, rel=0.01) and dec.min() == pytest.approx(-2.0, rel=0.01)
    # one ramp alone serves both ways; a round trip through job_to_dict keeps what was written
    one = job_from_dict({"kind": "move", "axes": ["j1"], "target": [1.0], "ramps": {"decel_ms": 250}}, cell)
    assert effective_limits(one, cell).acceleration_up.tolist() == pytest.approx([8.0])
    assert job_to_dict(one)["ramps"] == {"decel_ms": 250.0}
    assert job_from_dict(job_to_dict(job), cell) == job


def test_ramps_errors_name_the_fields(cell: CellConfig) -> None:
    base = {"kind": "move", "axes": ["j1", "j2"], "target": [0.5, 0.5]}
    with pytest.raises(PlanningError) as e:
        job_from_dict({**base, "ramps": {"accel_ms": 500}, "limits": {"acceleration": [4.0, 4.0]}}, cell)
    assert e.value.code == "SCHEMA" and e.value.path == "ramps"
    assert "ramps" in e.value.message and "limits.acceleration" in e.value.message
    assert e.value.detail["fields"] == ["ramps", "limits.acceleration"]
    with pytest.raises(PlanningError) as e:
        job_from_dict({**base, "ramps": {"accel_ms": 500}, "acceleration_scale": 0.5}, cell)
    assert e.value.code == "SCHEMA" and "acceleration_scale" in e.value.message
    with pytest.raises(PlanningError) as e:  # 2 rad/s in 0.1 s = 20 rad/s^2 > 0x60C5 12
        job_from_dict({**base, "ramps": {"accel_ms": [500, 100]}}, cell)
    assert e.value.code == "LIMITS_EXCEED_DRIVE" and e.value.path == "ramps.accel_ms[1]" and "'j2'" in e.value.message
    with pytest.raises(PlanningError) as e:
        job_from_dict({**base, "ramps": {"accel_ms": -5}}, cell)
    assert e.value.code == "LIMITS" and e.value.path == "ramps.accel_ms" and "-5" in e.value.message
    with pytest.raises(PlanningError) as e:
        job_from_dict({**base, "ramps": {"accel": 5}}, cell)
    assert e.value.code == "SCHEMA" and e.value.path == "ramps.accel"
    with pytest.raises(PlanningError) as e:
        job_from_dict({**base, "ramps": {}}, cell)
    assert e.value.code == "SCHEMA"
    with pytest.raises(PlanningError) as e:  # ramps belong to moves
        job_from_dict({"kind": "path", "axes": ["j1"], "waypoints": [[0.0], [1.0]], "ramps": {"accel_ms": 500}}, cell)
    assert e.value.code == "SCHEMA" and e.value.path == "ramps"


# ----------------------------------------------------------------------------------------------------
# emergency stop


def test_emergency_stop_uses_the_emergency_deceleration(cell: CellConfig) -> None:
    axes = list(cell.axis_names())
    move = plan_job(job_from_dict({"kind": "move", "axes": axes, "target": [2.5, -1.8, 2.2, -3.0, 1.9, 2.0]}, cell),
                    cell, start=[0.0] * 6)
    k = int(np.argmax(np.abs(move.velocities[0])))  # near full speed
    state = MotionState.from_knot(move, k)
    normal = plan_stop_from_wire(cell, axes, state.positions_counts, state.velocities_rpm, state.accelerations)
    emergency = plan_emergency_stop_from_wire(cell, axes, state.positions_counts, state.velocities_rpm,
                                              state.accelerations)
    assert emergency.kind == "emergency_stop"
    assert np.array_equal(emergency.positions[:, 0], move.positions[:, k])
    assert np.array_equal(emergency.velocities[:, 0], move.velocities[:, k])
    assert np.all(emergency.velocities[:, -1] == 0)
    assert emergency.duration_ms < 0.75 * normal.duration_ms
    pos, vel, acc = emergency.drive_profile()
    dev = np.abs(hermite.round_counts_array(pos) - hermite.round_counts_array(emergency.plan.positions))
    assert dev.max() <= emergency.tolerance_counts
    peak = []
    for i, name in enumerate(axes):  # within the limits at every ms
        ax = cell.axis(name)
        cpu = emergency.counts_per_unit[i]
        a = np.abs(acc[i]) * 1.0e6 / cpu
        assert a.max() <= ax.emergency_stop_deceleration * (1 + ACC_EXCESS_LIMIT) + 1e-9
        assert a.max() <= ax.max_acceleration + 1e-9
        assert np.abs(vel[i]).max() / (ax.counts_per_rev / 60000.0) <= ax.max_profile_velocity_rpm
        peak.append(a.max() / ax.emergency_stop_deceleration)
    # the limiting axis brakes at its emergency deceleration (less where the encoder had to play the stop
    # slower: time_scale), above its normal acceleration limit
    assert max(peak) > 0.9 / emergency.info.get("time_scale", 1.0) ** 2
    i = int(np.argmax(peak))
    assert peak[i] * cell.axis(axes[i]).emergency_stop_deceleration > cell.axis(axes[i]).acceleration


def test_emergency_deceleration_from_the_cell(rotary: CellConfig) -> None:
    slow = cell_from_dict(_rotary_with(emergency_deceleration=1500.0))
    assert slow.axes[0].emergency_stop_deceleration == 1500.0
    assert rotary.axes[0].emergency_stop_deceleration == 2000.0  # 2 x 1440, capped at 0x60C5
    v = [round(300.0 * DEG_CPU * 60 / 8192)]
    fast = plan_emergency_stop_from_wire(rotary, ["c"], [0], v)
    gentle = plan_emergency_stop_from_wire(slow, ["c"], [0], v)
    assert gentle.duration_ms > fast.duration_ms
    assert gentle.stats[0].peak_acceleration <= 1500.0 * (1 + ACC_EXCESS_LIMIT)


# ----------------------------------------------------------------------------------------------------
# velocity mode


def _exact(anchor: int, rpm: int, cpr: int, elapsed_ms: int) -> int:
    """Cruise position computed independently: anchor + round-half-up(rpm * cpr * ms / 60000)."""
    q = Fraction(rpm * cpr * elapsed_ms, 60000)
    return anchor + int((q + Fraction(1, 2)).__floor__())


def _check_chunk(traj: PvtTrajectory) -> None:
    """What the encoder promises, for a trajectory that may end moving."""
    pos = traj.drive_profile()[0]
    dev = np.abs(hermite.round_counts_array(pos) - hermite.round_counts_array(traj.plan.positions))
    assert dev.max() <= traj.tolerance_counts
    assert all(s.acceleration_excess_share <= ACC_EXCESS_LIMIT + 1e-12 for s in traj.stats)
    assert all(1 <= t <= 255 for t in traj.dt_ms.tolist())


def test_velocity_plan_is_open_ended_and_extends_exactly(rotary: CellConfig) -> None:
    job = job_from_dict({"kind": "move", "axes": ["c", "b"], "mode": "velocity", "velocity": [200.0, -45.5]}, rotary)
    traj = plan_job(job, rotary, start=[10.0, 20.0])
    assert traj.open_ended and traj.open_end is not None
    cruise = traj.open_end
    rpm = [int(200.0 * DEG_CPU * 60 / 8192), -int(45.5 * rotary.axes[1].counts_per_unit * 60 / 8192)]
    assert list(cruise.velocity_rpm) == rpm  # whole rpm toward zero
    assert traj.velocities[:, -1].tolist() == rpm
    assert traj.positions[:, 0].tolist() == [round(10.0 * DEG_CPU), round(20.0 * rotary.axes[1].counts_per_unit)]
    assert traj.duration_ms == int(traj.info["velocity_ramp_ms"]) + 2000
    assert traj.summary()["open_ended"] is True
    _check_chunk(traj)
    # no end record: the extension's records follow
    assert traj.records(0)[-1].time_ms == int(traj.dt_ms[-1]) and len(traj.records(0)) == traj.n_segments
    # the plan's velocity reaches the target and stays there (all axes reach it together)
    ramp = int(traj.info["velocity_ramp_ms"])
    conv = traj.counts_per_rev / 60000.0
    want = np.broadcast_to((np.array(rpm) * conv)[:, None], traj.plan.velocities[:, ramp:].shape)
    np.testing.assert_allclose(traj.plan.velocities[:, ramp:], want, rtol=1e-9)
    prev = traj
    total = 0
    lengths = [100, 101, 255, 256, 1000, 2000, 133, 60000]
    for i in range(1000):
        chunk = lengths[i % len(lengths)] if i < 16 else 100 + (i * 37) % 400
        ext = extend_velocity(prev, chunk)
        assert ext.open_ended and ext.duration_ms == chunk
        assert np.array_equal(ext.positions[:, 0], prev.positions[:, -1])
        assert np.array_equal(ext.velocities[:, 0], prev.velocities[:, -1])
        total += chunk
        if i < 16 or i % 97 == 0:
            _check_chunk(ext)
        prev = ext
    for j, c in enumerate(rotary.axes):  # exactly the integer cruise, however it was chunked
        assert int(prev.positions[j, -1]) == _exact(cruise.anchor_counts[j], rpm[j], c.counts_per_rev, total)
    assert isinstance(prev.open_end, CruiseState) and prev.open_end.elapsed_ms == total
    from_state = extend_velocity(prev.open_end, 100).positions[:, -1].tolist()
    assert from_state == extend_velocity(prev, 100).positions[:, -1].tolist()
    with pytest.raises(PlanningError) as e:  # cruise segments this short would shake the acceleration
        extend_velocity(prev, 20)
    assert e.value.code == "LIMITS" and e.value.path == "chunk_ms"


@settings(max_examples=25, deadline=None)
@given(
    rpm=st.integers(-6000, 6000),
    cpr=st.sampled_from([500, 2000, 4096, 8192, 10000]),
    anchor=st.integers(-(2**30), 2**30),
    chunks=st.lists(st.integers(1, 3000), min_size=1, max_size=40),
)
def test_cruise_positions_are_the_exact_integer_sum(rpm: int, cpr: int, anchor: int, chunks: list[int]) -> None:
    data = copy.deepcopy(ROTARY)
    cpu = cpr * 10 / 360.0
    data["axis"] = [dict(data["axis"][0], counts_per_rev=cpr, counts_per_unit=cpu, position_min=-(2**31) / cpu + 1,
                         position_max=(2**31 - 1) / cpu - 1)]
    cell = cell_from_dict(data)
    ax = cell.axes[0]
    cruise = CruiseState(cell, ("c",), (anchor,), (rpm,), 0, (ax.acceleration,), (ax.jerk,), (ax.velocity,),
                         (ax.acceleration,), (ax.acceleration,))
    elapsed = 0
    for chunk in chunks:
        elapsed += chunk
        assert cruise.position_at(elapsed) == [_exact(anchor, rpm, cpr, elapsed)]


def test_velocity_stops_at_the_position_limits(cell: CellConfig) -> None:
    """j1 (limits +-3 rad) at 0.6 rad/s: the chunks go on until a stop from the next one would leave the
    limits; that chunk cruises to the last ms the stop fits and brakes at the job's deceleration."""
    job = job_from_dict({"kind": "move", "axes": ["j1", "j2"], "mode": "velocity", "velocity": [0.6, -0.1],
                         "ramps": {"decel_ms": 500}}, cell)
    traj = plan_job(job, cell)
    chunks = [traj]
    while chunks[-1].open_ended:
        chunks.append(extend_velocity(chunks[-1]))
        assert len(chunks) < 10
    last = chunks[-1]
    assert last.info["position_limit_stop"] == 1.0 and last.info["limit_axis"] == 0.0
    assert np.all(last.velocities[:, -1] == 0) and len(last.records(0)) == last.n_segments + 1
    assert np.array_equal(last.positions[:, 0], chunks[-2].positions[:, -1])
    assert_invariants(last, cell)
    end = last.positions[:, -1] / last.counts_per_unit
    assert 2.95 < end[0] <= 3.0  # stopped inside the limit, close to it
    pos, _vel, acc = last.drive_profile()
    assert pos[0].max() / last.counts_per_unit[0] <= 3.0
    # braking at the deceleration of the ramps (2 rad/s in 0.5 s = 4 rad/s^2), not the axis' 8
    braking = -acc[0] * 1.0e6 / last.counts_per_unit[0]
    assert braking.max() == pytest.approx(4.0, rel=ACC_EXCESS_LIMIT)
    # a velocity job whose ramp alone cannot stop inside the limits is refused
    near = job_from_dict({"kind": "move", "axes": ["j1"], "mode": "velocity", "velocity": [2.0], "start": [2.8]},
                         cell)
    with pytest.raises(PlanningError) as e:
        plan_job(near, cell)
    assert e.value.code == "POSITION_LIMIT" and e.value.path == "velocity[0]" and "'j1'" in e.value.message
    # the first chunk itself closes when the limit comes within it
    short = plan_job(job_from_dict({"kind": "move", "axes": ["j1"], "mode": "velocity", "velocity": [-1.0],
                                    "start": [-1.5]}, cell), cell)
    assert not short.open_ended and short.info["position_limit_stop"] == 1.0
    assert -3.0 <= short.positions[0, -1] / short.counts_per_unit[0] < -2.9


def test_velocity_from_a_moving_state_and_to_rest(cell: CellConfig) -> None:
    axes = ["j1", "j2", "j3"]
    move = plan_job(job_from_dict({"kind": "move", "axes": axes, "target": [1.5, -1.0, 1.0]}, cell),
                    cell, start=[0.0, 0.0, 0.0])
    k = move.n_segments // 3
    state = MotionState.from_knot(move, k)
    vel_job = job_from_dict({"kind": "move", "axes": axes, "mode": "velocity", "velocity": [-0.5, 0.2, 0.0]}, cell)
    traj = plan_velocity(vel_job, cell, state, chunk_ms=500)
    assert np.array_equal(traj.positions[:, 0], move.positions[:, k])
    assert np.array_equal(traj.velocities[:, 0], move.velocities[:, k])
    assert traj.open_ended
    _check_chunk(traj)
    # velocity 0 on every axis: a ramp to rest, closed
    zero = job_from_dict({"kind": "move", "axes": axes, "mode": "velocity", "velocity": [0.0, 0.0, 0.0]}, cell)
    rest = plan_velocity(zero, cell, MotionState.from_knot(traj))
    assert not rest.open_ended and np.all(rest.velocities[:, -1] == 0)
    assert_invariants(rest, cell)
    with pytest.raises(PlanningError) as e:
        extend_velocity(rest)
    assert e.value.code == "SCHEMA"


def test_velocity_job_fields(cell: CellConfig) -> None:
    job = job_from_dict({"kind": "move", "axes": ["j1", "j2"], "mode": "velocity", "velocity": [1.0, -0.5],
                         "ramps": {"accel_ms": 400}}, cell)
    assert job_to_dict(job) == {"kind": "move", "axes": ["j1", "j2"], "velocity": [1.0, -0.5], "mode": "velocity",
                                "ramps": {"accel_ms": 400.0}}
    assert job_from_dict(job_to_dict(job), cell) == job
    cases = [
        ({"velocity": [1.0, 0.0], "target": [0.0, 0.0]}, "SCHEMA", "target"),
        ({}, "SCHEMA", "velocity"),
        ({"velocity": [2.5, 0.0]}, "LIMITS", "velocity[0]"),
        ({"velocity": [1.0, 0.0], "velocity_scale": 0.4}, "LIMITS", "velocity[0]"),
        ({"velocity": [1.0, "x"]}, "TYPE", "velocity[1]"),
        ({"velocity": [1.0]}, "AXIS_COUNT", "velocity"),
    ]
    for extra, code, path in cases:
        with pytest.raises(PlanningError) as e:
            job_from_dict({"kind": "move", "axes": ["j1", "j2"], "mode": "velocity", **extra}, cell)
        assert (e.value.code, e.value.path) == (code, path), (extra, e.value)
    with pytest.raises(PlanningError) as e:
        job_from_dict({"kind": "move", "axes": ["j1"], "target": [0.0], "velocity": [1.0]}, cell)
    assert e.value.code == "SCHEMA" and e.value.path == "velocity"
    with pytest.raises(PlanningError) as e:
        job_from_dict({"kind": "move", "axes": ["j1"], "target": [0.0], "mode": "endless"}, cell)
    assert e.value.code == "SCHEMA" and "additive" in e.value.message and "velocity" in e.value.message
    with pytest.raises(PlanningError) as e:
        job_from_dict({"kind": "move", "axes": ["j1"], "mode": "additive"}, cell)
    assert e.value.code == "SCHEMA" and e.value.path == "target"
    with pytest.raises(PlanningError) as e:
        resolve_target(job, cell, [0.0, 0.0])
    assert e.value.code == "SCHEMA"
    with pytest.raises(PlanningError) as e:
        plan_velocity(job, cell, chunk_ms=0)
    assert e.value.code == "LIMITS" and e.value.path == "chunk_ms"


# ----------------------------------------------------------------------------------------------------
# the cell's travel settings


def test_travel_settings_defaults_and_checks(cell: CellConfig, rotary: CellConfig) -> None:
    j1 = cell.axis("j1")
    assert not j1.is_modulo and rotary.axes[0].is_modulo
    assert j1.emergency_stop_deceleration == 12.0  # 2 x 8, capped at 0x60C5 12
    assert j1.target_window_user == pytest.approx(10 / j1.counts_per_unit)
    assert j1.in_target_timeout_ms == 1000
    tuned = cell_from_dict(_rotary_with(target_window=0.05, in_target_timeout_ms=250))
    assert tuned.axes[0].target_window_user == 0.05 and tuned.axes[0].in_target_timeout_ms == 250
    bad = [
        ({"modulo_tolerance": 180.0}, "LIMITS", "axis[0].modulo_tolerance"),
        ({"modulo_period": 0}, "LIMITS", "axis[0].modulo_period"),
        ({"emergency_deceleration": 2500.0}, "LIMITS", "axis[0].emergency_deceleration"),
        ({"emergency_deceleration": "fast"}, "CONFIG", "axis[0].emergency_deceleration"),
        ({"in_target_timeout_ms": 0}, "LIMITS", "axis[0].in_target_timeout_ms"),
        ({"in_target_timeout_ms": 2.5}, "CONFIG", "axis[0].in_target_timeout_ms"),
        ({"target_window": -1.0}, "LIMITS", "axis[0].target_window"),
        ({"modulo_tolrance": 1.0}, "CONFIG", "axis[0].modulo_tolrance"),
    ]
    for change, code, path in bad:
        with pytest.raises(PlanningError) as e:
            cell_from_dict(_rotary_with(**change))
        assert (e.value.code, e.value.path) == (code, path), (change, e.value)
        assert "'c'" in e.value.message or "axis[0]" in e.value.message
    no_period = copy.deepcopy(ROTARY)
    del no_period["axis"][0]["modulo_period"]
    with pytest.raises(PlanningError) as e:
        cell_from_dict(no_period)
    assert e.value.code == "CONFIG" and e.value.path == "axis[0].modulo_tolerance"
    assert "modulo_period" in e.value.message


@settings(max_examples=30, deadline=None)
@given(data=st.data())
def test_velocity_plans_from_random_states(cell: CellConfig, data: st.DataObject) -> None:
    """From any state inside the limits (moving, accelerating): either a plan that starts exactly at the
    state, stays within the tolerance, the excess budget and the software limits, and cruises at the wire
    velocity; or POSITION_LIMIT naming a velocity field."""
    names = list(cell.axis_names())
    axes = data.draw(st.lists(st.sampled_from(names), min_size=1, max_size=4, unique=True))
    cfg = [cell.axis(a) for a in axes]
    pos = [data.draw(st.floats(0.6 * c.position_min, 0.6 * c.position_max)) for c in cfg]
    vel = [data.draw(st.floats(-0.8, 0.8)) * c.velocity for c in cfg]
    acc = [data.draw(st.floats(-0.8, 0.8)) * c.acceleration for c in cfg]
    want = [data.draw(st.floats(-1.0, 1.0)) * c.velocity for c in cfg]
    cpu = np.array([c.counts_per_unit for c in cfg])
    conv = np.array([c.counts_per_rev / 60000.0 for c in cfg])
    state = MotionState(tuple(int(x) for x in np.round(np.array(pos) * cpu)),
                        tuple(int(x) for x in np.round(np.array(vel) * cpu / 1000.0 / conv)),
                        tuple(float(x) for x in np.array(acc) * cpu / 1.0e6))
    job = job_from_dict({"kind": "move", "axes": axes, "mode": "velocity", "velocity": want}, cell)
    try:
        traj = plan_velocity(job, cell, state, chunk_ms=data.draw(st.integers(100, 3000)))
    except PlanningError as e:
        assert e.code == "POSITION_LIMIT" and e.path.startswith("velocity["), e
        return
    assert traj.positions[:, 0].tolist() == list(state.positions_counts)
    assert traj.velocities[:, 0].tolist() == list(state.velocities_rpm)
    _check_chunk(traj)
    inside = traj.drive_profile()[0] / cpu[:, None]
    assert np.all(inside.min(axis=1) >= [c.position_min - 1e-6 for c in cfg])
    assert np.all(inside.max(axis=1) <= [c.position_max + 1e-6 for c in cfg])
    if traj.open_ended:
        assert traj.velocities[:, -1].tolist() == np.trunc(np.array(want) * cpu / 1000.0 / conv).astype(int).tolist()
    else:
        assert np.all(traj.velocities[:, -1] == 0)


@pytest.mark.parametrize("config", ["xtrapuls.toml", "mixed.toml"])
def test_velocity_on_cyclic_drives(config: str) -> None:
    """Axes fed one set point per SYNC: each chunk's stats are their drive's own interpolation, measured to
    the chunk's end (the motion goes on after it), within the tolerance."""
    cell = load_cell(CONFIGS / config)
    axes = list(cell.axes)
    job = job_from_dict({"kind": "move", "axes": [a.name for a in axes], "mode": "velocity",
                         "velocity": [0.1 * a.velocity * (-1) ** i for i, a in enumerate(axes)]}, cell)
    chunks = [plan_velocity(job, cell, chunk_ms=1000)]
    while chunks[-1].open_ended and len(chunks) < 4:
        chunks.append(extend_velocity(chunks[-1]))
    for prev, chunk in itertools.pairwise(chunks):
        assert np.array_equal(chunk.positions[:, 0], prev.positions[:, -1])
    cyclic = [i for i, a in enumerate(axes) if a.profile != "epos-ipm"]
    assert cyclic
    for chunk in chunks:
        for i in cyclic:
            s = chunk.stats[i]
            assert s.interpolation == axes[i].ip_submode or (axes[i].profile == "cia402-csp" and s.interpolation)
            assert s.setpoint_period_ms == cell.sync_period_ms and s.max_deviation_counts <= chunk.tolerance_counts
