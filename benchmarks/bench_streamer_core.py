"""Benchmark: streamer core cost per axis per SYNC, and frames on the wire per PVT point.

Runs jobs through `streamer.core.Coordinator` against a minimal in-process drive loopback (a FIFO,
SYNC-locked consumption and the Hermite position demand at each SYNC; not timed) and times only the
core's `handle()` calls. The baseline, measured in the same run over the same number of axis-SYNCs,
is what the bus adapter must do anyway for the events the core consumes: decode TPDO1 and TPDO2
(`bus.cob.unpack_tpdo1/2`) and build the BufferStatus and PositionFeedback events. Ratios are the
portable number; microseconds depend on the machine.

Also reports frames per PVT point (all frames the core sends / records in the streams, end records
included; target <= 1.05) nominally and with 1% of the record frames dropped at random, and the share
of those losses the core repaired, for a sparse grid (segments >= one SYNC) and a dense one.

Run: `python -m benchmarks.bench_streamer_core` or call `main()`.
"""

from __future__ import annotations

import math
import random
import statistics
import time
from collections import deque
from collections.abc import Callable

from bus.cob import classify, pack_tpdo1, pack_tpdo2, unpack_controlword, unpack_tpdo1, unpack_tpdo2
from bus.events import BufferStatus, PositionFeedback, Send, Sync
from planner.encoding.hermite import coefficients, evaluate, round_counts, rpm_to_counts_per_ms
from planner.encoding.record import PvtRecord, unpack
from streamer.core import Coordinator, JobState, StreamerSettings, StreamPlan

CPR = 8192
PERIOD_MS = 10


def make_plan(n_axes: int, duration_ms: int, dt_choices: tuple[int, ...], seed: int) -> StreamPlan:
    """Rest-to-rest minimum-jerk moves on a random shared grid (as a planner would hand them over)."""
    rng = random.Random(seed)
    grid: list[int] = []
    while sum(grid) < duration_ms:
        grid.append(rng.choice(dt_choices))
    total = sum(grid)
    starts, records = [], []
    for _ in range(n_axes):
        p0 = rng.randint(-100_000, 100_000)
        amp = rng.choice([-1, 1]) * rng.randint(50_000, 600_000)
        rows: list[tuple[int, int, int]] = []
        t = 0
        for dt in grid:
            t += dt
            u = t / total
            pos = p0 + round(amp * (10 * u**3 - 15 * u**4 + 6 * u**5))
            vel = round(amp * (30 * u**2 - 60 * u**3 + 30 * u**4) / total * 60_000 / CPR)
            rows.append((pos, vel, dt))
        rows[-1] = (p0 + amp, 0, grid[-1])
        starts.append(p0)
        records.append(rows)
    return StreamPlan.from_records(
        list(range(1, n_axes + 1)), starts, [[PvtRecord(*r) for r in rows] for rows in records]
    )


class LoopbackDrive:
    """Minimal drive: FIFO, SYNC-locked consumption, demand at the SYNC instant (for the benchmark only)."""

    def __init__(self, node: int, start: int) -> None:
        self.node = node
        self.fifo: deque[PvtRecord] = deque()
        self.demand = start
        self.prev = (start, 0.0)
        self.into_ms = 0  # ms into the head segment
        self.active = False
        self.cw = 0x000F
        self.pending: int | None = None

    def receive(self, send: Send) -> None:
        if classify(send.cob_id).kind == "RPDO1":
            cw = unpack_controlword(send.data)
            self.pending = cw
        else:
            self.fifo.append(unpack(send.data))

    def sync(self) -> tuple[bytes, bytes]:
        if self.active:
            left = PERIOD_MS
            while left and self.fifo:
                head = self.fifo[0]
                step = min(left, head.time_ms - self.into_ms)
                self.into_ms += step
                left -= step
                if self.into_ms == head.time_ms:
                    self.fifo.popleft()
                    self.prev = (head.position, rpm_to_counts_per_ms(head.velocity, CPR))
                    self.demand = head.position
                    self.into_ms = 0
                    if self.fifo and self.fifo[0].time_ms == 0:
                        self.fifo.popleft()
                        self.active = False
                        break
            if self.active and self.into_ms and self.fifo:
                head = self.fifo[0]
                c = coefficients(
                    self.prev[0],
                    self.prev[1],
                    head.position,
                    rpm_to_counts_per_ms(head.velocity, CPR),
                    head.time_ms,
                )
                self.demand = round_counts(evaluate(c, self.into_ms - head.time_ms)[0])
        pending = self.pending
        if pending is not None:
            if pending & 0x10 and not self.cw & 0x10 and len(self.fifo) >= 2:
                self.active = True
                self.into_ms = 0
                self.prev = (self.demand, 0.0)
            self.cw = pending
            self.pending = None
        sw = 0x0027 | (0x1000 if self.active else 0x0400)
        return pack_tpdo1(sw, 64 - len(self.fifo)), pack_tpdo2(self.demand, self.demand)


def run_job(plan: StreamPlan, drop: Callable[[Send], bool] | None = None) -> tuple[Coordinator, float, int]:
    """Run one job to its end; (coordinator, seconds inside handle(), axis-SYNCs while in motion)."""
    settings = StreamerSettings(counts_per_rev=dict.fromkeys(plan.node_ids, CPR))
    core = Coordinator(plan, settings)
    drives = [LoopbackDrive(node, plan.start_positions[i]) for i, node in enumerate(plan.node_ids)]
    by_node = {d.node: d for d in drives}
    in_core = 0.0
    axis_syncs = 0
    clock = time.perf_counter
    for count in range(10_000_000):
        frames = [d.sync() for d in drives]
        t = count * PERIOD_MS / 1000.0
        events: list[object] = [Sync(count, t)]
        for d, (tp1, _) in zip(drives, frames, strict=True):
            sw, free = unpack_tpdo1(tp1)
            events.append(BufferStatus(d.node, sw, 0x8000 if sw & 0x1000 else 0, free, t, count))
        for d, (_, tp2) in zip(drives, frames, strict=True):
            actual, demand = unpack_tpdo2(tp2)
            events.append(PositionFeedback(d.node, actual, demand, t, count))
        for ev in events:
            t0 = clock()
            reaction = core.handle(ev)
            in_core += clock() - t0
            for send in reaction.sends:
                if drop is None or not drop(send):
                    by_node[send.cob_id & 0x7F].receive(send)
        if core.state in (JobState.RUNNING, JobState.FINISHING):
            axis_syncs += len(drives)
        if core.state in (JobState.DONE, JobState.CANCELLED, JobState.FAILED):
            return core, in_core, axis_syncs
    raise RuntimeError("job did not end")


def decode_baseline(n_items: int) -> float:
    """Seconds to decode n TPDO1+TPDO2 pairs into the core's events (the adapter's share)."""
    tp1, tp2 = pack_tpdo1(0x1027, 40), pack_tpdo2(123_456, 123_450)
    t0 = time.perf_counter()
    for i in range(n_items):
        sw, free = unpack_tpdo1(tp1)
        BufferStatus(1, sw, 0x8000 if sw & 0x1000 else 0, free, 0.0, i)
        actual, demand = unpack_tpdo2(tp2)
        PositionFeedback(1, actual, demand, 0.0, i)
    return time.perf_counter() - t0


def main() -> dict[str, float]:
    results: dict[str, float] = {}
    print("streamer core benchmark (virtual time, 10 ms SYNC, 1 Mbit/s)")
    print(f"{'case':<34}{'us/axis/SYNC':>14}{'TPDO decode':>13}{'ratio':>8}{'frames/point':>14}")
    for n_axes, dts, label in (
        (6, (10, 20, 30, 40), "6 axes, dt 10-40 ms"),
        (6, (5, 10, 20), "6 axes, dt 5-20 ms"),
        (16, (10, 20, 30), "16 axes, dt 10-30 ms"),
    ):
        plan = make_plan(n_axes, 30_000, dts, seed=n_axes)
        costs, bases = [], []
        core = None
        for _ in range(3):
            core, in_core, axis_syncs = run_job(plan)
            assert core.state is JobState.DONE, core.outcome
            costs.append(in_core / axis_syncs * 1e6)
            bases.append(decode_baseline(axis_syncs) / axis_syncs * 1e6)
        assert core is not None
        cost, base = statistics.median(costs), statistics.median(bases)
        fpp = core.report().frames_per_point
        print(f"{label:<34}{cost:>14.2f}{base:>13.2f}{cost / base:>8.2f}{fpp:>14.4f}")
        results[f"us_per_axis_sync[{label}]"] = cost
        results[f"ratio_vs_tpdo_decode[{label}]"] = cost / base
        results[f"frames_per_point[{label}]"] = fpp

    print()
    print("1% of PVT record frames dropped at random (6 axes; a job stops at its first unrepairable loss)")
    print(
        f"{'grid':<32}{'jobs':>5}{'dropped':>9}{'detected':>10}{'repaired':>10}{'share':>7}{'done':>6}"
        f"{'frames/point':>14}"
    )
    for dts, label, n_jobs, duration in (
        ((10, 20, 30, 40), "sparse: dt 10-40 ms (<=1/SYNC)", 5, 30_000),
        ((2, 3, 5), "dense: dt 2-5 ms (2-5/SYNC)", 20, 10_000),
    ):
        dropped = detected = repaired = done = 0
        fpps = []
        for seed in range(n_jobs):
            rng = random.Random(seed)
            count = [0]

            def drop(send: Send, rng: random.Random = rng, count: list[int] = count) -> bool:
                if send.cob_id & 0x780 == 0x300 and rng.random() < 0.01:
                    count[0] += 1
                    return True
                return False

            core, _, _ = run_job(make_plan(6, duration, dts, seed=100 + seed), drop)
            dropped += count[0]
            detected += sum(t.losses_detected for t in core.telemetry())
            repaired += sum(t.losses_repaired for t in core.telemetry())
            done += core.state is JobState.DONE
            if core.state is JobState.DONE:
                fpps.append(core.report().frames_per_point)
        share = repaired / detected if detected else math.nan
        fpp = statistics.mean(fpps) if fpps else math.nan
        print(
            f"{label:<32}{n_jobs:>5}{dropped:>9}{detected:>10}{repaired:>10}{share:>7.0%}{done:>6}{fpp:>14.4f}"
        )
        results[f"repair_share[{label}]"] = share
    return results


if __name__ == "__main__":
    main()
