"""Strict, bounded decoding of job submissions (and the msgpack helpers of the wire format).

Untrusted bytes -> a `Submission` (optional `job_id`, the job body as a plain dict) or `MotionError` with a
stable code, never anything else (Hypothesis feeds it arbitrary bytes). Cheapest checks first, each cost
bounded before it is paid: size, one msgpack object (pairs hook: duplicate and non-string keys seen), one
iterative walk (depth, lengths, keys, bools, huge integers, NaN) with the job file's paths, the envelope
(`job_id`, `start = "current"`). Unknown job fields are the validator's. The idempotency hash is over a
canonical form, so another client's encoding of the same job matches.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import msgpack

from planner.config import check_name
from streamer.api import errors as E
from streamer.api.errors import MotionError
from streamer.api.keys import valid_job_id

START_CURRENT = "current"  # the job field value `start = "current"` (planner.job.START_CURRENT)
MAX_SAFE_INT = 2**53  # integers beyond this are not exact as float64: "huge ints" are TYPE errors

# Fields whose second index is the axis (one row per waypoint/knot), and fields whose first index is.
_ROW_AXIS_FIELDS = frozenset({"waypoints", "positions", "velocities", "rows", "points"})
_COLUMN_AXIS_FIELDS = frozenset({"target", "start", "velocity_scale", "acceleration_scale", "path_tolerance"})


@dataclass(frozen=True)
class PayloadLimits:
    """Bounds applied to every submission before and while decoding."""

    max_bytes: int = 4 * 1024 * 1024  # payload size, checked before decoding
    max_depth: int = 16  # nesting of maps/arrays (a job needs 4)
    max_array_len: int = 100_000  # elements per array: the waypoint/row limit
    max_str_len: int = 4096  # characters per string (axis names, kind, mode)
    max_map_len: int = 256  # entries per map

    def __post_init__(self) -> None:
        for name in ("max_bytes", "max_depth", "max_array_len", "max_str_len", "max_map_len"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"PayloadLimits.{name} must be >= 1, got {getattr(self, name)}")


DEFAULT_LIMITS = PayloadLimits()


@dataclass(frozen=True)
class Submission:
    """A decoded submission: the client's job id (or None) and the job body (job file fields)."""

    job_id: str | None
    body: dict[str, Any]
    body_hash: str
    # `start = "current"` was given (path, move): plan from where the axes stand (prepended to a path whose
    # first waypoint is elsewhere) instead of failing INFEASIBLE; removed from `body`, kept in the hash
    start_current: bool = False

    @property
    def kind(self) -> str:
        k = self.body.get("kind")
        return k if isinstance(k, str) else ""


class _BadMap:
    """Placeholder the pairs hook returns for a map with a non-string or duplicate key.

    Raising inside the hook would lose the path; the walk finds the placeholder and reports it with
    the field path instead.
    """

    __slots__ = ("key", "reason")

    def __init__(self, reason: str, key: Any):
        self.reason = reason
        self.key = key


def _pairs_hook(pairs: list[tuple[Any, Any]]) -> dict[str, Any] | _BadMap:
    out: dict[str, Any] = {}
    for k, v in pairs:
        if not isinstance(k, str):
            return _BadMap("non-string", k)
        if k in out:
            return _BadMap("duplicate", k)
        out[k] = v
    return out


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _fmt_path(parts: tuple[str | int, ...]) -> str:
    out = ""
    for p in parts:
        if isinstance(p, int):
            out += f"[{p}]"
        else:
            out += f".{p}" if out else p
    return out


def _axis_of(parts: tuple[str | int, ...], root: Mapping[str, Any]) -> str | None:
    """The axis name a path refers to, when the job says which axes its columns are."""
    axes = root.get("axes")
    if not parts or not isinstance(parts[0], str) or not isinstance(axes, list):
        return None
    index: Any = None
    if parts[0] in _ROW_AXIS_FIELDS and len(parts) >= 3:
        index = parts[2]
    elif parts[0] in _COLUMN_AXIS_FIELDS and len(parts) >= 2:
        index = parts[1]
    elif parts[0] == "limits" and len(parts) >= 3:  # limits.velocity[1]: one value per axis
        index = parts[2]
    if isinstance(index, int) and 0 <= index < len(axes) and isinstance(axes[index], str):
        return str(axes[index])
    return None


def _where(parts: tuple[str | int, ...], root: Mapping[str, Any]) -> str:
    path = _fmt_path(parts) or "payload"
    axis = _axis_of(parts, root)
    return f"{path} of axis {axis!r}" if axis is not None else path


def _unpack(data: bytes, limits: PayloadLimits) -> Any:
    try:
        return msgpack.unpackb(
            data,
            raw=False,
            use_list=True,
            strict_map_key=False,
            object_pairs_hook=_pairs_hook,
            max_str_len=limits.max_bytes,
            max_bin_len=limits.max_bytes,
            max_ext_len=limits.max_bytes,
            max_array_len=limits.max_bytes,
            max_map_len=limits.max_bytes,
        )
    except msgpack.ExtraData:
        raise MotionError(E.MALFORMED_PAYLOAD, "trailing bytes after the msgpack object") from None
    except msgpack.StackError:
        raise MotionError(E.MALFORMED_PAYLOAD, f"nested too deep (limit {limits.max_depth} levels)") from None
    except UnicodeDecodeError as exc:
        raise MotionError(E.MALFORMED_PAYLOAD, f"a string is not valid UTF-8: {exc.reason}") from None
    except (ValueError, TypeError, OverflowError, MemoryError, RecursionError) as exc:
        text = str(exc) or type(exc).__name__
        if "incomplete input" in text:
            text = "truncated msgpack (incomplete input)"
        raise MotionError(E.MALFORMED_PAYLOAD, f"not a valid msgpack object: {text}"[:300]) from None
    except Exception as exc:  # any other decoder failure is still malformed input, never a crash
        raise MotionError(E.MALFORMED_PAYLOAD, f"not a valid msgpack object: {type(exc).__name__}") from None


def _check_tree(obj: dict[str, Any], limits: PayloadLimits) -> None:
    """Walk the decoded tree once, iteratively, raising the first problem found (in document order)."""
    stack: list[tuple[Any, tuple[str | int, ...], int]] = [(obj, (), 1)]
    while stack:
        value, parts, depth = stack.pop()
        if isinstance(value, dict):
            if depth > limits.max_depth:
                raise MotionError(
                    E.MALFORMED_PAYLOAD,
                    f"{_fmt_path(parts) or 'payload'} is nested too deep (limit {limits.max_depth})",
                    path=_fmt_path(parts),
                )
            if len(value) > limits.max_map_len:
                raise MotionError(
                    E.TOO_LARGE,
                    f"{_fmt_path(parts) or 'payload'} has {len(value)} fields, more "
                    f"than the limit {limits.max_map_len}",
                    path=_fmt_path(parts),
                )
            for k in reversed(list(value)):
                stack.append((value[k], (*parts, k), depth + 1))
        elif isinstance(value, list):
            if depth > limits.max_depth:
                raise MotionError(
                    E.MALFORMED_PAYLOAD,
                    f"{_fmt_path(parts)} is nested too deep (limit {limits.max_depth})",
                    path=_fmt_path(parts),
                )
            if len(value) > limits.max_array_len:
                raise MotionError(
                    E.TOO_LARGE,
                    f"{_fmt_path(parts)} has {len(value)} elements, more than the "
                    f"limit {limits.max_array_len}",
                    path=_fmt_path(parts),
                )
            for i in range(len(value) - 1, -1, -1):
                stack.append((value[i], (*parts, i), depth + 1))
        elif isinstance(value, _BadMap):
            path = _fmt_path(parts)
            where = path or "payload"
            if value.reason == "duplicate":
                raise MotionError(
                    E.SCHEMA, f"{where} has the key {value.key!r} twice", path=_fmt_path((*parts, value.key))
                )
            raise MotionError(
                E.SCHEMA, f"{where} has a non-string key {_short(value.key)}; keys must be strings", path=path
            )
        elif isinstance(value, bool):
            raise MotionError(
                E.TYPE,
                f"{_where(parts, obj)} is a bool ({value!r}); no job field is a bool, "
                "expected a number or a string",
                path=_fmt_path(parts),
            )
        elif isinstance(value, int):
            if not -MAX_SAFE_INT <= value <= MAX_SAFE_INT:
                raise MotionError(
                    E.TYPE,
                    f"{_where(parts, obj)} is the integer {value}, outside +-2**53 (not exact as a float64)",
                    path=_fmt_path(parts),
                )
        elif isinstance(value, float):
            if not math.isfinite(value):
                name = "NaN" if math.isnan(value) else ("inf" if value > 0 else "-inf")
                raise MotionError(E.NONFINITE, f"{_where(parts, obj)} is {name}", path=_fmt_path(parts))
        elif isinstance(value, str):
            if len(value) > limits.max_str_len:
                raise MotionError(
                    E.TOO_LARGE,
                    f"{_fmt_path(parts)} is a string of {len(value)} characters, "
                    f"more than the limit {limits.max_str_len}",
                    path=_fmt_path(parts),
                )
        elif value is None:
            pass  # nil: the job validator decides whether the field may be absent/null
        elif isinstance(value, bytes | bytearray):
            raise MotionError(
                E.TYPE,
                f"{_where(parts, obj)} is binary data (msgpack bin), expected a number or a string",
                path=_fmt_path(parts),
            )
        else:
            raise MotionError(
                E.TYPE,
                f"{_where(parts, obj)} is a msgpack extension value ({type(value).__name__}),"
                " expected a number or a string",
                path=_fmt_path(parts),
            )


def _canonical(value: Any) -> Any:
    if isinstance(value, dict):
        return [[k, _canonical(value[k])] for k in sorted(value)]
    if isinstance(value, list):
        return [_canonical(v) for v in value]
    if isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    return value


def body_hash(body: Mapping[str, Any]) -> str:
    """SHA-256 of the canonical form of a job body (sorted keys, ints as floats)."""
    packed = msgpack.packb(_canonical(dict(body)), use_bin_type=True)
    return hashlib.sha256(packed).hexdigest()


def decode_submission(
    data: bytes | bytearray | memoryview, limits: PayloadLimits = DEFAULT_LIMITS
) -> Submission:
    """Decode and check one submission; raises `MotionError`, never anything else."""
    try:
        raw = bytes(data)
    except Exception:
        raise MotionError(E.MALFORMED_PAYLOAD, "payload is not bytes") from None
    if len(raw) > limits.max_bytes:
        raise MotionError(E.TOO_LARGE, f"payload is {len(raw)} bytes, more than the limit {limits.max_bytes}")
    if not raw:
        raise MotionError(E.MALFORMED_PAYLOAD, "empty payload (expected a msgpack map)")
    obj = _unpack(raw, limits)
    hint = obj.get("job_id") if isinstance(obj, dict) else None
    try:
        return _submission(obj, limits)
    except MotionError as err:
        if isinstance(hint, str) and valid_job_id(hint):
            err.job_id = hint
        raise


def _submission(obj: Any, limits: PayloadLimits) -> Submission:
    if isinstance(obj, _BadMap):
        _check_tree({"": obj}, limits)  # reports the key problem with the payload as its place
    if not isinstance(obj, dict):
        raise MotionError(E.SCHEMA, f"payload must be a msgpack map (the job), got {type(obj).__name__}")
    try:
        _check_tree(obj, limits)
    except MotionError:
        raise
    except Exception as exc:  # defensive: the walk only inspects builtins, but never crash on input
        raise MotionError(E.MALFORMED_PAYLOAD, f"could not check payload: {type(exc).__name__}") from None
    job_id = obj.pop("job_id", None)
    if job_id is not None:
        if not isinstance(job_id, str):
            raise MotionError(E.TYPE, f"job_id must be a string, got {_short(job_id)}", path="job_id")
        try:
            check_name(job_id, "job_id", path="job_id")  # the one rule of names (docs/formats.md)
        except ValueError as exc:
            raise E.error_from_exception(exc) from None
    if "kind" not in obj:
        raise MotionError(E.SCHEMA, "missing field 'kind' (one of path, move, timed, pvt)", path="kind")
    hashed = body_hash(obj)
    start_current = obj.get("start") == START_CURRENT
    if start_current:
        if obj.get("kind") not in ("path", "move"):
            raise MotionError(
                E.SCHEMA,
                f"start = {START_CURRENT!r} applies to path and move jobs (a {obj.get('kind')} job keeps its "
                "own timing from its first row)",
                path="start",
            )
        del obj["start"]  # the service plans from where the axes stand; the planner never sees it
    return Submission(job_id=job_id, body=obj, body_hash=hashed, start_current=start_current)


def decode_job(
    data: bytes | bytearray | memoryview, cell: Any, limits: PayloadLimits = DEFAULT_LIMITS
) -> tuple[Submission, Any]:
    """The whole job decoder: bytes -> (submission, the planner's validated `Job`).

    Raises `MotionError` and nothing else: payload problems with their codes, the planner's
    `PlanningError` with its code/path/message, and anything unexpected as INTERNAL (a bug to fix).
    This is what the service does before planning; fuzz tests drive it directly.
    """
    sub = decode_submission(data, limits)
    try:
        from planner.job import job_from_dict  # the planner owns the job schema

        return sub, job_from_dict(sub.body, cell)
    except Exception as exc:
        err = E.error_from_exception(exc)
        err.job_id = sub.job_id
        raise err from None


def encode_submission(body: Mapping[str, Any], job_id: str | None = None) -> bytes:
    """The msgpack payload for a job body (a job file's fields) and an optional job id."""
    out = dict(body)
    out.pop("job_id", None)
    if job_id is not None:
        out["job_id"] = job_id
    return pack(out)


def plain(value: Any, _depth: int = 0) -> Any:
    """A copy made only of msgpack/JSON-safe builtins (numpy scalars -> Python, NaN -> None).

    Backend reports and telemetry pass through this before they are journalled or published, so a
    numpy float or a stray object can never break the wire format.
    """
    if _depth > 32:
        return None
    if value is None or isinstance(value, bool | str):
        return value
    if isinstance(value, int):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Mapping):
        return {str(k): plain(v, _depth + 1) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [plain(v, _depth + 1) for v in value]
    item = getattr(value, "item", None)  # numpy scalar
    if callable(item):
        try:
            return plain(item(), _depth + 1)
        except Exception:
            return str(value)
    tolist = getattr(value, "tolist", None)  # numpy array
    if callable(tolist):
        try:
            return plain(tolist(), _depth + 1)
        except Exception:
            return str(value)
    if hasattr(value, "value") and isinstance(getattr(value, "value", None), str):  # enums
        return value.value
    return str(value)


def pack(obj: Any) -> bytes:
    """msgpack encoding used for every reply, event and telemetry sample."""
    packed: bytes = msgpack.packb(obj, use_bin_type=True)
    return packed


def unpack(data: bytes | bytearray | memoryview, *, max_bytes: int = 64 * 1024 * 1024) -> Any:
    """Decode a reply/event from the service (the client side; bounded, strict about bytes)."""
    raw = bytes(data)
    if len(raw) > max_bytes:
        raise MotionError(E.TOO_LARGE, f"message of {len(raw)} bytes exceeds {max_bytes}")
    try:
        return msgpack.unpackb(raw, raw=False, strict_map_key=False)
    except Exception as exc:
        raise MotionError(E.MALFORMED_PAYLOAD, f"not a valid msgpack message: {exc}"[:300]) from None
