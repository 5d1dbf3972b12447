"""Job field readers: one field of a decoded job mapping -> checked numbers, or exactly what is wrong.

Theory of operation. planner/job.py hands each raw value here with its path ("waypoints[7][2]"); a reader
returns float64 numbers (scalar, per-axis vector, rows, series) or a checked string, or raises a
`PlanningError` (TYPE, NONFINITE, AXIS_COUNT, TOO_LARGE, LIMITS, SCHEMA) naming the field, the axis and
the value. Booleans are not numbers; integers beyond 2**53, NaN and infinity are refused. Which fields a
kind has stays in planner/job.py.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from planner.config import check_name
from planner.errors import AXIS_COUNT, LIMITS, NONFINITE, SCHEMA, TOO_LARGE, TYPE, PlanningError
from planner.motion.reference import FloatArray

MAX_EXACT_INT = 2**53  # larger integers are not exact as float64 (TYPE)
MAX_TEXT = 1000  # characters of a free text field (description)


def read_number(value: Any, path: str, what: str = "") -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise PlanningError(TYPE, f"{path}{what} must be a number, got {show(value)}", path=path)
    if isinstance(value, int):
        if abs(value) > MAX_EXACT_INT:
            raise PlanningError(
                TYPE, f"{path}{what} = {value} is too large (integers must be within +-2**53)", path=path
            )
        return float(value)
    if not math.isfinite(value):
        raise PlanningError(NONFINITE, f"{path}{what} is {nan_name(value)}", path=path)
    return float(value)


def show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def nan_name(value: float) -> str:
    return "NaN" if math.isnan(value) else ("infinity" if value > 0 else "-infinity")


def axis_note(axes: Sequence[str], j: int) -> str:
    return f" of axis {axes[j]!r}" if 0 <= j < len(axes) else ""


def read_vector(value: Any, path: str, axes: Sequence[str]) -> FloatArray:
    """A list with one number per axis."""
    if not isinstance(value, list | tuple):
        raise PlanningError(
            TYPE, f"{path} must be a list of {len(axes)} numbers, got {show(value)}", path=path
        )
    if len(value) != len(axes):
        raise PlanningError(
            AXIS_COUNT, f"{path} has {len(value)} values for {len(axes)} axes {list(axes)!r}", path=path
        )
    return np.array([read_number(v, f"{path}[{j}]", axis_note(axes, j)) for j, v in enumerate(value)])


def check_list(value: Any, path: str, items: str, what: str, max_rows: int) -> None:
    """TYPE unless `value` is a list, TOO_LARGE when it has more than `max_rows` items."""
    if not isinstance(value, list | tuple):
        raise PlanningError(TYPE, f"{path} must be {what}, got {show(value)}", path=path)
    if len(value) > max_rows:
        raise PlanningError(
            TOO_LARGE,
            f"{path} has {len(value)} {items}, more than the limit of {max_rows}",
            path=path,
            detail={"rows": len(value), "limit": max_rows},
        )


def read_matrix(value: Any, path: str, axes: Sequence[str], max_rows: int) -> FloatArray:
    """A list of rows, one number per axis in each row (fast path through numpy, exact errors after)."""
    check_list(value, path, "rows", "a list of rows", max_rows)
    n = len(axes)
    if all(isinstance(row, list | tuple) and len(row) == n for row in value):
        flat = [x for row in value for x in row]
        if all(type(x) is float or (type(x) is int and abs(x) <= MAX_EXACT_INT) for x in flat):
            arr = np.array(flat, dtype=np.float64).reshape(len(value), n)
            if np.all(np.isfinite(arr)):
                return arr
    # slow path: find and name the first bad element
    out = np.empty((len(value), n))
    for i, row in enumerate(value):
        rp = f"{path}[{i}]"
        if not isinstance(row, list | tuple):
            raise PlanningError(TYPE, f"{rp} must be a list of {n} numbers, got {show(row)}", path=rp)
        if len(row) != n:
            raise PlanningError(
                AXIS_COUNT, f"{rp} has {len(row)} values for {n} axes {list(axes)!r}", path=rp
            )
        for j, x in enumerate(row):
            out[i, j] = read_number(x, f"{rp}[{j}]", axis_note(axes, j))
    return out


def read_series(value: Any, path: str, max_rows: int) -> FloatArray:
    check_list(value, path, "values", "a list of numbers", max_rows)
    return np.array([read_number(x, f"{path}[{i}]") for i, x in enumerate(value)], dtype=np.float64)


def read_scale(value: Any, path: str, axes: Sequence[str]) -> tuple[tuple[float, ...], bool]:
    if isinstance(value, list | tuple):
        vals = read_vector(value, path, axes)
        scalar = False
    else:
        vals = np.full(len(axes), read_number(value, path))
        scalar = True
    for j, v in enumerate(vals):
        if not 0.0 < v <= 1.0:
            p = path if scalar else f"{path}[{j}]"
            raise PlanningError(
                LIMITS,
                f"{p}{'' if scalar else axis_note(axes, j)} is {v:g}; scales must be in (0, 1]",
                path=p,
            )
    return tuple(float(v) for v in vals), scalar


def read_text(value: Any, path: str, *, job_id: bool = False) -> str:
    if not isinstance(value, str):
        raise PlanningError(TYPE, f"{path} must be a string, got {show(value)}", path=path)
    if job_id:  # the one rule of names (planner/config.py), the same in the job API and the CLI
        return check_name(value, path, path=path)
    if len(value) > MAX_TEXT:
        raise PlanningError(SCHEMA, f"{path} must be 0..{MAX_TEXT} characters long", path=path)
    if any(ord(c) < 32 and c not in "\n\t" for c in value):
        raise PlanningError(
            SCHEMA, f"{path} {value!r} contains a character that is not allowed (no control characters)", path=path
        )
    return value



def read_per_axis(value: Any, path: str, axes: Sequence[str]) -> tuple[tuple[float, ...], bool]:
    """One number for every axis, or one per axis: (values, given as one number)."""
    if isinstance(value, list | tuple):
        return tuple(float(v) for v in read_vector(value, path, axes)), False
    return (read_number(value, path),) * len(axes), True
