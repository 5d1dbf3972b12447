"""Errors with a stable machine-readable code.

Every rejection the product makes is a `PlanningError` with a `code` (stable: clients switch on it), a
`path` naming the offending field ("waypoints[7][2]", "" when no single field is to blame) and a message
naming the axis and the value. The planner never returns None for failure and never lets a raw
ruckig, numpy or numba exception escape.
"""

from __future__ import annotations

from typing import Any

# Stable codes (documented in docs/formats.md and docs/api.md).
INFEASIBLE = "INFEASIBLE"
LIMITS = "LIMITS"
LIMITS_EXCEED_DRIVE = "LIMITS_EXCEED_DRIVE"
NONFINITE = "NONFINITE"
AXIS_COUNT = "AXIS_COUNT"
AXIS_ID = "AXIS_ID"
DEGENERATE = "DEGENERATE"
NON_MONOTONIC = "NON_MONOTONIC"
POSITION_LIMIT = "POSITION_LIMIT"
ENCODING_RANGE = "ENCODING_RANGE"
SCHEMA = "SCHEMA"
TYPE = "TYPE"
CONFIG = "CONFIG"
TOO_LARGE = "TOO_LARGE"
MODULO_RANGE = "MODULO_RANGE"  # a modulo target outside what its mode allows (seed 002: MODULO_SHORT)

CODES = frozenset(
    {
        INFEASIBLE,
        LIMITS,
        LIMITS_EXCEED_DRIVE,
        NONFINITE,
        AXIS_COUNT,
        AXIS_ID,
        DEGENERATE,
        NON_MONOTONIC,
        POSITION_LIMIT,
        ENCODING_RANGE,
        SCHEMA,
        TYPE,
        CONFIG,
        TOO_LARGE,
        MODULO_RANGE,
    }
)


class PlanningError(ValueError):
    """A rejected job, config or plan. `code` is stable; `path` names the field; `detail` is extra data."""

    def __init__(self, code: str, message: str, *, path: str = "", detail: dict[str, Any] | None = None):
        if code not in CODES:
            raise ValueError(f"unknown error code {code!r}")
        super().__init__(message)
        self.code = code
        self.path = path
        self.message = message
        self.detail = dict(detail or {})

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"code": self.code, "path": self.path, "message": self.message}
        if self.detail:
            out["detail"] = self.detail
        return out

    def __repr__(self) -> str:
        return f"PlanningError({self.code!r}, {self.message!r}, path={self.path!r})"


class EncodingRangeError(PlanningError):
    """A value does not fit its wire field (int32 position, int24 velocity, uint8 time)."""

    def __init__(self, message: str, *, path: str = "", detail: dict[str, Any] | None = None):
        super().__init__(ENCODING_RANGE, message, path=path, detail=detail)
