"""What the streamer core needs from a trajectory and from the stop planner (Protocols), and the validated
per-job copy of the records it streams (`StreamPlan`).

The core does not import the planner's `PvtTrajectory`: it takes anything with `n_axes`, `node_ids`,
`dt_ms` (the shared grid), `positions` (knot 0 is the start) and `records(axis)` (the end record appended
when missing), and turns it into a `StreamPlan` once, at job construction: every record checked against
the grid and packed to its wire bytes, so nothing fails to encode on the SYNC thread. A stop planner is
any callable `StopRequest -> trajectory-like` whose knot 0 is exactly the requested state. An open-ended
trajectory becomes an open `StreamPlan` extended chunk by chunk (open_stream.py).
"""

from __future__ import annotations

import operator
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

from planner.encoding.record import PvtRecord, pack


class PvtTrajectoryLike(Protocol):
    """The part of a planned trajectory the streamer uses (planner.PvtTrajectory satisfies it)."""

    @property
    def n_axes(self) -> int: ...

    @property
    def node_ids(self) -> Sequence[int]: ...

    @property
    def dt_ms(self) -> Any: ...  # N ints (sequence or numpy array)

    @property
    def positions(self) -> Any: ...  # positions[axis][k], counts

    def records(self, axis: int) -> Sequence[PvtRecord]: ...


@dataclass(frozen=True)
class StopRequest:
    """The state all axes are in at the end of what is queued, which a stop trajectory must start from.

    `knot_index` counts plan records already queued (the state is that of knot `knot_index`), `time_ms`
    is that knot's time from the job start. Positions are counts, velocities rpm (the wire values), and
    accelerations the drive's Hermite acceleration at the end of the last queued segment in counts/ms^2
    (None when counts_per_rev is not configured).
    """

    knot_index: int
    time_ms: int
    node_ids: tuple[int, ...]
    positions_counts: tuple[int, ...]
    velocities_rpm: tuple[int, ...]
    accelerations_counts_per_ms2: tuple[float, ...] | None


StopPlanner = Callable[[StopRequest], PvtTrajectoryLike]
ChangePlanner = Callable[[StopRequest], PvtTrajectoryLike]
# the next chunk of an open-ended trajectory (given the chunk before it); None: not ready yet, ask again at the
# next SYNC (a runtime plans it on another thread); an exception: it cannot be extended (the core stops)
Extender = Callable[[PvtTrajectoryLike], PvtTrajectoryLike | None]


@dataclass(frozen=True)
class Change:
    """A change of the running motion, fed to the core like `Cancel` (the core's answer: `ChangeResult`).

    `mode` "aborting": the motion after what is already queued is replaced by the trajectory `planner`
    returns for the state at the end of the queue (a `StopRequest`: the same state a stop starts from).
    "buffered": it is appended at the plan's end (the state there is rest at the final knot), so the
    axes go on without the stop and restart of a new job. `tag` names who asked (the new job's id).
    """

    t: float
    planner: ChangePlanner
    mode: str = "aborting"
    tag: str = ""


@dataclass(frozen=True)
class EmergencyStop:
    """Stop every axis at its emergency deceleration, fed to the core like `Cancel`: `planner` plans the stop
    from the state at the end of what is queued (planner.motion.stop.plan_emergency_stop_from_wire behind
    streamer.splice_planners.make_emergency_planner) and the core splices it as the cancel's stop; when no plan is
    possible in time (none given, it raised, or it cannot be streamed in time) the core falls back to the
    drives' quick stop (controlword 0x000B) and the job fails EMERGENCY_STOP. `Coordinator.emergency` says
    which happened."""

    t: float
    planner: StopPlanner | None = None


@dataclass(frozen=True)
class ChangeResult:
    """What the core did with a `Change`: accepted (spliced at `knot`, `time_ms` from the job's start,
    the new part lasting `duration_ms`) or not (`reason`, the running motion untouched)."""

    tag: str
    mode: str
    accepted: bool
    reason: str = ""
    knot: int | None = None
    time_ms: int | None = None
    duration_ms: int | None = None
    sync: int | None = None  # the SYNC the core had seen when it decided


def _as_int(value: object, what: str) -> int:
    if isinstance(value, bool):
        raise ValueError(f"{what} must be an integer, got {value!r}")
    try:
        return operator.index(value)  # type: ignore[arg-type]
    except TypeError:
        raise ValueError(f"{what} must be an integer, got {value!r}") from None


@dataclass(frozen=True)
class StreamPlan:
    """Per-axis record streams on one shared grid, validated and packed. Construct with `from_trajectory`
    or directly (records must then include the end record)."""

    node_ids: tuple[int, ...]
    start_positions: tuple[int, ...]  # knot 0 per axis, counts
    segment_ms: tuple[int, ...]  # shared grid, N >= 1 entries in 1..255
    records: tuple[tuple[PvtRecord, ...], ...]  # per axis N + 1 records, the last one the end record
    frames: tuple[tuple[bytes, ...], ...]  # the packed records (same shape as `records`)
    # the planned motion at every ms, when the trajectory carries it (planner.Reference: positions counts,
    # velocities counts/ms, accelerations counts/ms^2, each (n_axes, M+1)): what the set points of a cyclic
    # drive are sampled from (streamer/core/cyclic_feeder.py); None: sampled from the records' own Hermite curve
    reference: tuple[Any, Any, Any] | None = field(default=None, compare=False, repr=False)
    # open-ended (a velocity move's chunk): no end record, the last knot moves; the stream goes on with the
    # next chunk (per axis N records instead of N + 1)
    open_end: bool = False

    def __post_init__(self) -> None:
        n = len(self.node_ids)
        if n == 0:
            raise ValueError("a stream plan needs at least one axis")
        if len(set(self.node_ids)) != n:
            raise ValueError(f"duplicate node ids {list(self.node_ids)!r}")
        for node in self.node_ids:
            if not 1 <= node <= 127:
                raise ValueError(f"node id {node} is outside 1..127")
        if len(self.start_positions) != n or len(self.records) != n or len(self.frames) != n:
            raise ValueError(
                f"{n} node ids but {len(self.start_positions)} start positions, "
                f"{len(self.records)} record lists and {len(self.frames)} frame lists"
            )
        n_seg = len(self.segment_ms)
        if n_seg < 1:
            raise ValueError("a stream plan needs at least one segment")
        for k, dt in enumerate(self.segment_ms):
            if not 1 <= dt <= 255:
                raise ValueError(f"segment_ms[{k}] = {dt} is outside 1..255")
        for axis, (node, recs, frames) in enumerate(
            zip(self.node_ids, self.records, self.frames, strict=True)
        ):
            where = f"axis {axis} (node {node})"
            if self.open_end:
                if len(recs) != n_seg or len(frames) != n_seg:
                    raise ValueError(f"{where} has {len(recs)} records for {n_seg} segments (an open-ended plan "
                                     "has no end record)")
                for k in range(n_seg):
                    if recs[k].time_ms != self.segment_ms[k]:
                        raise ValueError(f"{where} record {k} has time {recs[k].time_ms} ms but the shared grid "
                                         f"says {self.segment_ms[k]} ms")
                continue
            if len(recs) != n_seg + 1 or len(frames) != n_seg + 1:
                raise ValueError(
                    f"{where} has {len(recs)} records for {n_seg} segments (need {n_seg + 1} "
                    f"including the end record)"
                )
            for k in range(n_seg):
                if recs[k].time_ms != self.segment_ms[k]:
                    raise ValueError(
                        f"{where} record {k} has time {recs[k].time_ms} ms but the shared grid "
                        f"says {self.segment_ms[k]} ms"
                    )
            end, last = recs[n_seg], recs[n_seg - 1]
            if end.time_ms != 0:
                raise ValueError(f"{where} last record {end!r} is not an end record (time 0)")
            if last.velocity != 0:
                raise ValueError(
                    f"{where} final knot velocity is {last.velocity} rpm; a plan must end at rest"
                )
            if end.position != last.position or end.velocity != 0:
                raise ValueError(
                    f"{where} end record {end!r} does not repeat the final knot {last!r} at rest"
                )

    @property
    def n_axes(self) -> int:
        return len(self.node_ids)

    @property
    def n_segments(self) -> int:
        return len(self.segment_ms)

    @property
    def duration_ms(self) -> int:
        return sum(self.segment_ms)

    @classmethod
    def from_records(
        cls,
        node_ids: Sequence[int],
        start_positions: Sequence[int],
        records: Sequence[Sequence[PvtRecord | tuple[int, int, int]]],
        *,
        open_end: bool = False,
    ) -> StreamPlan:
        """Build from per-axis record lists (end record optional, none when `open_end`; the grid is taken
        from axis 0)."""
        recs: list[tuple[PvtRecord, ...]] = []
        for axis, rows in enumerate(records):
            out = [
                PvtRecord(
                    _as_int(r[0], f"axis {axis} record {k} position"),
                    _as_int(r[1], f"axis {axis} record {k} velocity"),
                    _as_int(r[2], f"axis {axis} record {k} time_ms"),
                )
                for k, r in enumerate(rows)
            ]
            if not out:
                raise ValueError(f"axis {axis} has no records")
            if out[-1].time_ms != 0 and not open_end:
                out.append(PvtRecord(out[-1].position, 0, 0))
            recs.append(tuple(out))
        if not recs:
            raise ValueError("a stream plan needs at least one axis")
        grid = tuple(r.time_ms for r in (recs[0] if open_end else recs[0][:-1]))
        frames = tuple(tuple(pack(r) for r in axis_recs) for axis_recs in recs)  # raises EncodingRangeError
        return cls(
            node_ids=tuple(_as_int(n, "node id") for n in node_ids),
            start_positions=tuple(_as_int(p, "start position") for p in start_positions),
            segment_ms=grid,
            records=tuple(recs),
            frames=frames,
            open_end=open_end,
        )

    @classmethod
    def from_trajectory(cls, traj: PvtTrajectoryLike) -> StreamPlan:
        """Validate and pack a trajectory-like object (see the module docstring)."""
        n_axes = _as_int(traj.n_axes, "n_axes")
        node_ids = [_as_int(n, "node id") for n in traj.node_ids]
        if len(node_ids) != n_axes:
            raise ValueError(f"trajectory has n_axes {n_axes} but {len(node_ids)} node ids")
        grid = [_as_int(d, f"dt_ms[{k}]") for k, d in enumerate(traj.dt_ms)]
        records = [list(traj.records(axis)) for axis in range(n_axes)]
        positions = traj.positions
        starts: list[int] = []
        for axis in range(n_axes):
            row = positions[axis]
            if len(row) != len(grid) + 1:
                raise ValueError(
                    f"positions[{axis}] has {len(row)} knots for {len(grid)} segments: positions "
                    f"must be indexed [axis][knot]"
                )
            starts.append(_as_int(row[0], f"positions[{axis}][0]"))
        plan = cls.from_records(node_ids, starts, records, open_end=bool(getattr(traj, "open_ended", False)))
        if list(plan.segment_ms) != grid:
            raise ValueError("the records' times do not match the trajectory's dt_ms grid")
        ref = getattr(traj, "plan", None)
        if ref is not None and hasattr(ref, "positions") and hasattr(ref, "velocities"):
            pos, vel = ref.positions, ref.velocities
            acc = getattr(ref, "acc_left", None)
            if len(pos) == n_axes and len(pos[0]) == plan.duration_ms + 1:
                plan = replace(plan, reference=(pos, vel, acc if acc is not None else vel * 0.0))
        return plan
