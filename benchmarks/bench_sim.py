"""Simulated drive throughput in virtual time (bus/sim): how much faster than real time it runs.

Each scenario boots a `VirtualCell` (drives configured exactly as over SDO), enables the drives,
primes their FIFOs, starts ip mode on one SYNC and then streams a sinusoidal PVT trajectory (10 ms
segments) the way the streamer does: every SYNC it reads each drive's TPDO1 (free size) and tops the
FIFO up through RPDO2 frames. Reported:

- drive ticks per second (one tick = 1 ms of one drive's position loop + interpolation);
- the ratio simulated time / wall time (>1 = faster than real time; the per-SYNC frame handling,
  PDO decoding and record feeding are included, nothing is skipped).

Run: python -m benchmarks.bench_sim   (or via python -m benchmarks)
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

from bus import cob, codec
from bus.sim.virtual import VirtualCell
from planner.config import CellConfig, load_cell
from planner.encoding import record
from planner.encoding.hermite import counts_per_ms_to_rpm

AMPLITUDE_COUNTS = 30_000.0
PERIOD_S = 2.0
SEGMENT_MS = 10
FIFO_TARGET = 48


def _record(k: int, counts_per_rev: int) -> bytes:
    """Knot k of x(t) = A (1 - cos(2 pi t / P)) at t = k * SEGMENT_MS."""
    t = k * SEGMENT_MS / 1000.0
    w = 2.0 * math.pi / PERIOD_S
    p = AMPLITUDE_COUNTS * (1.0 - math.cos(w * t))
    v_counts_per_ms = AMPLITUDE_COUNTS * w * math.sin(w * t) / 1000.0
    return record.pack((round(p), round(counts_per_ms_to_rpm(v_counts_per_ms, counts_per_rev)), SEGMENT_MS))


def run(cell: CellConfig, simulated_s: float) -> dict[str, float]:
    """Stream for `simulated_s` of drive time; returns wall time, ticks, ratio."""
    vc = VirtualCell(cell)
    period = cell.sync_period_s
    nodes = [a.node_id for a in cell.axes]
    cpr = {a.node_id: a.counts_per_rev for a in cell.axes}
    next_knot = dict.fromkeys(nodes, 1)
    t = 0.0

    def sync() -> list[codec.Frame]:
        nonlocal t
        t += period
        out = vc.advance(t)
        return out + vc.sync(t)

    for cw in (0x0006, 0x000F):
        for n in nodes:
            vc.deliver(cob.rpdo1_id(n), cob.pack_controlword(cw), t)
        sync()
    for n in nodes:
        vc.sdo_write(n, 0x60C4, 6, 0)
        vc.sdo_write(n, 0x60C4, 6, 1)
        for _ in range(FIFO_TARGET):
            vc.deliver(cob.rpdo2_id(n), _record(next_knot[n], cpr[n]), t)
            next_knot[n] += 1
    for n in nodes:
        vc.deliver(cob.rpdo1_id(n), cob.pack_controlword(0x001F), t)
    syncs = max(1, round(simulated_s / period))
    # the records a streamer would send, encoded up front (the benchmark measures the drives)
    knots = syncs * round(cell.sync_period_ms / SEGMENT_MS + 1) + FIFO_TARGET + 2
    records = {n: [_record(k, cpr[n]) for k in range(next_knot[n] + knots)] for n in nodes}
    tpdo1 = {cob.tpdo1_id(n): n for n in nodes}
    ticks0 = sum(m.counters.ticks for m in vc.models.values())
    clock = time.perf_counter
    drives_s = 0.0  # time spent inside the drive models (sync, timers, frame handling)
    start = clock()
    for _ in range(syncs):
        t0 = clock()
        frames = sync()
        drives_s += clock() - t0
        for frame in frames:
            node = tpdo1.get(frame.cob_id, 0)
            if not node:
                continue
            free = codec.decode_tpdo1(frame.data).free_size
            recs = records[node]
            for _ in range(free - (64 - FIFO_TARGET)):
                t0 = clock()
                vc.deliver(cob.rpdo2_id(node), recs[next_knot[node]], t)
                drives_s += clock() - t0
                next_knot[node] += 1
    wall = clock() - start
    ticks = sum(m.counters.ticks for m in vc.models.values()) - ticks0
    faults = sum(m.counters.faults for m in vc.models.values())
    if faults:
        logs = [m.fault_log for m in vc.models.values()]
        raise RuntimeError(f"benchmark trajectory faulted a drive: {logs}")
    simulated = syncs * period
    return {"wall_s": wall, "simulated_s": simulated, "ticks": ticks, "ticks_per_s": ticks / wall,
            "ratio": simulated / wall, "drives_ratio": simulated / drives_s}


def best_of(repeats: int, cell: CellConfig, simulated_s: float) -> dict[str, float]:
    """The fastest of `repeats` runs (the machine is shared: the minimum is the least disturbed)."""
    return max((run(cell, simulated_s) for _ in range(repeats)), key=lambda r: r["ratio"])


def main() -> int:
    demo = load_cell(load_demo_path())
    print("bench_sim: simulated EPOS IPM drives in virtual time "
          "(sinusoid, 10 ms PVT segments, FIFO kept at 48; best of 3)")
    for label, cell, seconds, target in (
        ("1 drive  @ 10 ms SYNC", replace(demo.with_axes(1), sync_period_ms=10), 20.0, ""),
        ("6 drives @ 10 ms SYNC", demo, 10.0, " (target >= 100x)"),
        ("32 drives @ 1 ms SYNC", replace(demo.with_axes(32), sync_period_ms=1), 1.0, " (target > 1x)"),
    ):
        r = best_of(3, cell, seconds)
        print(f"  {label}: {r['ticks_per_s']:,.0f} drive ticks/s; {r['ratio']:.1f}x real time with the "
              f"master-side frame handling, {r['drives_ratio']:.1f}x for the drives alone{target}")
    return 0


def load_demo_path() -> str:
    from planner.config import default_config_path

    return str(default_config_path())


if __name__ == "__main__":
    raise SystemExit(main())
