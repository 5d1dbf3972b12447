"""`pvt demo` on the cyclic families (issue 12 section 3/4): configs/xtrapuls.toml (six XtrapulsPac axes, PV,
10 ms, two multiplexed groups) and configs/mixed.toml (three EPOS, three XtrapulsPac on one bus), in virtual
and real time, with the same guarantees as the EPOS demo:

- every axis starts on the same SYNC;
- each cyclic drive's own position demand, at every internal cycle (1 ms tick) of the simulated drive, is
  within the deviation bound the planner reported for the axis; the EPOS axes' records are the plan's;
- the final position is exact;
- every cycle's set point was on the wire before its SYNC (at least 100 us: the XtrapulsPac's error 50),
  and the set points decoded from bus.log are the plan's, once per SYNC, through to the end.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from wire_context import explain_failure

from bus.cob import SYNC_COB_ID
from bus.families import setpoint_slots
from bus.sim.virtual import VirtualCell
from planner.encoding import cyclic
from streamer import demo
from streamer.cli.demo import guarantees
from streamer.report import decode_candump, decode_setpoints
from streamer.runtime.virtual import VirtualRuntime
from streamer.splice_planners import make_stop_planner

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = {"xtrapuls": ROOT / "configs" / "xtrapuls.toml", "mixed": ROOT / "configs" / "mixed.toml"}


def tick_log(vcell: VirtualCell) -> dict[int, list[tuple[float, int]]]:
    """Instrument the simulated cyclic drives: (time, position demand) at every internal 1 ms tick. A drive
    locked to SYNC runs the ticks of the period that just ended at each SYNC: tick i of n is at
    t_sync - (n - i) ms."""
    log: dict[int, list[tuple[float, int]]] = {}
    for node, m in vcell.models.items():
        if m.profile.kind != "cyclic":
            continue
        rows: list[tuple[float, int]] = []
        raw: list[int] = []
        log[node] = rows

        def record(demands: Iterable[int], _raw: list[int] = raw) -> Iterator[int]:
            for d in demands:
                _raw.append(d)
                yield d

        def traced_integrate(demands: Iterable[int], _integrate: Any = m._integrate, _record: Any = record) -> int:
            return int(_integrate(_record(demands)))

        def traced_on_sync(t: float, data: bytes = b"", _on_sync: Any = m.on_sync, _raw: list[int] = raw,
                           _rows: list[tuple[float, int]] = rows) -> Any:
            before = len(_raw)
            out = _on_sync(t, data)
            ticks = _raw[before:]
            for i, d in enumerate(ticks, start=1):
                _rows.append((t - (len(ticks) - i) * 1e-3, d))
            return out

        m._integrate = traced_integrate  # type: ignore[method-assign]
        m.on_sync = traced_on_sync  # type: ignore[method-assign]
    return log


def check_cyclic_wire(report: dict[str, Any], out: Path, cell: Any, traj: Any, trace: Any) -> None:
    """Set points from bus.log: each at least 100 us before the SYNC after it, one per SYNC per axis from the
    start to the end, and the plan's (the drive's curve through them within the planner's bound)."""
    slots = setpoint_slots(cell.axes)
    start = {n: int(traj.positions[i, 0]) for i, n in enumerate(traj.node_ids)}
    sent = decode_setpoints(out / "bus.log", slots, start, since_s=report["job_start_s"])
    with can.LogReader(str(out / "bus.log")) as reader:
        syncs = np.array([m.timestamp for m in reader if m.arbitration_id == SYNC_COB_ID])
    period = cell.sync_period_ms
    for i, node in enumerate(traj.node_ids):
        if node not in slots:
            continue
        rows = sent[node]
        assert rows, f"node {node}: no set points on the wire"
        times = np.array([r[0] for r in rows])
        k = np.searchsorted(syncs, times, side="right")
        k = k[k < syncs.size]
        margins = syncs[k] - times[: k.size]
        assert margins.min() >= 100e-6, f"node {node}: a set point {1e6 * margins.min():.0f} us before its SYNC"
        # from the frame sent after SYNC S - 1 on: set point 1, 2, ... N of the plan, each once, in order
        sp = cyclic.sample(traj.plan.positions[i], traj.plan.velocities[i], period,
                           pv=traj.stats[i].interpolation == "pv")
        t_before = trace.sync_times[report["axes"][0]["start_sync"] - 1]
        after = [r for r in rows if r[0] > t_before]
        before = [r for r in rows if r[0] <= t_before]
        assert before and all(r[1] == sp.positions[0] for r in before), f"node {node}: holds before the start"
        moving = [r[1] for r in after[:sp.n]]
        assert moving == [int(x) for x in sp.positions[1:]], f"node {node}: the wire's set points are not the plan's"
        assert all(r[1] == sp.positions[-1] for r in after[sp.n:])  # then the hold at the end
        decoded = cyclic.Setpoints(period, np.array([before[-1][1], *moving], dtype=np.int64),
                                   np.array([before[-1][2]] + [r[2] for r in after[:sp.n]], dtype=np.int64))
        dev = cyclic.deviation(traj.plan.positions[i], decoded, traj.stats[i].interpolation)[0]
        assert dev <= traj.stats[i].max_deviation_counts


def check_family_demo(report: dict[str, Any], traj: Any, out: Path, cell: Any, trace: Any) -> None:
    axes = report["axes"]
    assert report["result"] == "done", explain_failure(report, out, trace)
    assert len({a["start_sync"] for a in axes}) == 1 and axes[0]["start_sync"] is not None
    for a, st in zip(axes, traj.stats, strict=True):
        assert a["errors"] == [], a
        assert a["interpolation"] == st.interpolation
        assert a["max_deviation_counts"] <= traj.tolerance_counts, a
        assert a["final_position_error_counts"] == 0, a
    fifo = [n for n, a in zip(traj.node_ids, axes, strict=True) if a["interpolation"] == "pvt"]
    if fifo:
        sent = decode_candump(out / "bus.log", fifo, report["job_start_s"])
        for i, node in enumerate(traj.node_ids):
            if node in fifo:
                assert sent[node] == traj.records(i)
    check_cyclic_wire(report, out, cell, traj, trace)
    assert guarantees(report, traj.tolerance_counts) == []


@pytest.mark.virtual  # virtual time only: `make test` runs it on every core
@pytest.mark.parametrize("name", ["xtrapuls", "mixed"])
def test_family_demo_virtual_time(tmp_path: Path, name: str) -> None:
    cell, _job, traj = demo.prepare(CONFIGS[name])
    report, trace = demo.run_fast(cell, traj, tmp_path)
    check_family_demo(report, traj, tmp_path, cell, trace)
    assert json.loads((tmp_path / "report.json").read_text()) == report
    assert (tmp_path / "motion.png").stat().st_size > 10_000 and (tmp_path / "job.mcap").exists()


@pytest.mark.virtual  # virtual time only: `make test` runs it on every core
@pytest.mark.parametrize("name", ["xtrapuls", "mixed"])
def test_each_cyclic_drive_stays_within_its_bound_at_every_internal_cycle(name: str) -> None:
    cell, _job, traj = demo.prepare(CONFIGS[name])
    vcell = VirtualCell(cell, initial_positions=demo.start_positions(cell, traj))
    log = tick_log(vcell)
    rt = VirtualRuntime(cell, vcell=vcell)
    result = rt.run(traj, stop_planner=make_stop_planner(cell, traj))
    assert result.coordinator.outcome is not None and result.coordinator.outcome.result.value == "done"
    s = result.coordinator.start_sync
    assert s is not None
    t_start = result.trace.sync_times[s]
    planned = traj.planned_demand()
    checked = 0
    for i, node in enumerate(traj.node_ids):
        if node not in log:
            continue
        bound = traj.stats[i].max_deviation_counts
        for t, d in log[node]:
            k = round((t - t_start) * 1000.0)
            if 0 <= k <= traj.duration_ms:
                assert abs(d - int(planned[i, k])) <= bound, (node, k, d, int(planned[i, k]), bound)
                checked += 1
    assert checked >= sum(1 for n in traj.node_ids if n in log) * traj.duration_ms


@pytest.mark.realtime
@pytest.mark.parametrize("name", ["xtrapuls", "mixed"])
def test_family_demo_real_time(tmp_path: Path, name: str) -> None:
    cell, _job, traj = demo.prepare(CONFIGS[name])
    report, trace = demo.run_realtime(cell, traj, tmp_path, plot=False)
    check_family_demo(report, traj, tmp_path, cell, trace)
