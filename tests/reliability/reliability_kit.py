"""The rig every reliability scenario (issue 7 section 2) runs on, and the measurements it asserts on.

- `cell3()`: the demo cell cut to 3 axes (j1..j3, nodes 1..3, 10 ms SYNC, 1 Mbit/s).
- jobs: `demo_traj()` (the demo pick-and-place path, ~3.6 s), `long_traj()` (the same path cycled to
  >= 60 s, ~1450 records per axis); `slow_sync_cell()` runs them at a 20 ms SYNC, where one cycle's
  batch holds several records of an axis (the planner's segments are >= 10 ms).
- `Rig`: a `VirtualRuntime` over a `VirtualCell` standing at the plan's start, with an optional
  `FaultModel` (as its `FaultLink`), SYNC timing, foreign traffic and candump log, and instrumented
  drives: every record that entered each FIFO (`entered`), the drive's position demand at every
  interpolation tick (`demand_ms`), each drive's state at the end of every SYNC cycle (`states`), and
  every frame on the wire (`wire`).
Instrumenting wraps two private methods of each `EposDrive` instance (`_append_record`, `_integrate`):
the only places where "a record entered the FIFO" and "the drive ran one 1 ms tick" are visible.
"""

from __future__ import annotations

import bisect
import dataclasses
import functools
import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from bus.cob import RPDO1_BASE, RPDO2_BASE, SYNC_COB_ID, classify, unpack_controlword
from bus.codec import Cia402State, Frame
from bus.faults import FaultLink, FaultModel
from bus.sim.epos import EposDrive
from bus.sim.virtual import VirtualCell
from planner.config import CellConfig, load_cell
from planner.encoding.record import PvtRecord
from planner.job import job_from_dict
from planner.plan import plan_job
from planner.readings import DriveReadings, SimDriveOptions
from planner.trajectory import PvtTrajectory
from streamer.core.coordinator import CW_QUICK_STOP, Coordinator
from streamer.core.fifo_feeder import framed
from streamer.core.settings import StreamerSettings
from streamer.runtime.virtual import ForeignTraffic, VirtualResult, VirtualRuntime
from streamer.splice_planners import make_stop_planner

ROOT = Path(__file__).resolve().parents[2]
SEED = int(os.environ.get("PVT_FAULT_SEED", "20260"))
STOPPING = frozenset({Cia402State.QUICK_STOP_ACTIVE, Cia402State.FAULT_REACTION_ACTIVE, Cia402State.FAULT,
                      Cia402State.SWITCH_ON_DISABLED})

_DEMO_WAYPOINTS = [
    [0.00, 0.00, 0.00],
    [0.60, 0.45, -0.55],
    [0.62, 0.70, -0.80],
    [0.60, 0.30, -0.35],
    [-0.20, 0.10, 0.40],
    [-0.85, 0.55, -0.30],
    [-0.87, 0.78, -0.60],
    [-0.40, 0.30, -0.10],
]


@functools.cache
def cell3() -> CellConfig:
    return load_cell(ROOT / "configs" / "demo.toml").with_axes(3)


@functools.cache
def demo_traj() -> PvtTrajectory:
    # the spline the scenarios' timings were measured on (its segment times decide when a burst hits)
    return plan_job(job_from_dict({"kind": "path", "axes": ["j1", "j2", "j3"], "geometry": "spline",
                                   "waypoints": [*_DEMO_WAYPOINTS, [0.0, 0.0, 0.0]]}, cell3()), cell3())


@functools.cache
def long_traj(min_s: float = 60.0) -> PvtTrajectory:
    """The demo path cycled until the motion lasts at least `min_s` (time-optimal, rest to rest). The
    acceleration-only plan: its 10-60 ms segments put 2-3 records in a 20 ms SYNC's batch, which the
    scenarios of lost and swapped records within a batch need (the jerk-limited plan's are mostly longer)."""
    reps = 18
    while True:
        body = {"kind": "path", "axes": ["j1", "j2", "j3"], "waypoints": _DEMO_WAYPOINTS * reps + [[0.0] * 3],
                "jerk_limited": False}
        traj = plan_job(job_from_dict(body, cell3()), cell3())
        if traj.duration_s >= min_s:
            return traj
        reps += 1


@functools.cache
def slow_sync_cell(sync_ms: int = 20) -> CellConfig:
    """The 3-axis cell with a slower SYNC: the planner's ~10-60 ms segments then put up to 2-3 records
    of an axis in one cycle's batch (the case where part of a batch can be lost, or swapped)."""
    return dataclasses.replace(cell3(), sync_period_ms=sync_ms)


def probed_as_simulated(cell: CellConfig) -> CellConfig:
    """The cell with every axis' [axis.probed] set to what its simulated drive does."""
    return dataclasses.replace(cell, axes=tuple(dataclasses.replace(a, probed=DriveReadings.of_sim(a.sim))
                                                for a in cell.axes))


def with_variant(cell: CellConfig, **options: Any) -> CellConfig:
    """The cell with every axis' simulated drive set to the given readings (planner/readings.py)."""
    sim = SimDriveOptions(**options)
    return dataclasses.replace(cell, axes=tuple(dataclasses.replace(a, sim=sim) for a in cell.axes))


def start_positions(traj: PvtTrajectory) -> dict[int, float]:
    return {int(n): float(traj.positions[i, 0]) for i, n in enumerate(traj.node_ids)}


@dataclass
class WireFrame:
    t: float
    cob_id: int
    data: bytes


@dataclass
class Rig:
    """One 3-axis cell in virtual time with faults and instruments (see the module docstring)."""

    traj: PvtTrajectory
    faults: FaultModel | None = None
    sync_time: Callable[[int], float] | None = None
    foreign: ForeignTraffic | None = None
    candump: Path | None = None
    settings: StreamerSettings | None = None
    cell: CellConfig = field(default_factory=cell3)
    entered: dict[int, list[PvtRecord]] = field(default_factory=dict)
    demand_ms: dict[int, dict[int, int]] = field(default_factory=dict)
    states: dict[int, dict[int, tuple[Cia402State, bool, float]]] = field(default_factory=dict)
    wire: list[WireFrame] = field(default_factory=list)
    queued: list[WireFrame] = field(default_factory=list)  # what the master queued, at its queue time
    ticks_at: dict[int, dict[int, int]] = field(default_factory=dict)  # SYNC -> node -> drive ticks run
    activated_at: dict[int, int] = field(default_factory=dict)  # node -> drive ticks run when ip mode began
    variant: dict[str, Any] = field(default_factory=dict)  # simulated drives' readings (with_variant)

    def stream(self, i: int) -> list[PvtRecord]:
        """The records the master sends axis i: the plan's, framed as the drive's readings need (an origin
        record for a drive that takes the first record as time zero, a second end record for one that
        counts the target out of its FIFO; streamer/core/fifo_feeder.py)."""
        r = self.cell.axes[[a.node_id for a in self.cell.axes].index(self.traj.node_ids[i])].probed
        return framed(self.traj.records(i), int(self.traj.positions[i, 0]), r.first_record, r.fifo_count)

    def __post_init__(self) -> None:
        # the master knows the drives' readings (as after `pvt probe --write`): the scenarios inject their
        # faults into jobs, not into the standstill probe
        if self.variant:
            self.cell = with_variant(self.cell, **self.variant)
        self.cell = probed_as_simulated(self.cell)
        self.vcell = VirtualCell(self.cell, initial_positions=start_positions(self.traj))
        for node, model in self.vcell.models.items():
            self._instrument(node, model)
        self._logger = can.Logger(str(self.candump)) if self.candump is not None else None
        self.rt = VirtualRuntime(
            self.cell,
            vcell=self.vcell,
            log=self._log,
            link=FaultLink(self.faults) if self.faults is not None else None,
            sync_time=self.sync_time,
            foreign=self.foreign,
            settings=self.settings,
        )
        send = self.rt._send

        def queue(frame: Frame, t: float) -> str | None:
            reason = send(frame, t)
            if reason is None:
                self.queued.append(WireFrame(t, frame.cob_id, bytes(frame.data)))
            return reason

        self.rt._send = queue  # type: ignore[method-assign]

    def _instrument(self, node: int, m: EposDrive) -> None:
        entered = self.entered.setdefault(node, [])
        ticks = self.demand_ms.setdefault(node, {})
        append, integrate, activate = m._append_record, m._integrate, m._activate

        def on_record(rec: PvtRecord) -> None:
            rejected = m.counters.records_rejected
            append(rec)
            if m.counters.records_rejected == rejected:
                entered.append(rec)

        def on_ticks(demands: Iterable[int]) -> int:
            lst = list(demands)
            t0 = m.counters.ticks
            done: int = integrate(lst)
            for i in range(done):
                ticks[t0 + i + 1] = lst[i]
            return done

        def on_activate() -> None:
            self.activated_at[node] = m.counters.ticks
            activate()

        m._append_record = on_record  # type: ignore[method-assign]
        m._integrate = on_ticks  # type: ignore[method-assign]
        m._activate = on_activate  # type: ignore[method-assign]

    def _log(self, t: float, cob_id: int, data: bytes) -> None:
        self.wire.append(WireFrame(t, cob_id, bytes(data)))
        if self._logger is not None:
            self._logger.on_message_received(
                can.Message(timestamp=t, arbitration_id=cob_id, data=data, is_extended_id=False, channel="vcan0"))

    def _observe(self, n: int) -> None:
        self.states[n] = {node: (m.state, m.ip_active, m.position_actual_exact)
                          for node, m in self.vcell.models.items()}
        self.ticks_at[n] = {node: m.counters.ticks for node, m in self.vcell.models.items()}

    # ---- running
    def run(self, *, on_sync: Callable[[Coordinator, int], None] | None = None, **kw: Any) -> VirtualResult:
        def hook(core: Coordinator, n: int) -> None:
            self._observe(n)
            if on_sync is not None:
                on_sync(core, n)

        try:
            self.result = self.rt.run(self.traj, stop_planner=make_stop_planner(self.cell, self.traj),
                                      on_sync=hook, **kw)
        finally:
            if self._logger is not None:
                self._logger.stop()
                self._logger = None
        return self.result

    def idle(self, seconds: float) -> None:
        self.rt.idle(seconds, on_sync=self._observe)

    # ---- measurements
    @property
    def core(self) -> Coordinator:
        return self.result.coordinator

    def _demand_rows(self) -> Iterable[tuple[int, int, dict[int, int], int]]:
        """(axis index, node, drive demand per tick, the ticks the drive had run when its ip mode began: plan
        ms k is its k-th tick after that) per axis. The ticks seen at the start SYNC's hook are the same for a
        drive locked to SYNC; a drive with its own clock ticks between SYNCs, and how many it had run when the
        hook looked depends on the frames handled before it."""
        s = self.core.start_sync
        assert s is not None, self.describe()
        for i, node in enumerate(self.traj.node_ids):
            yield i, node, self.demand_ms[node], self.activated_at.get(node, self.ticks_at[s][node])

    def ms_deviation(self) -> dict[int, int]:
        """max |drive position demand - plan| over every interpolated ms of the plan, per node (counts).
        Plan ms k is the drive's k-th tick after the start SYNC (the drive is locked to SYNC)."""
        planned = self.traj.planned_demand()
        out: dict[int, int] = {}
        for i, node, ticks, t0 in self._demand_rows():
            dev = 0
            for k in range(1, self.traj.duration_ms + 1):
                d = ticks.get(t0 + k)
                if d is None:
                    break
                dev = max(dev, abs(d - int(planned[i, k])))
            out[node] = dev
        return out

    def ms_interpolated(self) -> dict[int, int]:
        """How many plan ms each drive interpolated (all of them for a job that ran to its end)."""
        out: dict[int, int] = {}
        for _, node, ticks, t0 in self._demand_rows():
            k = 0
            while ticks.get(t0 + k + 1) is not None and k < self.traj.duration_ms:
                k += 1
            out[node] = k
        return out

    def first_deviation_ms(self, tolerance: int) -> int | None:
        """The first plan ms at which some drive's demand left the plan by more than `tolerance`."""
        planned = self.traj.planned_demand()
        first: int | None = None
        for i, _, ticks, t0 in self._demand_rows():
            for k in range(1, self.traj.duration_ms + 1):
                d = ticks.get(t0 + k)
                if d is None:
                    break
                if abs(d - int(planned[i, k])) > tolerance:
                    first = k if first is None else min(first, k)
                    break
        return first

    def stopped_after(self, sync: int) -> dict[int, tuple[Cia402State, bool]]:
        """Each drive's (state, ip active) at the end of SYNC cycle `sync`."""
        return {node: (st, ip) for node, (st, ip, _) in self.states[sync].items()}

    def master_frames_after(self, t: float) -> list[WireFrame]:
        """Frames the master queued after `t`, SYNC excepted (a record queued before a quick stop may still
        reach the wire after it: the quick stop's lower COB-ID wins the arbitration)."""
        return [w for w in self.queued if w.t > t and w.cob_id != SYNC_COB_ID
                and classify(w.cob_id).kind in ("RPDO1", "RPDO2", "NMT", "SDO_RX")]

    def quick_stops_queued(self) -> dict[int, float]:
        """When the master queued the quick-stop controlword, per node."""
        out: dict[int, float] = {}
        for w in self.queued:
            if RPDO1_BASE < w.cob_id <= RPDO1_BASE + 127 and unpack_controlword(w.data) == CW_QUICK_STOP:
                out.setdefault(w.cob_id - RPDO1_BASE, w.t)
        return out

    def quick_stops(self) -> dict[int, float]:
        """When the quick-stop controlword went on the wire, per node."""
        out: dict[int, float] = {}
        for w in self.wire:
            if RPDO1_BASE < w.cob_id <= RPDO1_BASE + 127 and unpack_controlword(w.data) == CW_QUICK_STOP:
                out.setdefault(w.cob_id - RPDO1_BASE, w.t)
        return out

    def sync_at(self, t: float) -> int:
        """The count of the last SYNC echoed at or before `t` (from the trace)."""
        times = self.result.trace.sync_times
        counts = sorted(times)
        ts = [times[c] for c in counts]
        i = bisect.bisect_right(ts, t) - 1
        return counts[i] if i >= 0 else counts[0] - 1

    def records_on_wire(self, node: int) -> list[WireFrame]:
        return [w for w in self.wire if w.cob_id == RPDO2_BASE + node]

    def describe(self) -> str:
        o = self.result.coordinator.outcome if hasattr(self, "result") else None
        return f"{self.faults.describe() if self.faults else 'no faults'}; outcome {o}"


def batch_index(rig: Rig, node: int, size: int) -> int:
    """Index (among the node's records on the wire) of the first record of the first cycle, 5 SYNCs
    into the motion, whose batch for that node held `size` records."""
    frames = rig.records_on_wire(node)
    by_sync: dict[int, list[int]] = {}
    for k, w in enumerate(frames):
        by_sync.setdefault(rig.sync_at(w.t), []).append(k)
    start = rig.core.start_sync
    assert start is not None
    for s in sorted(by_sync):
        if s > start + 5 and len(by_sync[s]) == size:
            return by_sync[s][0]
    raise AssertionError(f"no batch of {size} records for node {node}")


def assert_all_stopped_within_one_sync(rig: Rig) -> int:
    """The failing decision's SYNC m: at the end of cycle m + 1 every drive is out of ip mode and in a
    stopping state (quick stop, fault reaction, fault, switch on disabled). Returns m."""
    outcome = rig.core.outcome
    assert outcome is not None and outcome.sync is not None, outcome
    m = outcome.sync
    states = rig.stopped_after(m + 1)
    for node, (state, ip) in states.items():
        assert not ip and state in STOPPING, (node, state, ip, rig.describe())
    return m


def assert_no_motion_resumes(rig: Rig, seconds: float = 1.0) -> None:
    """After a failed job: the master sent nothing but SYNC after its quick stops, and during `seconds`
    more of SYNC no drive moves (actual position within one count) or re-enters ip mode."""
    stops = rig.quick_stops()
    assert set(stops) == set(rig.traj.node_ids), stops
    late = rig.master_frames_after(max(rig.quick_stops_queued().values()))
    assert late == [], (stops, late[:5])
    before = {n: m.position_actual_exact for n, m in rig.vcell.models.items()}
    rig.idle(seconds)
    for n, m in rig.vcell.models.items():
        assert abs(m.position_actual_exact - before[n]) < 1.0, (n, before[n], m.position_actual_exact)
        assert not m.ip_active, n
    late = rig.master_frames_after(max(rig.quick_stops_queued().values()))
    assert late == [], (stops, late[:5])
