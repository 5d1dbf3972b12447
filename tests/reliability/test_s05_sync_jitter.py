"""Scenario 5: SYNC jitter of +-30% of the period on every SYNC interval, and one gap of 1.4 periods:
no fault, and a deviation within what the jitter explains.

The drives' clocks are locked to SYNC (0x1006 = the period): each SYNC runs exactly one period of 1 ms
interpolation ticks, however long the interval was. So the interpolation, as a function of the SYNC
count, is the plan to the count (the per-ms deviation stays within the planner's tolerance); jitter
only moves *when*, in wall time, a given plan ms is executed. The bound that jitter explains, per axis:
|demand(t) - plan(t)| <= v_max * max|dt| + tolerance + 1, where dt is how far the SYNC that ran a plan
ms is from its nominal time (jitter is per SYNC, the 1.4x gap shifts every later SYNC by 0.4 period)
and v_max the axis' largest planned speed (counts/ms). Nothing faults: the 1.4x gap is below the
drives' 1.5x SYNC-loss threshold, and a +-30% interval never reaches it.

The same for the drives whose clock is not the SYNC count (their own, or timed by the SYNCs they receive),
and for every reading on the SYNCs of a real-time master: late by a little each, now and then by 4.5 ms."""

from __future__ import annotations

import dataclasses
import random
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from reliability_kit import SEED, Rig, demo_traj, long_traj

from streamer.core import JobState
from streamer.core.attribution import FeedbackLog
from streamer.core.job_state import JobReport
from streamer.report import build_report
from tests.runtime.test_variants import VARIANTS

JITTER = 0.30  # of the period, on the interval between consecutive SYNCs
GAP = 1.4


def jittery_sync_time(period_s: float, seed: int, gap_cycle: int) -> Callable[[int], float]:
    """t_n = n T + j_n (+ 0.4 T after the gap), j_n uniform in +-JITTER/2 T: every interval within
    +-JITTER T of T; the two SYNCs around the gap are exact so that interval is exactly GAP T."""

    def jitter(n: int) -> float:
        if n in (gap_cycle - 1, gap_cycle):
            return 0.0
        return random.Random(seed * 1_000_003 + n).uniform(-JITTER / 2, JITTER / 2) * period_s

    def sync_time(n: int) -> float:
        return n * period_s + jitter(n) + ((GAP - 1.0) * period_s if n >= gap_cycle else 0.0)

    return sync_time


def test_sync_jitter_and_a_short_gap_cause_no_fault_and_only_the_explained_deviation() -> None:
    traj = long_traj()
    period_s = 0.01
    gap_cycle = 2500  # ~25 s into the job, in motion
    sync_time = jittery_sync_time(period_s, SEED, gap_cycle)
    intervals = np.diff([sync_time(n) for n in range(0, 8000)]) / period_s
    assert intervals.min() >= 1 - JITTER - 1e-9 and intervals.max() <= GAP + 1e-9
    others = intervals[np.arange(intervals.size) != gap_cycle - 1]
    assert abs(intervals[gap_cycle - 1] - GAP) < 1e-9 and others.max() <= 1 + JITTER + 1e-9

    rig = Rig(traj, sync_time=sync_time)
    result = rig.run()
    core = result.coordinator
    assert core.state is JobState.DONE, core.outcome
    for node, m in rig.vcell.models.items():
        assert m.counters.emcy_sent == 0 and m.counters.sync_gaps == 0, (node, m.fault_log)
    # the interpolation itself is the plan, to the tolerance, at every ms
    tol = traj.tolerance_counts
    assert max(rig.ms_deviation().values()) <= tol
    # against wall time: the demand each drive reported at each SYNC vs the plan at that SYNC's time
    start = core.start_sync
    assert start is not None
    t0 = result.trace.sync_times[start]
    vmax = np.abs(np.diff(traj.plan.positions, axis=1)).max(axis=1)  # counts per ms, per axis
    measured: dict[str, float] = {}
    bounds: dict[str, float] = {}
    for i, node in enumerate(traj.node_ids):
        ax = result.trace.axes[node]
        worst = worst_dt = 0.0
        for s, demand in zip(ax.pos_sync, ax.demand, strict=True):
            if s <= start or (s - start) * 10 > traj.duration_ms:
                continue
            wall_ms = (result.trace.sync_times[s] - t0) * 1000.0
            nominal_ms = (s - start) * 10.0
            ref = float(traj.reference(min(wall_ms, traj.duration_ms) / 1000.0)[i, 0])
            worst = max(worst, abs(demand - ref))
            worst_dt = max(worst_dt, abs(wall_ms - nominal_ms))
        bound = float(vmax[i]) * worst_dt + tol + 1
        measured[traj.axis_names[i]], bounds[traj.axis_names[i]] = worst, bound
        assert worst <= bound, (node, worst, bound)
    print(f"[scenario 5] max |dt| of a SYNC vs nominal: {worst_dt:.2f} ms; deviation vs the plan in wall "
          f"time (counts) {({k: round(v) for k, v in measured.items()})} <= bound "
          f"{({k: round(v) for k, v in bounds.items()})}; per-ms interpolation deviation "
          f"{rig.ms_deviation()} (tolerance {tol})")


def send_delayed_sync_time(period_s: float, seed: int, mean_delay_us: float = 60.0) -> Callable[[int], float]:
    """t_n = n T + d_n, d_n exponential with the given mean: a real-time master's SYNCs, each leaving a little
    after its due time (a few tens of us here, more on a loaded machine), never early."""

    def sync_time(n: int) -> float:
        return n * period_s + random.Random(seed * 1_000_003 + n).expovariate(1e6 / mean_delay_us)

    return sync_time


@pytest.mark.parametrize("variant", ["optional_objects_absent", "own_clock_slow"])
@pytest.mark.parametrize("seed", [0, 3])
def test_a_drive_whose_grid_is_not_anchored_at_the_start_sync_is_judged_on_its_own_phase(
        variant: str, seed: int) -> None:
    """A drive timed by the SYNCs it receives (0x1006 absent) keeps the remainder of the SYNC intervals before
    the job: its 1 ms grid stands anywhere within a tick of the enabling SYNC. The master started its window
    at +-0.25 ms of that SYNC (the anchored own clock's reading): with SYNCs leaving 60 us late on average the
    drive was a tick "ahead" as soon as a SYNC left later than the enabling one, PROTOCOL ("position demand
    12731 at SYNC 29 is 115 counts from the plan's 12616"), here and in bench_realtime --only epos. The own
    clock, anchored there, is judged right as before."""
    rig = Rig(demo_traj(), sync_time=send_delayed_sync_time(0.01, seed), variant=VARIANTS[variant])
    core = rig.run().coordinator
    assert core.state is JobState.DONE, core.outcome
    assert max(rig.ms_deviation().values()) <= rig.traj.tolerance_counts


def late_window_sync_time(n: int) -> float:
    """10 ms SYNCs, 40-44 each 4 ms late (every interval within the drives' 1.5-period SYNC watch)."""
    return n * 0.01 + (0.004 if 40 <= n <= 44 else 0.0)


@pytest.mark.parametrize("variant", ["own_clock_fast", "optional_objects_absent"])
def test_the_report_judges_a_drive_on_its_own_time_by_when_each_sync_left(variant: str) -> None:
    """A drive with its own clock (or timed by the SYNCs it receives) runs on time, not on SYNC counts: at a SYNC
    4 ms late it has run 4 ticks more than the SYNC count says. The report judged its demand in a window around
    the SYNC count's plan ms and counted 19-70 counts "off the plan by more than its clock's stated error
    explains" (a missed guarantee in bench_realtime --only epos, own_clock_slow); it now centres the window on
    when the SYNC left. A demand really off its clock is still counted."""
    rig = Rig(demo_traj(), sync_time=late_window_sync_time, variant=VARIANTS[variant])
    result = rig.run()
    core = result.coordinator
    assert core.state is JobState.DONE, core.outcome

    def report(job: JobReport) -> dict[str, Any]:
        return build_report(rig.traj, job, result.trace, sync_period_ms=rig.cell.sync_period_ms,
                            first_sync=result.first_sync, last_sync=result.last_sync,
                            readings={a.node_id: a.probed for a in rig.cell.axes}, time_stamp=rig.cell.time_stamp)

    job = core.report()
    assert [a["unexplained_counts"] for a in report(job)["axes"]] == [0, 0, 0]
    node = rig.traj.node_ids[0]
    log, off = job.feedback[node], FeedbackLog()
    for s, demand, actual, late in zip(log.sync, log.demand, log.actual, log.late, strict=True):
        off.position(int(s), int(demand) + (1000 if s == 42 else 0), int(actual), int(late))  # SYNC 42: late
    moved = report(dataclasses.replace(job, feedback={**job.feedback, node: off}))
    assert moved["axes"][0]["unexplained_counts"] > 500  # its window spans ~300 counts there


def real_time_sync_time(seed: int, period_s: float = 0.01) -> Callable[[int], float]:
    """A real-time master's SYNCs: each leaves after its due time by an exponential delay (mean 300 us, at most
    4 ms), and one in a hundred 4.5 ms late (a preempted sender), every interval within the drives' 1.5-period
    SYNC watch."""
    rnd = random.Random(seed)
    delays: dict[int, float] = {}

    def sync_time(n: int) -> float:
        if n not in delays:
            d = min(rnd.expovariate(1e6 / 300.0), 0.004)
            delays[n] = 0.0045 if rnd.random() < 0.01 else d
        return n * period_s + delays[n]

    return sync_time


@pytest.mark.parametrize("answers", ["prompt", "late"])
@pytest.mark.parametrize("variant", ["reference", *VARIANTS])
def test_every_reading_keeps_its_guarantees_on_a_real_time_schedule(variant: str, answers: str) -> None:
    """Virtual time is one schedule of events; a real bus allows others. Every reading, with the SYNCs of a
    real-time master (late by a little each, now and then by 4.5 ms) and answers prompt or late (9 ms stated,
    up to 15 ms: some after the next SYNC): the job is DONE and the report finds no demand off the plan by more
    than the drive's clock explains. Before the two fixes above, 3 readings of 11 failed here with prompt
    answers, in 6 of their 22 runs (a false PROTOCOL on the drive timed by the SYNCs, 6-111 counts unexplained
    on every clock not locked to the SYNC count); late answers hid both, as the windows then ran on to the
    answer's time."""
    options = {**VARIANTS.get(variant, {})}
    if answers == "late":
        options.update(tpdo_latency_ms=9.0, tpdo_jitter_ms=6.0)
    for seed in (0, 1):
        rig = Rig(demo_traj(), sync_time=real_time_sync_time(seed), variant={**options, "seed": seed})
        result = rig.run()
        core = result.coordinator
        assert core.state is JobState.DONE, (seed, core.outcome)
        report = build_report(rig.traj, core.report(), result.trace, sync_period_ms=rig.cell.sync_period_ms,
                              first_sync=result.first_sync, last_sync=result.last_sync,
                              readings={a.node_id: a.probed for a in rig.cell.axes}, time_stamp=rig.cell.time_stamp)
        assert [a.get("unexplained_counts", 0) for a in report["axes"]] == [0, 0, 0], (seed, report["axes"])
