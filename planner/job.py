"""Motion jobs: the validated, immutable description of one motion (TOML, JSON, or the API's msgpack).

Theory of operation. `job_from_dict(data, cell)` checks everything that can be checked without planning
and rejects the first problem with a `PlanningError` whose `code` is stable and whose `path` names the
field ("waypoints[7][2]"). It returns a frozen `Job` of read-only float64 arrays: nothing downstream
re-validates. `job_to_dict` is its inverse, `load_job` reads a file; one field's readers are
planner/fields.py. Kinds: path (waypoints, blended or spline), move (a travel command's target, or
endless velocity), timed (the user's timing), pvt (raw rows), home (the drives reference themselves).
docs/formats.md, section 2, is the schema.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np

from planner.config import HOMING_METHODS, AxisConfig, CellConfig
from planner.encoding.record import POSITION_MAX, POSITION_MIN, SEGMENT_TIME_MAX_MS, VELOCITY_MAX, VELOCITY_MIN
from planner.errors import (
    AXIS_COUNT,
    AXIS_ID,
    DEGENERATE,
    ENCODING_RANGE,
    LIMITS,
    LIMITS_EXCEED_DRIVE,
    MODULO_RANGE,
    NON_MONOTONIC,
    NONFINITE,
    POSITION_LIMIT,
    SCHEMA,
    TOO_LARGE,
    TYPE,
    PlanningError,
)
from planner.fields import (
    axis_note,
    nan_name,
    read_matrix,
    read_number,
    read_per_axis,
    read_scale,
    read_series,
    read_text,
    read_vector,
    show,
)
from planner.limits import AxisLimits
from planner.motion.reference import FloatArray

Kind = Literal["path", "move", "timed", "pvt", "home"]
KINDS: tuple[str, ...] = ("path", "move", "timed", "pvt", "home")
MoveMode = Literal[
    "absolute", "relative", "additive", "velocity", "modulo_short", "modulo_plus", "modulo_minus", "modulo_current"
]
MOVE_MODES: tuple[str, ...] = (
    "absolute", "relative", "additive", "velocity", "modulo_short", "modulo_plus", "modulo_minus", "modulo_current"
)
MODULO_MODES: tuple[str, ...] = ("modulo_short", "modulo_plus", "modulo_minus", "modulo_current")
OFFSET_MODES: tuple[str, ...] = ("relative", "additive")  # target is an offset (from the actual / last target)
RAMP_KEYS = ("accel_ms", "decel_ms")
MAX_RAMP_MS = 600_000.0
MAX_ROWS = 100_000  # waypoints / rows per job (TOO_LARGE above)
HOME_TIMEOUT_S = 120.0  # the master's default wait for homing attained / error
MAX_HOME_TIMEOUT_S = 3600.0
MAX_DURATION_S = 900.0  # user timing (timed/pvt) longer than this is TOO_LARGE
MAX_TOLERANCE_COUNTS = 1_000_000
GEOMETRIES: tuple[str, ...] = ("lines", "spline")
# a jerk-limited path's timing (docs/formats.md, "jerk_timing"): knots within the jerk bound, or shortest
JERK_TIMINGS: tuple[str, ...] = ("smooth", "fastest")
# a path job without `jerk_limited` keeps the jerk limits when every axis of the job has one (every axis
# of a cell states one: planner/config.py); False plans the acceleration-only optimum
JERK_LIMITED_DEFAULT = True
# the default `tolerance_counts` of a jerk-limited path: the drive's units need the room (docs/formats.md,
# "jerk_limited"). A cruise between two whole rpm values keeps its acceleration continuous only by bowing
# its position: step x bow >= q^2 / 4 (q counts/ms per rpm), 0.9-1.2 x the bound J x 1 ms on the demo
# cell's 50:1 axes with a bow of one count; a second count halves it
JERK_TOLERANCE_COUNTS = 2
DEFAULT_PATH_TOLERANCE_SHARE = 1.0e-2  # of the axis' travel (position_max - position_min)

_COMMON = {
    "kind",
    "axes",
    "job_id",
    "description",
    "tolerance_counts",
    "velocity_scale",
    "acceleration_scale",
    "limits",
}
_KIND_FIELDS: dict[str, tuple[set[str], set[str]]] = {  # (required, optional) besides the common ones
    "path": ({"waypoints"}, {"path_tolerance", "geometry", "jerk_limited", "jerk_timing"}),
    "move": (set(), {"target", "mode", "start", "velocity", "ramps"}),  # target or velocity: by mode
    "timed": ({"times", "positions"}, set()),
    "pvt": ({"times", "positions", "velocities"}, set()),
    "home": ({"method"}, {"search_speed", "zero_speed", "acceleration", "offset", "timeout_s"}),
}
_LIMIT_KEYS = ("velocity", "acceleration", "jerk")


def job_fields(kind: str) -> tuple[frozenset[str], frozenset[str]]:
    """(required, optional) top-level fields of a job of `kind` as `job_from_dict` takes them (a move needs
    `target`, or `velocity` in velocity mode: both optional here). KeyError for an unknown kind."""
    required, optional = _KIND_FIELDS[kind]
    common = _HOME_COMMON if kind == "home" else _COMMON
    extra = {"start"} if kind == "path" else set()
    return frozenset({"kind", "axes"} | required), frozenset((common | optional | extra) - {"kind", "axes"})
# `start = "current"` (path and move jobs): plan from where the axes stand. The planner itself plans a path
# from its first waypoint (and a move from the caller's start); the job service, which knows where the axes
# stand, prepends that position to a path whose first waypoint is elsewhere (docs/api.md section 3).
START_CURRENT = "current"


def _ro(a: FloatArray) -> FloatArray:
    out = np.array(a, dtype=np.float64, copy=True)
    out.setflags(write=False)
    return out


def _eq_arrays(a: FloatArray | None, b: FloatArray | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return a.shape == b.shape and bool(np.array_equal(a, b))


@dataclass(frozen=True, eq=False)
class PathData:
    waypoints: FloatArray  # (n_waypoints, n_axes), user units
    geometry: Literal["lines", "spline"] = "lines"
    path_tolerance: tuple[float, ...] | None = None  # per axis, user units; None = the default
    scalar_tolerance: bool = False  # given as one number (kept for job_to_dict)
    # keep every axis' jerk limit (planner/motion/jerkpath.py); None: the default (`jerk_limited_default`)
    jerk_limited: bool | None = None
    jerk_timing: Literal["smooth", "fastest"] | None = None  # a jerk-limited path's timing; None: "smooth"


@dataclass(frozen=True)
class Ramps:
    """Seed 002's ramp times (ms for 0 -> 100 % of the axis' speed range, here its velocity limit), per axis.
    One of the two given alone serves both; `scalar` remembers a single number (for job_to_dict)."""

    accel_ms: tuple[float, ...]
    decel_ms: tuple[float, ...]
    given: tuple[bool, bool] = (True, True)  # accel_ms, decel_ms given in the job
    scalar: tuple[bool, bool] = (False, False)


@dataclass(frozen=True, eq=False)
class MoveData:
    # (n_axes,), user units: the absolute target, or the offset (relative, additive), or the modulo
    # position (modulo modes); zeros in velocity mode (the job has no target: `velocity` instead)
    target: FloatArray
    mode: MoveMode = "absolute"
    start: FloatArray | None = None  # (n_axes,) assumed start when the caller gives none
    velocity: FloatArray | None = None  # (n_axes,) user units/s, signed: velocity mode only
    ramps: Ramps | None = None


@dataclass(frozen=True, eq=False)
class TimedData:
    times: FloatArray  # (n,), s, strictly increasing
    positions: FloatArray  # (n, n_axes), user units


@dataclass(frozen=True, eq=False)
class PvtData:
    times: FloatArray  # (n,), s; intervals whole ms in 1..255
    positions: FloatArray  # (n, n_axes), user units
    velocities: FloatArray  # (n, n_axes), user units/s


@dataclass(frozen=True, eq=False)
class HomeData:
    """A home job, per axis: 0x6098 method, 0x6099:01/02 speeds (user units/s), 0x609A acceleration (user
    units/s^2), 0x607C offset (user units); the time the master waits for the drives (s)."""

    method: tuple[int, ...]
    search_speed: tuple[float, ...]
    zero_speed: tuple[float, ...]
    acceleration: tuple[float, ...]
    offset: tuple[float, ...]
    timeout_s: float = HOME_TIMEOUT_S


JobData = PathData | MoveData | TimedData | PvtData | HomeData
_DATA_TYPES: dict[str, type] = {"path": PathData, "move": MoveData, "timed": TimedData, "pvt": PvtData,
                                "home": HomeData}


@dataclass(frozen=True, eq=False)
class Job:
    """One validated motion job. Arrays are read-only float64; per-axis tuples follow `axes`."""

    kind: Kind
    axes: tuple[str, ...]
    data: JobData
    tolerance_counts: int = 1
    velocity_scale: tuple[float, ...] = ()  # () = 1.0 for every axis
    acceleration_scale: tuple[float, ...] = ()
    velocity_limit: tuple[float, ...] | None = None  # per-axis overrides (user units/s), None = config
    acceleration_limit: tuple[float, ...] | None = None
    jerk_limit: tuple[float, ...] | None = None
    job_id: str | None = None
    description: str | None = None
    _scalar_scales: tuple[bool, bool] = field(default=(False, False), repr=False)

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise PlanningError(SCHEMA, f"kind must be one of {list(KINDS)}, got {self.kind!r}", path="kind")
        if not isinstance(self.data, _DATA_TYPES[self.kind]):
            raise PlanningError(
                SCHEMA,
                f"a {self.kind} job needs {_DATA_TYPES[self.kind].__name__}, got {type(self.data).__name__}",
                path="kind",
            )
        n = len(self.axes)
        if n == 0:
            raise PlanningError(AXIS_COUNT, "a job needs at least one axis", path="axes")
        if len(set(self.axes)) != n:
            raise PlanningError(AXIS_ID, f"duplicate axis names in {list(self.axes)!r}", path="axes")
        for name in ("velocity_scale", "acceleration_scale"):
            v = getattr(self, name)
            if v == ():
                object.__setattr__(self, name, (1.0,) * n)
            elif len(v) != n:
                raise PlanningError(AXIS_COUNT, f"{name} has {len(v)} values for {n} axes", path=name)
        for name in ("velocity_limit", "acceleration_limit", "jerk_limit"):
            v = getattr(self, name)
            if v is not None and len(v) != n:
                raise PlanningError(AXIS_COUNT, f"{name} has {len(v)} values for {n} axes", path=name)
        if not (
            isinstance(self.tolerance_counts, int) and 1 <= self.tolerance_counts <= MAX_TOLERANCE_COUNTS
        ):
            raise PlanningError(
                LIMITS,
                f"tolerance_counts must be a whole number of counts in 1..."
                f"{MAX_TOLERANCE_COUNTS}, got {self.tolerance_counts!r}",
                path="tolerance_counts",
            )
        for f_name, arr in _arrays(self.data):
            if arr is None:
                continue
            if not np.all(np.isfinite(arr)):
                raise PlanningError(NONFINITE, f"{f_name} contains NaN or infinity", path=f_name)
            want = n if arr.ndim == 1 and f_name in ("target", "start", "velocity") else None
            if arr.ndim == 2 and arr.shape[1] != n:
                raise PlanningError(
                    AXIS_COUNT, f"{f_name} rows have {arr.shape[1]} values for {n} axes", path=f_name
                )
            if want is not None and arr.shape != (n,):
                raise PlanningError(
                    AXIS_COUNT, f"{f_name} has {arr.shape[0]} values for {n} axes", path=f_name
                )
        if isinstance(self.data, PathData):
            _check_path_options(self.data, self.axes)
        if isinstance(self.data, MoveData):
            if self.data.mode not in MOVE_MODES:
                raise PlanningError(SCHEMA, f"mode must be one of {list(MOVE_MODES)}, got {self.data.mode!r}",
                                    path="mode")
            if (self.data.mode == "velocity") != (self.data.velocity is not None):
                raise PlanningError(SCHEMA, "velocity goes with mode 'velocity', and only with it", path="velocity")
            if self.data.ramps is not None and self.acceleration_limit is not None:
                raise PlanningError(SCHEMA, "ramps and limits.acceleration both set the acceleration: give one",
                                    path="ramps")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Job):
            return NotImplemented
        return job_to_dict(self) == job_to_dict(other)

    __hash__ = None  # type: ignore[assignment]

    @property
    def n_axes(self) -> int:
        return len(self.axes)


def _check_path_options(data: PathData, axes: Sequence[str]) -> None:
    if data.geometry not in GEOMETRIES:
        raise PlanningError(
            SCHEMA, f"geometry must be one of {list(GEOMETRIES)}, got {data.geometry!r}", path="geometry"
        )
    if data.jerk_timing is not None and data.jerk_timing not in JERK_TIMINGS:
        raise PlanningError(SCHEMA, f"jerk_timing must be one of {list(JERK_TIMINGS)}, got {data.jerk_timing!r}",
                            path="jerk_timing")
    if data.jerk_timing == "fastest" and data.jerk_limited is False:
        raise PlanningError(SCHEMA, "jerk_timing applies to a jerk-limited path, and jerk_limited is false",
                            path="jerk_timing")
    tol = data.path_tolerance
    if tol is None:
        return
    if data.geometry != "lines":
        raise PlanningError(
            SCHEMA,
            "path_tolerance applies to the straight segments (geometry 'lines'); a spline passes "
            "through every waypoint",
            path="path_tolerance",
        )
    if len(tol) != len(axes):
        raise PlanningError(
            AXIS_COUNT, f"path_tolerance has {len(tol)} values for {len(axes)} axes", path="path_tolerance"
        )
    for j, v in enumerate(tol):
        p = "path_tolerance" if data.scalar_tolerance else f"path_tolerance[{j}]"
        if not math.isfinite(v):
            raise PlanningError(NONFINITE, f"{p}{axis_note(axes, j)} is {nan_name(v)}", path=p)
        if v < 0:
            raise PlanningError(
                LIMITS,
                f"{p}{'' if data.scalar_tolerance else axis_note(axes, j)} is {v:g}; a path tolerance "
                f"is >= 0 (0: stop exactly at every corner)",
                path=p,
            )


def _arrays(data: JobData) -> list[tuple[str, FloatArray | None]]:
    if isinstance(data, HomeData):
        return []
    if isinstance(data, PathData):
        return [("waypoints", data.waypoints)]
    if isinstance(data, MoveData):
        return [("target", data.target), ("start", data.start), ("velocity", data.velocity)]
    if isinstance(data, TimedData):
        return [("times", data.times), ("positions", data.positions)]
    return [("times", data.times), ("positions", data.positions), ("velocities", data.velocities)]


# ----------------------------------------------------------------------------------------------------
# job_from_dict


def job_from_dict(data: Mapping[str, Any], cell: CellConfig, *, max_rows: int = MAX_ROWS) -> Job:
    """Validate a job mapping against `cell` and build the `Job` (raises PlanningError with a code)."""
    if not isinstance(data, Mapping):
        raise PlanningError(SCHEMA, f"a job must be a table/object, got {type(data).__name__}", path="")
    for key in data:
        if not isinstance(key, str):
            raise PlanningError(SCHEMA, f"job keys must be strings, got {show(key)}", path=str(key))
    if "kind" not in data:
        raise PlanningError(SCHEMA, "missing field 'kind' (one of path, move, timed, pvt)", path="kind")
    kind = data["kind"]
    if not isinstance(kind, str):
        raise PlanningError(TYPE, f"kind must be a string, got {show(kind)}", path="kind")
    if kind not in KINDS:
        raise PlanningError(SCHEMA, f"kind must be one of {list(KINDS)}, got {kind!r}", path="kind")
    required, optional = _KIND_FIELDS[kind]
    common = _HOME_COMMON if kind == "home" else _COMMON
    allowed = common | required | optional | ({"start"} if kind == "path" else set())
    unknown = sorted(k for k in data if k not in allowed)
    if unknown:
        raise PlanningError(
            SCHEMA,
            f"unknown field {unknown[0]!r} in a {kind} job (allowed: {sorted(allowed)})",
            path=unknown[0],
        )
    for key in sorted(required | {"axes"}):
        if key not in data:
            raise PlanningError(SCHEMA, f"missing field {key!r} in a {kind} job", path=key)

    axes = _axes(data["axes"], cell)
    axis_cfg = [cell.axis(a) for a in axes]
    job_id = read_text(data["job_id"], "job_id", job_id=True) if data.get("job_id") is not None else None
    description = read_text(data["description"], "description") if data.get("description") is not None else None

    tolerance = 1
    if "tolerance_counts" in data:
        t = read_number(data["tolerance_counts"], "tolerance_counts")
        if t <= 0 or t != math.floor(t) or t > MAX_TOLERANCE_COUNTS:
            raise PlanningError(
                LIMITS,
                f"tolerance_counts is {t:g}; it must be a whole number of counts in "
                f"1..{MAX_TOLERANCE_COUNTS} (the drive commands whole counts)",
                path="tolerance_counts",
            )
        tolerance = int(t)
    vscale, vs_scalar = (
        read_scale(data["velocity_scale"], "velocity_scale", axes)
        if "velocity_scale" in data
        else ((1.0,) * len(axes), False)
    )
    ascale, as_scalar = (
        read_scale(data["acceleration_scale"], "acceleration_scale", axes)
        if "acceleration_scale" in data
        else ((1.0,) * len(axes), False)
    )
    limits = _limits(data.get("limits"), axes, axis_cfg) if "limits" in data else {}

    job_data: JobData
    if kind == "home":
        job_data = _home_data(data, axes, axis_cfg)
    elif kind == "path":
        if data.get("start") is not None and data["start"] != START_CURRENT:
            raise PlanningError(
                SCHEMA,
                f"start of a path job can only be {START_CURRENT!r} (re-plan from where the axes stand), "
                f"got {show(data['start'])}; the first waypoint is where the path starts",
                path="start",
            )
        wp = read_matrix(data["waypoints"], "waypoints", axes, max_rows)
        _check_positions(wp, "waypoints", axes, axis_cfg)
        distinct = 1 + int(np.count_nonzero(np.any(np.diff(wp, axis=0) != 0.0, axis=1))) if wp.shape[0] else 0
        if distinct < 2:
            raise PlanningError(
                DEGENERATE,
                f"a path needs at least 2 distinct waypoints, got {distinct} (use a move job to stand still)",
                path="waypoints",
            )
        geometry = data.get("geometry", "lines")
        if not isinstance(geometry, str):
            raise PlanningError(TYPE, f"geometry must be a string, got {show(geometry)}", path="geometry")
        tol: tuple[float, ...] | None = None
        tol_scalar = False
        if data.get("path_tolerance") is not None:
            value = data["path_tolerance"]
            if isinstance(value, list | tuple):
                tol = tuple(float(v) for v in read_vector(value, "path_tolerance", axes))
            else:
                tol = (read_number(value, "path_tolerance"),) * len(axes)
                tol_scalar = True
        jerk_flag = data.get("jerk_limited")
        if jerk_flag is not None and not isinstance(jerk_flag, bool):
            raise PlanningError(
                TYPE, f"jerk_limited must be true or false, got {show(jerk_flag)}", path="jerk_limited"
            )
        timing = data.get("jerk_timing")
        if timing is not None and not isinstance(timing, str):
            raise PlanningError(TYPE, f"jerk_timing must be a string, got {show(timing)}", path="jerk_timing")
        job_data = PathData(_ro(wp), cast(Any, geometry), tol, tol_scalar, jerk_flag, cast(Any, timing))
    elif kind == "move":
        job_data = _move_data(data, axes, axis_cfg, limits, vscale, "acceleration_scale" in data)
    else:
        times = read_series(data["times"], "times", max_rows)
        pos = read_matrix(data["positions"], "positions", axes, max_rows)
        if pos.shape[0] != times.size:
            raise PlanningError(
                SCHEMA,
                f"times has {times.size} entries but positions has {pos.shape[0]} rows",
                path="positions",
            )
        if times.size < 2:
            raise PlanningError(
                DEGENERATE, f"a {kind} job needs at least 2 rows, got {times.size}", path="times"
            )
        _check_times(times)
        _check_positions(pos, "positions", axes, axis_cfg)
        if kind == "timed":
            job_data = TimedData(_ro(times), _ro(pos))
        else:
            vel = read_matrix(data["velocities"], "velocities", axes, max_rows)
            if vel.shape[0] != times.size:
                raise PlanningError(
                    SCHEMA,
                    f"times has {times.size} entries but velocities has {vel.shape[0]} rows",
                    path="velocities",
                )
            _check_pvt(times, vel, axes, axis_cfg)
            job_data = PvtData(_ro(times), _ro(pos), _ro(vel))

    job = Job(
        kind=cast(Kind, kind),
        axes=axes,
        data=job_data,
        tolerance_counts=tolerance,
        velocity_scale=vscale,
        acceleration_scale=ascale,
        velocity_limit=limits.get("velocity"),
        acceleration_limit=limits.get("acceleration"),
        jerk_limit=limits.get("jerk"),
        job_id=job_id,
        description=description,
        _scalar_scales=(vs_scalar and "velocity_scale" in data, as_scalar and "acceleration_scale" in data),
    )
    if "tolerance_counts" not in data and jerk_limited(job, cell):
        job = dataclasses.replace(job, tolerance_counts=JERK_TOLERANCE_COUNTS)
    return job


# ---- home jobs ----------------------------------------------------------------------------------------
_HOME_COMMON = {"kind", "axes", "job_id", "description"}
# defaults from the axis' limits: search at a tenth of its velocity, the zero (final approach) at a tenth of that
HOME_SEARCH_SHARE = 0.1
HOME_ZERO_SHARE = 0.01


def _home_data(data: Mapping[str, Any], axes: tuple[str, ...], cfg: Sequence[AxisConfig]) -> HomeData:
    raw = data["method"]
    methods = raw if isinstance(raw, list | tuple) else [raw] * len(axes)
    if isinstance(raw, list | tuple) and len(raw) != len(axes):
        raise PlanningError(AXIS_COUNT, f"method has {len(raw)} values for {len(axes)} axes {list(axes)!r}",
                            path="method")
    method: list[int] = []
    for j, m in enumerate(methods):
        p = f"method[{j}]" if isinstance(raw, list | tuple) else "method"
        if isinstance(m, bool) or not isinstance(m, int):
            raise PlanningError(TYPE, f"{p} of axis {axes[j]!r} must be a whole number (0x6098), got {show(m)}",
                                path=p)
        supported = HOMING_METHODS[cfg[j].profile]
        if m not in supported:
            raise PlanningError(SCHEMA, f"{p} of axis {axes[j]!r} is {m}: a {cfg[j].profile} drive homes with "
                                f"{sorted(supported)} (docs/drive-model.md, Homing)", path=p)
        method.append(m)
    speeds: dict[str, tuple[float, ...]] = {}
    for key, default in (("search_speed", [HOME_SEARCH_SHARE * c.velocity for c in cfg]),
                         ("zero_speed", [HOME_ZERO_SHARE * c.velocity for c in cfg]),
                         ("acceleration", [c.acceleration for c in cfg])):
        vals, scalar = read_per_axis(data[key], key, axes) if key in data else (tuple(default), False)
        limit = [c.velocity if key != "acceleration" else c.acceleration for c in cfg]
        for j, v in enumerate(vals):
            p = key if scalar else f"{key}[{j}]"
            if not 0.0 < v <= limit[j]:
                unit = f"{cfg[j].unit}/s" if key != "acceleration" else f"{cfg[j].unit}/s^2"
                raise PlanningError(LIMITS, f"{p} of axis {axes[j]!r} is {v:g} {unit}; it must be > 0 and at most "
                                    f"the axis' {'velocity' if key != 'acceleration' else 'acceleration'} "
                                    f"{limit[j]:g} {unit}", path=p)
        speeds[key] = vals
    offset, scalar = read_per_axis(data["offset"], "offset", axes) if "offset" in data else ((0.0,) * len(axes), False)
    for j, v in enumerate(offset):
        c = cfg[j]
        if not c.position_min <= v <= c.position_max:
            p = "offset" if scalar else f"offset[{j}]"
            raise PlanningError(POSITION_LIMIT, f"{p} of axis {axes[j]!r} is {v:g} {c.unit}, outside its position "
                                f"limits [{c.position_min:g}, {c.position_max:g}] (the home position gets it)",
                                path=p)
    timeout = read_number(data["timeout_s"], "timeout_s") if "timeout_s" in data else HOME_TIMEOUT_S
    if not 0.0 < timeout <= MAX_HOME_TIMEOUT_S:
        raise PlanningError(LIMITS, f"timeout_s is {timeout:g}; it must be in (0, {MAX_HOME_TIMEOUT_S:g}] s",
                            path="timeout_s")
    return HomeData(tuple(method), speeds["search_speed"], speeds["zero_speed"], speeds["acceleration"], offset,
                    timeout)


def _move_data(
    data: Mapping[str, Any],
    axes: tuple[str, ...],
    cfg: Sequence[AxisConfig],
    limits: dict[str, tuple[float, ...]],
    vscale: tuple[float, ...],
    has_acc_scale: bool,
) -> MoveData:
    """The move's mode, its target (or velocity), start and ramps, each checked against the cell."""
    mode = data.get("mode", "absolute")
    if not isinstance(mode, str):
        raise PlanningError(TYPE, f"mode must be a string, got {show(mode)}", path="mode")
    if mode not in MOVE_MODES:
        raise PlanningError(SCHEMA, f"mode must be one of {list(MOVE_MODES)}, got {mode!r}", path="mode")
    given = data.get("start")
    start = read_vector(given, "start", axes) if given is not None and given != START_CURRENT else None
    if start is not None:
        _check_positions(start[None, :], "start", axes, cfg, vector=True)
    ramps = _ramps(data["ramps"], axes, cfg) if "ramps" in data else None
    if ramps is not None:
        for other, present in (("limits.acceleration", "acceleration" in limits),
                               ("acceleration_scale", has_acc_scale)):
            if present:
                raise PlanningError(
                    SCHEMA,
                    f"ramps and {other} both set the move's acceleration: give one of them (ramps: seed 002's "
                    f"times for 0 -> 100 % of the velocity limit; {other}: the acceleration itself)",
                    path="ramps",
                    detail={"fields": ["ramps", other]},
                )
    if mode == "velocity":
        if "target" in data:
            raise PlanningError(SCHEMA, "a move with mode 'velocity' has no target: it travels endlessly at "
                                "`velocity = [...]` (user units/s)", path="target")
        if "velocity" not in data:
            raise PlanningError(SCHEMA, "missing field 'velocity' in a move job with mode 'velocity'", path="velocity")
        vel = read_vector(data["velocity"], "velocity", axes)
        vlim = limits.get("velocity") or tuple(c.velocity for c in cfg)
        for j, v in enumerate(vel):
            top = vlim[j] * vscale[j]
            if abs(v) > top * (1 + 1e-12):
                raise PlanningError(
                    LIMITS,
                    f"velocity[{j}] of axis {axes[j]!r} is {v:g}/s, above its velocity limit {top:g}/s "
                    f"(the axis' or limits.velocity, times velocity_scale)",
                    path=f"velocity[{j}]",
                )
        return MoveData(_ro(np.zeros(len(axes))), "velocity", None if start is None else _ro(start), _ro(vel), ramps)
    if "velocity" in data:
        raise PlanningError(SCHEMA, f"velocity belongs to mode 'velocity', not {mode!r} (a move's speed: "
                            "limits.velocity or velocity_scale)", path="velocity")
    if "target" not in data:
        raise PlanningError(SCHEMA, "missing field 'target' in a move job", path="target")
    target = read_vector(data["target"], "target", axes)
    if mode == "absolute":
        _check_positions(target[None, :], "target", axes, cfg, vector=True)
    elif mode in OFFSET_MODES:
        span = np.array([a.position_max - a.position_min for a in cfg])
        for j in range(len(axes)):
            if abs(target[j]) > span[j]:
                raise PlanningError(
                    POSITION_LIMIT,
                    f"target[{j}] of axis {axes[j]!r} moves {target[j]:g}, more "
                    f"than the axis' whole range {span[j]:g}",
                    path=f"target[{j}]",
                )
        if start is not None:  # planned without a service: the offset counts from `start`
            check_relative_target(start, target, axes, cfg)
            _check_positions((start + target)[None, :], "target", axes, cfg, vector=True)
    else:
        _check_modulo_targets(mode, target, axes, cfg)
    return MoveData(_ro(target), cast(MoveMode, mode), None if start is None else _ro(start), None, ramps)


def _check_modulo_targets(mode: str, target: FloatArray, axes: Sequence[str], cfg: Sequence[AxisConfig]) -> None:
    """Seed 002: "For modulo positioning with start type MODULO_SHORT, only modulo target positions within
    the basic period (e.g. less than 360°) are permitted, otherwise an error is returned"; the other
    directions take targets >= 0, a full period more for each extra turn."""
    for j, c in enumerate(cfg):
        if not c.is_modulo:
            raise PlanningError(
                SCHEMA,
                f"mode {mode!r} needs modulo axes, but axis {axes[j]!r} has no modulo_period in the cell",
                path="mode",
                detail={"axis": axes[j]},
            )
        v = float(target[j])
        if mode == "modulo_short" and not 0.0 <= v < c.modulo_period:
            raise PlanningError(
                MODULO_RANGE,
                f"target[{j}] of axis {axes[j]!r} is {v:g}, outside the basic period [0, {c.modulo_period:g}) "
                f"that mode 'modulo_short' accepts (the shortest way makes no extra turns; use modulo_plus or "
                f"modulo_minus for those)",
                path=f"target[{j}]",
                detail={"axis": axes[j], "value": v, "period": c.modulo_period},
            )
        if v < 0.0:
            raise PlanningError(
                MODULO_RANGE,
                f"target[{j}] of axis {axes[j]!r} is {v:g}; a modulo target is >= 0 (the direction is the "
                f"mode's: {mode!r}; each further period adds a turn)",
                path=f"target[{j}]",
                detail={"axis": axes[j], "value": v, "period": c.modulo_period},
            )


def _ramps(value: Any, axes: Sequence[str], cfg: Sequence[AxisConfig]) -> Ramps:
    """ramps = {accel_ms = ..., decel_ms = ...}: a number or one per axis; one alone serves both."""
    if not isinstance(value, Mapping):
        raise PlanningError(TYPE, f"ramps must be a table with {list(RAMP_KEYS)}, got {show(value)}", path="ramps")
    for key in value:
        if key not in RAMP_KEYS:
            raise PlanningError(SCHEMA, f"unknown field {key!r} in ramps (allowed: {list(RAMP_KEYS)})",
                                path=f"ramps.{key}")
    if not any(k in value for k in RAMP_KEYS):
        raise PlanningError(SCHEMA, f"ramps needs {RAMP_KEYS[0]} and/or {RAMP_KEYS[1]}", path="ramps")
    out: dict[str, tuple[float, ...]] = {}
    scalar: dict[str, bool] = {}
    for key in RAMP_KEYS:
        if key not in value:
            continue
        p = f"ramps.{key}"
        raw = value[key]
        scalar[key] = not isinstance(raw, list | tuple)
        vals = np.full(len(axes), read_number(raw, p)) if scalar[key] else read_vector(raw, p, axes)
        for j, ms in enumerate(vals):
            at = p if scalar[key] else f"{p}[{j}]"
            note = f" (axis {axes[j]!r})" if scalar[key] else axis_note(axes, j)
            if not 0.0 < ms <= MAX_RAMP_MS:
                raise PlanningError(LIMITS, f"{at}{note} is {ms:g} ms; a ramp time is in (0, {MAX_RAMP_MS:g}] ms",
                                    path=at)
            acc = cfg[j].velocity / (ms / 1000.0)
            if acc > cfg[j].max_acceleration * (1 + 1e-12):
                raise PlanningError(
                    LIMITS_EXCEED_DRIVE,
                    f"{at}{note} is {ms:g} ms: 0 -> {cfg[j].velocity:g}/s (the axis' velocity limit, its speed "
                    f"range) in that time is {acc:g}/s^2, above the drive's max acceleration 0x60C5 "
                    f"{cfg[j].max_acceleration:g}/s^2",
                    path=at,
                )
        out[key] = tuple(float(v) for v in vals)
    accel = out.get("accel_ms", out.get("decel_ms"))
    decel = out.get("decel_ms", out.get("accel_ms"))
    assert accel is not None and decel is not None
    return Ramps(accel, decel, ("accel_ms" in out, "decel_ms" in out),
                 (scalar.get("accel_ms", False), scalar.get("decel_ms", False)))


def _axes(value: Any, cell: CellConfig) -> tuple[str, ...]:
    if not isinstance(value, list | tuple):
        raise PlanningError(TYPE, f"axes must be a list of axis names, got {show(value)}", path="axes")
    if not value:
        raise PlanningError(AXIS_COUNT, "axes is empty: a job needs at least one axis", path="axes")
    known = cell.axis_names()
    if len(value) > len(known):
        raise PlanningError(
            AXIS_COUNT, f"axes lists {len(value)} axes but cell {cell.name!r} has {len(known)}", path="axes"
        )
    seen: set[str] = set()
    for j, name in enumerate(value):
        if not isinstance(name, str):
            raise PlanningError(TYPE, f"axes[{j}] must be an axis name, got {show(name)}", path=f"axes[{j}]")
        if name not in known:
            raise PlanningError(
                AXIS_ID,
                f"axes[{j}] {name!r} is not an axis of cell {cell.name!r} (axes: {list(known)})",
                path=f"axes[{j}]",
            )
        if name in seen:
            raise PlanningError(AXIS_ID, f"axes[{j}] {name!r} is listed twice", path=f"axes[{j}]")
        seen.add(name)
    return tuple(str(name) for name in value)  # plain str: a numpy string would print as np.str_('j1')


def _limits(value: Any, axes: Sequence[str], cfg: Sequence[AxisConfig]) -> dict[str, tuple[float, ...]]:
    if not isinstance(value, Mapping):
        raise PlanningError(
            TYPE, f"limits must be a table with {list(_LIMIT_KEYS)}, got {show(value)}", path="limits"
        )
    out: dict[str, tuple[float, ...]] = {}
    for key in value:
        if key not in _LIMIT_KEYS:
            raise PlanningError(
                SCHEMA,
                f"unknown field {key!r} in limits (allowed: {list(_LIMIT_KEYS)})",
                path=f"limits.{key}",
            )
    for key in _LIMIT_KEYS:
        if key not in value:
            continue
        p = f"limits.{key}"
        vals = read_vector(value[key], p, axes)
        for j, v in enumerate(vals):
            if v <= 0:
                raise PlanningError(
                    LIMITS, f"{p}[{j}] of axis {axes[j]!r} is {v:g}; limits must be > 0", path=f"{p}[{j}]"
                )
            if key == "velocity" and v > cfg[j].max_profile_velocity * (1 + 1e-12):
                raise PlanningError(
                    LIMITS_EXCEED_DRIVE,
                    f"{p}[{j}] of axis {axes[j]!r} is {v:g}/s = {cfg[j].velocity_rpm(v):.0f} rpm, above "
                    f"the drive's max profile velocity 0x607F {cfg[j].max_profile_velocity_rpm:g} rpm",
                    path=f"{p}[{j}]",
                )
            if key == "acceleration" and v > cfg[j].max_acceleration:
                raise PlanningError(
                    LIMITS_EXCEED_DRIVE,
                    f"{p}[{j}] of axis {axes[j]!r} is {v:g}/s^2, above the drive's max "
                    f"acceleration 0x60C5 {cfg[j].max_acceleration:g}/s^2",
                    path=f"{p}[{j}]",
                )
        out[key] = tuple(float(v) for v in vals)
    return out


def check_relative_target(
    origin: Sequence[float] | FloatArray, offset: Sequence[float] | FloatArray, axes: Sequence[str],
    cfg: Sequence[AxisConfig], origin_name: str = "start",
) -> None:
    """A relative move's end within the software limits; the message says what the user wrote (the offset)
    and where it comes from, not only the sum."""
    for j, c in enumerate(cfg):
        end = float(origin[j]) + float(offset[j])
        if not c.position_min <= end <= c.position_max:
            raise PlanningError(
                POSITION_LIMIT,
                f"target[{j}] of axis {axes[j]!r} is a relative move of {float(offset[j]):+g} from the "
                f"{origin_name} {float(origin[j]):g}: it would end at {end:g}, outside the software "
                f"position limits [{c.position_min:g}, {c.position_max:g}]",
                path=f"target[{j}]",
            )


def _check_positions(
    a: FloatArray, name: str, axes: Sequence[str], cfg: Sequence[AxisConfig], *, vector: bool = False
) -> None:
    lo = np.array([c.position_min for c in cfg])
    hi = np.array([c.position_max for c in cfg])
    bad = (a < lo) | (a > hi)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        p = f"{name}[{j}]" if vector else f"{name}[{i}][{j}]"
        raise PlanningError(
            POSITION_LIMIT,
            f"{p} of axis {axes[j]!r} is {a[i, j]:g}, outside the software "
            f"position limits [{lo[j]:g}, {hi[j]:g}]",
            path=p,
        )
    counts = a * np.array([c.counts_per_unit for c in cfg])
    bad = (counts < POSITION_MIN) | (counts > POSITION_MAX)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        p = f"{name}[{j}]" if vector else f"{name}[{i}][{j}]"
        raise PlanningError(
            ENCODING_RANGE,
            f"{p} of axis {axes[j]!r} is {a[i, j]:g} = {counts[i, j]:.0f} counts, "
            f"which does not fit the int32 PVT position",
            path=p,
        )


def _check_times(times: FloatArray) -> None:
    if times[0] < 0:
        raise PlanningError(
            NON_MONOTONIC, f"times[0] is {times[0]:g}; times start at >= 0 s", path="times[0]"
        )
    d = np.diff(times)
    if np.any(d <= 0):
        i = int(np.argmax(d <= 0)) + 1
        raise PlanningError(
            NON_MONOTONIC,
            f"times[{i}] = {times[i]:g} s does not come after times[{i - 1}] = "
            f"{times[i - 1]:g} s (times must strictly increase)",
            path=f"times[{i}]",
        )
    if times[-1] - times[0] > MAX_DURATION_S:
        raise PlanningError(
            TOO_LARGE,
            f"the job lasts {times[-1] - times[0]:g} s, more than the limit of {MAX_DURATION_S:g} s",
            path="times",
        )


def _check_pvt(times: FloatArray, vel: FloatArray, axes: Sequence[str], cfg: Sequence[AxisConfig]) -> None:
    dt_ms = np.diff(times) * 1000.0
    whole = np.round(dt_ms)
    bad = (np.abs(dt_ms - whole) > 1e-6) | (whole < 1) | (whole > SEGMENT_TIME_MAX_MS)
    if bad.any():
        i = int(np.argmax(bad)) + 1
        raise PlanningError(
            ENCODING_RANGE,
            f"times[{i}] - times[{i - 1}] is {dt_ms[i - 1]:g} ms; a PVT segment "
            f"time must be a whole number of ms in 1..{SEGMENT_TIME_MAX_MS}",
            path=f"times[{i}]",
        )
    rpm = vel * np.array([c.counts_per_unit * 60.0 / c.counts_per_rev for c in cfg])
    bad = (np.round(rpm) < VELOCITY_MIN) | (np.round(rpm) > VELOCITY_MAX)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise PlanningError(
            ENCODING_RANGE,
            f"velocities[{i}][{j}] of axis {axes[j]!r} is {vel[i, j]:g}/s = "
            f"{rpm[i, j]:.0f} rpm, which does not fit the int24 PVT velocity",
            path=f"velocities[{i}][{j}]",
        )


# ----------------------------------------------------------------------------------------------------
# job_to_dict / load_job


def job_to_dict(job: Job) -> dict[str, Any]:
    """The job as plain data (the fields of a job file); job_from_dict(job_to_dict(j), cell) == j."""
    out: dict[str, Any] = {"kind": job.kind, "axes": list(job.axes)}
    if job.job_id is not None:
        out["job_id"] = job.job_id
    if job.description is not None:
        out["description"] = job.description
    d = job.data
    if isinstance(d, PathData):
        out["waypoints"] = d.waypoints.tolist()
        if d.geometry != "lines":
            out["geometry"] = d.geometry
        if d.path_tolerance is not None:
            out["path_tolerance"] = d.path_tolerance[0] if d.scalar_tolerance else list(d.path_tolerance)
        if d.jerk_limited is not None:
            out["jerk_limited"] = d.jerk_limited
        if d.jerk_timing is not None:
            out["jerk_timing"] = d.jerk_timing
    elif isinstance(d, MoveData):
        if d.velocity is not None:
            out["velocity"] = d.velocity.tolist()
        else:
            out["target"] = d.target.tolist()
        out["mode"] = d.mode
        if d.start is not None:
            out["start"] = d.start.tolist()
        if d.ramps is not None:
            ramps: dict[str, Any] = {}
            for key, vals, given, scalar in zip(RAMP_KEYS, (d.ramps.accel_ms, d.ramps.decel_ms), d.ramps.given,
                                                d.ramps.scalar, strict=True):
                if given:
                    ramps[key] = vals[0] if scalar else list(vals)
            out["ramps"] = ramps
    elif isinstance(d, TimedData):
        out["times"] = d.times.tolist()
        out["positions"] = d.positions.tolist()
    elif isinstance(d, HomeData):
        out.update(method=list(d.method), search_speed=list(d.search_speed), zero_speed=list(d.zero_speed),
                   acceleration=list(d.acceleration), offset=list(d.offset), timeout_s=d.timeout_s)
    else:
        out["times"] = d.times.tolist()
        out["positions"] = d.positions.tolist()
        out["velocities"] = d.velocities.tolist()
    if job.tolerance_counts != 1:
        out["tolerance_counts"] = job.tolerance_counts
    for name, scalar in (
        ("velocity_scale", job._scalar_scales[0]),
        ("acceleration_scale", job._scalar_scales[1]),
    ):
        vals = getattr(job, name)
        if scalar:
            out[name] = vals[0]
        elif any(v != 1.0 for v in vals):
            out[name] = list(vals)
    limits = {
        k: list(v)
        for k, v in (
            ("velocity", job.velocity_limit),
            ("acceleration", job.acceleration_limit),
            ("jerk", job.jerk_limit),
        )
        if v is not None
    }
    if limits:
        out["limits"] = limits
    return out


def load_job(path: str | Path, cell: CellConfig, *, max_rows: int = MAX_ROWS) -> Job:
    """Read a TOML (.toml) or JSON (anything else) job file and validate it."""
    return job_from_dict(read_job_file(path), cell, max_rows=max_rows)


def read_job_file(path: str | Path) -> Any:
    """A TOML (.toml) or JSON (anything else) job file's data, not yet validated."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise PlanningError(SCHEMA, f"job file {str(p)!r} not found", path="") from None
    except (OSError, UnicodeDecodeError) as e:
        raise PlanningError(SCHEMA, f"job file {str(p)!r} cannot be read: {e}", path="") from None
    data: Any
    if p.suffix.lower() == ".toml":
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as e:
            raise PlanningError(SCHEMA, f"job file {str(p)!r} is not valid TOML: {e}", path="") from None
    else:
        try:
            data = json.loads(text)
        except (json.JSONDecodeError, RecursionError) as e:
            raise PlanningError(SCHEMA, f"job file {str(p)!r} is not valid JSON: {e}", path="") from None
    return data


def path_tolerance(job: Job, cell: CellConfig) -> FloatArray:
    """Per-axis path tolerance (user units) of a path job: the job's, or the default share of the travel."""
    d = job.data
    if isinstance(d, PathData) and d.path_tolerance is not None:
        return np.array(d.path_tolerance, dtype=np.float64)
    cfg = [cell.axis(a) for a in job.axes]
    return np.array([DEFAULT_PATH_TOLERANCE_SHARE * (c.position_max - c.position_min) for c in cfg])


def with_jerk_limited(data: Any, value: bool | None) -> Any:
    """A job's data with a path's `jerk_limited` set to `value` (None, or not a path: unchanged). On the data,
    not the `Job`: a jerk-limited path's default tolerance (2 counts) is chosen when the data is read."""
    if value is None or not isinstance(data, dict) or data.get("kind") != "path":
        return data
    return {**data, "jerk_limited": value}


def jerk_limited(job: Job, cell: CellConfig) -> bool:
    """Whether a path job is planned with every axis' jerk limit: its `jerk_limited`, else
    `JERK_LIMITED_DEFAULT` when every axis of the job has a jerk limit (a finite one above 0)."""
    d = job.data
    if not isinstance(d, PathData):
        return False
    if d.jerk_limited is not None:
        return d.jerk_limited
    jerk = effective_limits(job, cell).jerk
    return JERK_LIMITED_DEFAULT and bool(np.all(np.isfinite(jerk) & (jerk > 0.0)))


def effective_limits(job: Job, cell: CellConfig) -> AxisLimits:
    """Per-axis limits the job is planned with (user units): overrides, then scales, applied."""
    cfg = [cell.axis(a) for a in job.axes]
    vel = np.array(job.velocity_limit if job.velocity_limit is not None else [c.velocity for c in cfg])
    acc = np.array(
        job.acceleration_limit if job.acceleration_limit is not None else [c.acceleration for c in cfg]
    )
    jerk = np.array(job.jerk_limit if job.jerk_limit is not None else [c.jerk for c in cfg])
    dec = acc
    ramps = job.data.ramps if isinstance(job.data, MoveData) else None
    if ramps is not None:  # seed 002: the ramp time takes 0 -> 100 % of the speed range (the velocity limit)
        speed_range = np.array([c.velocity for c in cfg])
        acc = speed_range / (np.array(ramps.accel_ms) / 1000.0)
        dec = speed_range / (np.array(ramps.decel_ms) / 1000.0)
    scale = np.array(job.acceleration_scale)
    return AxisLimits(
        velocity=vel * np.array(job.velocity_scale),
        # the bound every check uses: the larger of the two ramps (moves plan with each where it applies)
        acceleration=np.maximum(acc, dec) * scale,
        acceleration_up=acc * scale,  # speeding up
        deceleration=dec * scale,  # slowing down
        jerk=jerk,
        velocity_axis=vel,  # before scaling: what "the axis limit" means in the checks
        acceleration_axis=np.maximum(acc, dec),
    )
