"""Job validation: every job-level row of the API's bad-input table, round trips, job files."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from planner_checks import CONFIGS

from planner.config import CellConfig
from planner.errors import PlanningError
from planner.job import Job, MoveData, PathData, jerk_limited, job_from_dict, job_to_dict, load_job
from planner.plan import plan_job

AX3 = ["j1", "j2", "j3"]


def path(**kw: Any) -> dict[str, Any]:
    job: dict[str, Any] = {
        "kind": "path",
        "axes": AX3,
        "waypoints": [[0, 0, 0], [0.5, -0.2, 0.1], [0.1, 0.1, 0.4]],
    }
    job.update(kw)
    return job


BAD: list[tuple[str, dict[str, Any], str, str, str]] = [
    # (name, job, code, path, text the message must contain)
    ("missing kind", {"axes": AX3}, "SCHEMA", "kind", "kind"),
    ("unknown kind", path(kind="spline"), "SCHEMA", "kind", "spline"),
    ("unknown field", path(speed=3), "SCHEMA", "speed", "speed"),
    ("missing waypoints", {"kind": "path", "axes": AX3}, "SCHEMA", "waypoints", "waypoints"),
    ("missing axes", {"kind": "move", "target": [1]}, "SCHEMA", "axes", "axes"),
    ("non-string key", {**path(), 3: 1}, "SCHEMA", "3", "string"),
    ("string in waypoints", path(waypoints=[[0, 0, 0], [0, "1", 0]]), "TYPE", "waypoints[1][1]", "'j2'"),
    ("bool as number", path(waypoints=[[0, 0, 0], [0, 0, True]]), "TYPE", "waypoints[1][2]", "'j3'"),
    ("huge int", path(waypoints=[[0, 0, 0], [2**60, 0, 0]]), "TYPE", "waypoints[1][0]", "2**53"),
    ("null", path(waypoints=[[0, 0, 0], [None, 0, 0]]), "TYPE", "waypoints[1][0]", "None"),
    ("waypoints not a list", path(waypoints=3), "TYPE", "waypoints", "list"),
    ("kind not a string", path(kind=1), "TYPE", "kind", "string"),
    (
        "NaN",
        path(waypoints=[[0, 0, 0]] * 7 + [[0, 0, math.nan]]),
        "NONFINITE",
        "waypoints[7][2]",
        "waypoints[7][2] of axis 'j3' is NaN",
    ),
    ("infinity", path(waypoints=[[0, 0, 0], [math.inf, 0, 0]]), "NONFINITE", "waypoints[1][0]", "infinity"),
    ("short row", path(waypoints=[[0, 0, 0], [0, 0]]), "AXIS_COUNT", "waypoints[1]", "2 values for 3 axes"),
    (
        "long target",
        {"kind": "move", "axes": AX3, "target": [0, 0, 0, 0]},
        "AXIS_COUNT",
        "target",
        "4 values",
    ),
    ("empty axes", path(axes=[]), "AXIS_COUNT", "axes", "at least one"),
    ("too many axes", path(axes=[f"j{i}" for i in range(1, 8)]), "AXIS_COUNT", "axes", "7 axes"),
    ("scale count", path(velocity_scale=[0.5, 0.5]), "AXIS_COUNT", "velocity_scale", "2 values"),
    ("unknown axis", path(axes=["j1", "j9", "j3"]), "AXIS_ID", "axes[1]", "'j9'"),
    ("duplicate axis", path(axes=["j1", "j2", "j1"]), "AXIS_ID", "axes[2]", "twice"),
    ("axis not a string", path(axes=["j1", 2, "j3"]), "TYPE", "axes[1]", "axis name"),
    ("one waypoint", path(waypoints=[[0, 0, 0]]), "DEGENERATE", "waypoints", "2 distinct"),
    ("identical waypoints", path(waypoints=[[0.1, 0, 0]] * 3), "DEGENERATE", "waypoints", "2 distinct"),
    (
        "timed one row",
        {"kind": "timed", "axes": ["j1"], "times": [0], "positions": [[0]]},
        "DEGENERATE",
        "times",
        "2 rows",
    ),
    (
        "times equal",
        {"kind": "timed", "axes": ["j1"], "times": [0, 1, 1], "positions": [[0], [0.1], [0.2]]},
        "NON_MONOTONIC",
        "times[2]",
        "strictly increase",
    ),
    (
        "times backwards",
        {
            "kind": "pvt",
            "axes": ["j1"],
            "times": [0, 0.2, 0.1],
            "positions": [[0], [0], [0]],
            "velocities": [[0], [0], [0]],
        },
        "NON_MONOTONIC",
        "times[2]",
        "times[2]",
    ),
    (
        "negative time",
        {"kind": "timed", "axes": ["j1"], "times": [-1, 1], "positions": [[0], [0.1]]},
        "NON_MONOTONIC",
        "times[0]",
        ">= 0",
    ),
    ("scale zero", path(velocity_scale=0), "LIMITS", "velocity_scale", "(0, 1]"),
    ("scale above one", path(acceleration_scale=[1, 1.5, 1]), "LIMITS", "acceleration_scale[1]", "'j2'"),
    ("tolerance zero", path(tolerance_counts=0), "LIMITS", "tolerance_counts", "whole number"),
    ("tolerance negative", path(tolerance_counts=-2), "LIMITS", "tolerance_counts", "-2"),
    ("tolerance fraction", path(tolerance_counts=1.5), "LIMITS", "tolerance_counts", "1.5"),
    ("limit zero", path(limits={"velocity": [1, 0, 1]}), "LIMITS", "limits.velocity[1]", "'j2'"),
    ("limit negative", path(limits={"jerk": [1, 1, -5]}), "LIMITS", "limits.jerk[2]", "-5"),
    ("unknown limit", path(limits={"torque": [1, 1, 1]}), "SCHEMA", "limits.torque", "torque"),
    (
        "outside soft limits",
        path(waypoints=[[0, 0, 0], [0, 2.5, 0]]),
        "POSITION_LIMIT",
        "waypoints[1][1]",
        "'j2' is 2.5",
    ),
    (
        "move target outside",
        {"kind": "move", "axes": ["j1"], "target": [-3.5]},
        "POSITION_LIMIT",
        "target[0]",
        "-3.5",
    ),
    (
        "velocity above 0x607F",
        path(limits={"velocity": [1, 1, 20]}),
        "LIMITS_EXCEED_DRIVE",
        "limits.velocity[2]",
        "0x607F",
    ),
    (
        "acceleration above 0x60C5",
        path(limits={"acceleration": [13, 1, 1]}),
        "LIMITS_EXCEED_DRIVE",
        "limits.acceleration[0]",
        "0x60C5",
    ),
    (
        "pvt segment too long",
        {"kind": "pvt", "axes": ["j1"], "times": [0, 0.3], "positions": [[0], [0]], "velocities": [[0], [0]]},
        "ENCODING_RANGE",
        "times[1]",
        "300 ms",
    ),
    (
        "pvt fractional ms",
        {
            "kind": "pvt",
            "axes": ["j1"],
            "times": [0, 0.0105],
            "positions": [[0], [0]],
            "velocities": [[0], [0]],
        },
        "ENCODING_RANGE",
        "times[1]",
        "10.5 ms",
    ),
    (
        "pvt velocity beyond int24",
        {
            "kind": "pvt",
            "axes": ["j1"],
            "times": [0, 0.01],
            "positions": [[0], [0]],
            "velocities": [[0], [1e5]],
        },
        "ENCODING_RANGE",
        "velocities[1][0]",
        "int24",
    ),
    ("limit -inf", path(limits={"velocity": [1, -math.inf, 1]}), "NONFINITE", "limits.velocity[1]", "'j2'"),
    ("path_tolerance negative", path(path_tolerance=-0.1), "LIMITS", "path_tolerance", ">= 0"),
    (
        "path_tolerance of one axis negative",
        path(path_tolerance=[0.1, -0.2, 0.1]),
        "LIMITS",
        "path_tolerance[1]",
        "'j2'",
    ),
    ("path_tolerance NaN", path(path_tolerance=[0.1, 0.1, math.nan]), "NONFINITE", "path_tolerance[2]", "'j3'"),
    ("path_tolerance count", path(path_tolerance=[0.1, 0.1]), "AXIS_COUNT", "path_tolerance", "2 values"),
    ("path_tolerance a string", path(path_tolerance="tight"), "TYPE", "path_tolerance", "number"),
    ("geometry unknown", path(geometry="bezier"), "SCHEMA", "geometry", "bezier"),
    ("geometry not a string", path(geometry=1), "TYPE", "geometry", "string"),
    ("tolerance with a spline", path(geometry="spline", path_tolerance=0.1), "SCHEMA", "path_tolerance", "spline"),
    (
        "path_tolerance on a move",
        {"kind": "move", "axes": ["j1"], "target": [0.1], "path_tolerance": 0.1},
        "SCHEMA",
        "path_tolerance",
        "path_tolerance",
    ),
    ("job_id not a string", path(job_id=5), "TYPE", "job_id", "string"),
    ("job_id with slash", path(job_id="a/b"), "SCHEMA", "job_id", "not allowed"),
    (
        "mode",
        {"kind": "move", "axes": ["j1"], "target": [1], "mode": "sideways"},
        "SCHEMA",
        "mode",
        "sideways",
    ),
]


@pytest.mark.parametrize("name,job,code,path_,text", BAD, ids=[b[0] for b in BAD])
def test_bad_input(
    cell: CellConfig, name: str, job: dict[str, Any], code: str, path_: str, text: str
) -> None:
    with pytest.raises(PlanningError) as e:
        job_from_dict(job, cell)
    assert e.value.code == code, e.value
    assert e.value.path == path_, e.value
    assert text in e.value.message, e.value


def test_too_large(cell: CellConfig) -> None:
    with pytest.raises(PlanningError) as e:
        job_from_dict(path(waypoints=[[0, 0, 0]] * 11), cell, max_rows=10)
    assert e.value.code == "TOO_LARGE" and e.value.path == "waypoints"
    big = {"kind": "timed", "axes": ["j1"], "times": [0, 1000.0], "positions": [[0], [0.1]]}
    with pytest.raises(PlanningError) as e:
        job_from_dict(big, cell)
    assert e.value.code == "TOO_LARGE"


def test_software_limits_beyond_int32_counts_are_refused_with_the_cell(cell: CellConfig) -> None:
    # software limits wider than int32 counts would let a job ask for a position the drive cannot hold:
    # the cell is refused when it is made (loaded), naming the axis, the limit and its counts
    import dataclasses

    with pytest.raises(PlanningError) as e:
        dataclasses.replace(cell.axes[0], position_min=-1e5, position_max=1e5)
    assert e.value.code == "LIMITS" and e.value.path == "axis.position_min"
    assert "'j1'" in e.value.message and "int32" in e.value.message and "-6518986000 counts" in e.value.message


def test_not_a_mapping(cell: CellConfig) -> None:
    with pytest.raises(PlanningError) as e:
        job_from_dict([1, 2], cell)  # type: ignore[arg-type]
    assert e.value.code == "SCHEMA"


def test_defaults_and_fields(cell: CellConfig) -> None:
    job = job_from_dict(
        path(
            job_id="abc-1",
            tolerance_counts=2.0,
            velocity_scale=0.5,
            acceleration_scale=[1, 0.5, 0.25],
            limits={"jerk": [10, 10, 10]},
        ),
        cell,
    )
    assert job.kind == "path" and job.axes == tuple(AX3) and job.job_id == "abc-1"
    assert job.tolerance_counts == 2 and isinstance(job.tolerance_counts, int)
    assert job.velocity_scale == (0.5, 0.5, 0.5) and job.acceleration_scale == (1.0, 0.5, 0.25)
    assert job.jerk_limit == (10.0, 10.0, 10.0) and job.velocity_limit is None
    assert isinstance(job.data, PathData) and not job.data.waypoints.flags.writeable
    assert job.data.geometry == "lines" and job.data.path_tolerance is None
    tol = job_from_dict(path(path_tolerance=0.01), cell)
    assert isinstance(tol.data, PathData) and tol.data.path_tolerance == (0.01, 0.01, 0.01)
    assert job_to_dict(tol)["path_tolerance"] == 0.01  # one value stays one value
    per_axis = job_from_dict(path(path_tolerance=[0.01, 0, 0.5], geometry="lines"), cell)
    assert job_to_dict(per_axis)["path_tolerance"] == [0.01, 0.0, 0.5] and "geometry" not in job_to_dict(per_axis)
    spline = job_from_dict(path(geometry="spline"), cell)
    assert isinstance(spline.data, PathData) and spline.data.geometry == "spline"
    assert job_to_dict(spline)["geometry"] == "spline"
    plain = job_from_dict(path(), cell)  # every axis of the cell has a jerk limit: jerk-limited, 2 counts
    assert plain.tolerance_counts == 2 and plain.velocity_scale == (1.0, 1.0, 1.0)
    assert jerk_limited(plain, cell) and isinstance(plain.data, PathData) and plain.data.jerk_limited is None
    off = job_from_dict(path(jerk_limited=False), cell)
    assert off.tolerance_counts == 1 and not jerk_limited(off, cell)
    move = job_from_dict({"kind": "move", "axes": ["j1"], "target": [0.5]}, cell)
    assert isinstance(move.data, MoveData) and move.data.mode == "absolute" and move.data.start is None


def test_job_constructor_validates() -> None:
    with pytest.raises(PlanningError) as e:
        Job("path", ("j1",), PathData(np.array([[0.0], [np.nan]])))
    assert e.value.code == "NONFINITE"
    with pytest.raises(PlanningError):
        Job("move", ("j1",), PathData(np.zeros((2, 1))))  # data of the wrong kind
    with pytest.raises(PlanningError):
        Job("path", ("j1", "j1"), PathData(np.zeros((2, 2))))


finite = st.floats(-0.9, 0.9, allow_nan=False, width=64)


@st.composite
def job_dicts(draw: st.DrawFn) -> dict[str, Any]:
    n = draw(st.integers(1, 6))
    axes = draw(st.permutations(["j1", "j2", "j3", "j4", "j5", "j6"]))[:n]
    kind = draw(st.sampled_from(["path", "move", "timed", "pvt"]))
    out: dict[str, Any] = {"kind": kind, "axes": list(axes)}
    rows = draw(st.integers(2, 5))
    if kind == "path":
        wp = [[draw(finite) for _ in range(n)] for _ in range(rows)]
        wp[1][0] = wp[0][0] + 0.5
        out["waypoints"] = wp
        geometry = draw(st.sampled_from(["default", "lines", "spline"]))
        if geometry != "default":
            out["geometry"] = geometry
        if geometry != "spline" and draw(st.booleans()):
            out["path_tolerance"] = (
                draw(st.floats(0.0, 0.1)) if draw(st.booleans()) else [draw(st.floats(0.0, 0.1)) for _ in range(n)]
            )
    elif kind == "move":
        out["target"] = [draw(finite) for _ in range(n)]
        out["mode"] = draw(st.sampled_from(["absolute", "relative"]))
        if draw(st.booleans()):
            out["start"] = [draw(st.floats(-0.05, 0.05)) for _ in range(n)]
    else:
        out["times"] = [0.01 * k for k in range(rows)]
        out["positions"] = [[draw(finite) for _ in range(n)] for _ in range(rows)]
        if kind == "pvt":
            out["velocities"] = [[draw(finite) for _ in range(n)] for _ in range(rows)]
    if draw(st.booleans()):
        out["velocity_scale"] = draw(st.floats(0.1, 1.0))
    if draw(st.booleans()):
        out["acceleration_scale"] = [draw(st.floats(0.1, 1.0)) for _ in range(n)]
    if draw(st.booleans()):
        out["tolerance_counts"] = draw(st.integers(2, 5))
    if draw(st.booleans()):
        out["job_id"] = draw(st.from_regex(r"[a-z0-9_-]{1,20}", fullmatch=True))
    if draw(st.booleans()):
        out["limits"] = {"jerk": [draw(st.floats(1, 100)) for _ in range(n)]}
    return out


@given(job_dicts())
def test_round_trip(cell: CellConfig, data: dict[str, Any]) -> None:
    job = job_from_dict(data, cell)
    again = job_from_dict(job_to_dict(job), cell)
    assert again == job
    assert job_to_dict(again) == job_to_dict(job)
    # plain data: JSON-able
    assert json.loads(json.dumps(job_to_dict(job))) == job_to_dict(job)


def test_example_files_load(cell: CellConfig) -> None:
    files = sorted((CONFIGS / "jobs").iterdir())
    kinds = {load_job(f, cell).kind for f in files}
    assert kinds == {"path", "move", "timed", "pvt"}
    assert any(f.suffix == ".json" for f in files) and any(f.suffix == ".toml" for f in files)
    assert (CONFIGS / "jobs" / "demo-path.toml").exists()


def test_load_job_errors(cell: CellConfig, tmp_path: Path) -> None:
    with pytest.raises(PlanningError) as e:
        load_job(tmp_path / "missing.toml", cell)
    assert e.value.code == "SCHEMA"
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(PlanningError) as e:
        load_job(bad, cell)
    assert e.value.code == "SCHEMA"
    toml = tmp_path / "nan.toml"
    toml.write_text('kind = "path"\naxes = ["j1"]\nwaypoints = [[0.0], [nan]]\n')
    with pytest.raises(PlanningError) as e:
        load_job(toml, cell)
    assert e.value.code == "NONFINITE" and e.value.path == "waypoints[1][0]"


def test_axis_names_from_numpy_are_plain_strings_in_the_job_and_its_messages(cell: CellConfig) -> None:
    """A Python caller may pass numpy strings (np.str_ is a str): the job keeps plain ones, so messages
    name the axis as 'j1', not np.str_('j1')."""
    axes = list(np.array(["j1", "j2"]))
    job = job_from_dict({"kind": "timed", "axes": axes, "times": [0.0, 0.02],
                         "positions": [[0.0, 0.0], [0.01, 0.0]]}, cell)
    assert all(type(a) is str for a in job.axes)
    with pytest.raises(PlanningError) as e:
        plan_job(job, cell)
    assert "axis 'j1' needs an acceleration" in e.value.message and "np.str_" not in e.value.message
