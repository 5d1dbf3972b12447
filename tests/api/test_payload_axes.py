"""Per-axis values outside the rows name their axis too (issue 13): `limits.*[i]` and `path_tolerance[i]`,
and the path job's `path_tolerance` / `geometry` pass the API to the planner's validator."""

from __future__ import annotations

import msgpack
import pytest

from planner.config import CellConfig
from planner.job import PathData, job_from_dict
from streamer.api.errors import MotionError
from streamer.api.payload import decode_submission, pack

PATH = {"kind": "path", "axes": ["j1", "j2", "j3"], "waypoints": [[0.0, 0.0, 0.0], [0.1, 0.2, 0.3]]}


@pytest.mark.parametrize(
    "body, path, words",
    [
        ({**PATH, "limits": {"velocity": [1.0, float("-inf"), 1.0]}}, "limits.velocity[1]",
         "limits.velocity[1] of axis 'j2' is -inf"),
        ({**PATH, "limits": {"jerk": [1.0, 1.0, float("nan")]}}, "limits.jerk[2]", "of axis 'j3' is NaN"),
        ({**PATH, "path_tolerance": [0.1, 0.1, float("inf")]}, "path_tolerance[2]",
         "path_tolerance[2] of axis 'j3' is inf"),
    ],
)
def test_nonfinite_per_axis_values_name_the_axis(body: dict[str, object], path: str, words: str) -> None:
    with pytest.raises(MotionError) as info:
        decode_submission(msgpack.packb(body, use_bin_type=True))
    assert info.value.code == "NONFINITE" and info.value.path == path
    assert words in info.value.message


def test_path_tolerance_and_geometry_reach_the_planner(demo_cell: CellConfig) -> None:
    sub = decode_submission(pack({**PATH, "path_tolerance": [0.01, 0.0, 0.02]}))
    job = job_from_dict(sub.body, demo_cell)
    assert isinstance(job.data, PathData) and job.data.path_tolerance == (0.01, 0.0, 0.02)
    sub = decode_submission(pack({**PATH, "geometry": "spline"}))
    job = job_from_dict(sub.body, demo_cell)
    assert isinstance(job.data, PathData) and job.data.geometry == "spline"
