"""The standstill probe: measure how a drive settles the points the manuals leave open, moving nothing.

For `pvt probe` and for the runtimes, for every reading `[axis.probed]` does not state. Pure: a
`StandstillProbe` says when to send SYNC and what, and is fed the answers; a driver does the I/O and SDO.
Hypothesis testing: for each combination of readings `predict` says what the drive must report, and the
ones matching everything are kept; a drive no reading explains is reported, never guessed. Experiments at
standstill: latency, timing (SYNC intervals stretched 30 %), underflow (`pvt probe` only), rounding (a
one-count move); objects present are surveyed over SDO.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum

from bus import cob, codec
from bus.codec import Frame
from bus.profile import DriveProfile, FeedbackSchedule
from planner.encoding import record
from planner.readings import MUST_KNOW, OPEN_POINTS, OPTIONAL_OBJECTS, DriveReadings

CW_ENABLE_OPERATION = 0x000F
CW_START_IP = 0x001F
STRETCH = 0.3  # of a period, per stretched SYNC interval (well inside the drives' 1.5-period SYNC watch)
LATENCY_SYNCS = 12
OWN_CLOCK_PPM = 5000.0  # the probe's own bound on a drive clock: wider than any crystal
# the timing experiment is run again (up to this many times in all) while what the drives showed leaves a
# reading open: a SYNC sent late or early by a loaded host can undo the stretched intervals that tell a
# SYNC-locked clock from an own one, and a TPDO lost or late can hide a fill change; the next run's
# schedule is another draw
TIMING_ATTEMPTS = 3
# the rounding experiment: its one-count segment lasts at least this long, and a drive whose demand shows
# the new count by this fraction of it rounds to nearest (from 0.5 on), later truncates (only at 1.0)
ROUNDING_MIN_MS = 100
ROUNDING_SPLIT = 0.75


class Phase(Enum):
    LATENCY = "latency"
    TIMING = "timing"
    UNDERFLOW = "underflow"
    ROUNDING = "rounding"
    ROUNDING_BACK = "rounding_back"
    DONE = "done"


ALL_EXPERIMENTS = (Phase.LATENCY, Phase.TIMING, Phase.UNDERFLOW, Phase.ROUNDING)
# what a runtime runs at configuration: all but the underflow test, which faults the drive (the master
# tolerates either underflow reading by design); the rounding test moves a count and back
AUTO_EXPERIMENTS = (Phase.LATENCY, Phase.TIMING, Phase.ROUNDING)


class ProbeError(RuntimeError):
    """The probe could not run (a drive faulted, did not answer, or no reading explains it)."""


@dataclass
class NodeRecord:
    """What one node did during the probe."""

    node: int
    p0: int
    latencies_ms: list[float] = field(default_factory=list)
    timing: dict[int, tuple[bool, int]] = field(default_factory=dict)  # j (SYNC s + j) -> (ip active, fill)
    underflow_j: int | None = None  # SYNC s + j at which the underflow showed (EMCY or error bit)
    # the one-count move: (j, ms since SYNC s by the SYNCs' stamps, position demand) per TPDO2
    rounding_samples: list[tuple[int, float, int]] = field(default_factory=list)
    back_demand: int | None = None
    emcys: list[tuple[str, int]] = field(default_factory=list)  # (phase, code)
    tpdo1_seen: int = 0  # TPDO1s in the current phase (sequence attribution)
    tpdo2_seen: int = 0
    last_fill: int = 0


@dataclass(frozen=True)
class NodeResult:
    node: int
    readings: DriveReadings
    evidence: tuple[str, ...]
    unexplained: str | None = None  # what the drive did that no reading explains


@dataclass(frozen=True)
class ProbeResult:
    nodes: Mapping[int, NodeResult]

    def readings(self) -> dict[int, DriveReadings]:
        return {n: r.readings for n, r in self.nodes.items()}

    def failures(self) -> list[str]:
        return [f"node {n}: {r.unexplained}" for n, r in self.nodes.items() if r.unexplained]

    def complete(self, known: Mapping[int, DriveReadings]) -> dict[int, DriveReadings]:
        """`known` readings with every unknown point taken from this probe; ProbeError when the probe
        could not explain a drive."""
        bad = self.failures()
        if bad:
            raise ProbeError("the drives' readings could not be measured: " + "; ".join(bad))
        return {n: r.merged(self.nodes[n].readings) if n in self.nodes else r for n, r in known.items()}


@dataclass(frozen=True)
class TimingPlan:
    """Record times of the timing experiment for a SYNC period, and the SYNC intervals (ms) after the
    enabling SYNC s."""

    t1: int
    t2: int
    t3: int
    stretched: int  # intervals after s+1 that are stretched
    stretch_ms: float

    @classmethod
    def for_period(cls, period_ms: int) -> TimingPlan:
        stretch = max(1.0, STRETCH * period_ms)
        k = max(2, math.ceil(4.0 / stretch))  # enough stretched intervals for >= 4 ms of difference
        # the first boundary between the SYNC-locked and the own-clock elapsed time at SYNC s+1+k
        t1 = (1 + k) * period_ms + math.floor(k * stretch / 2)
        return cls(t1=t1, t2=t1, t3=2 * period_ms + 3, stretched=k, stretch_ms=stretch)

    def interval_ms(self, j: int, period_ms: int) -> float:
        """SYNC s+j-1 -> s+j."""
        return period_ms + (self.stretch_ms if 2 <= j <= 1 + self.stretched else 0.0)

    def boundaries(self, first_record: str) -> list[int]:
        """Segment ends after the enabling SYNC (ms of drive time); the last one ends interpolation."""
        if first_record == "segment_end":
            return [self.t1, self.t1 + self.t2, self.t1 + self.t2 + self.t3]
        return [self.t2, self.t2 + self.t3]


def predict_timing(plan: TimingPlan, sampling: str, count: str, first: str, clock: str, j: int,
                   elapsed_true_ms: float, period_ms: int) -> set[tuple[bool, int]]:
    """What TPDO1 of SYNC s + j shows (ip active, fill) under one combination of readings. The FIFO held
    five records (D1, D2, D3, end, end) when the controlword started interpolation at SYNC s."""
    if j == 0 and sampling == "before_rpdo":
        return {(False, 5)}
    if clock == "sync":
        ticks = {j * period_ms}
    else:
        lo = elapsed_true_ms * (1.0 - OWN_CLOCK_PPM * 1e-6)
        hi = elapsed_true_ms * (1.0 + OWN_CLOCK_PPM * 1e-6)
        ticks = set(range(math.floor(lo) - 1, math.floor(hi) + 1))
    ends = plan.boundaries(first)
    out = set()
    for k in ticks:
        active = k < ends[-1]
        popped = sum(1 for b in ends[:-1] if b <= k) + (0 if active else 2)
        fill = 5 - popped - (1 if first == "time_zero" else 0)
        if active and count == "until_segment_start":
            fill -= 1
        out.add((active, fill))
    return out


_TIMING_POINTS = ("tpdo_sampling", "fifo_count", "first_record", "clock")


class StandstillProbe:
    """One probe of several nodes at once (see the module docstring). The driver calls `next_sync_time`,
    sends the SYNC then, feeds `on_sync`, `on_tpdo1`, `on_tpdo2`, `on_emcy` as frames come back and sends
    every frame these return at once; when `wants_enable` is set it enables the drives (operation enabled,
    buffer cleared and enabled, fault reset if needed) and calls `enabled(demands)`. Done when `done`."""

    def __init__(self, nodes: Sequence[int], period_ms: int, profile: DriveProfile, start_demands: Mapping[int, int],
                 *, experiments: Iterable[Phase] = AUTO_EXPERIMENTS, t0: float = 0.0,
                 feedback: FeedbackSchedule | None = None):
        self.period_ms = period_ms
        self.profile = profile
        self.nodes = tuple(nodes)
        self.experiments = [p for p in (Phase.LATENCY, Phase.TIMING, Phase.UNDERFLOW, Phase.ROUNDING)
                            if p in set(experiments)]
        self.plan = TimingPlan.for_period(period_ms)
        self.rec: dict[int, NodeRecord] = {n: NodeRecord(n, start_demands[n]) for n in self.nodes}
        self.phase = Phase.DONE
        self.wants_enable = False
        self._queue: list[Phase] = list(self.experiments)
        self._t = t0
        self._sync = -1
        self._sync_t: dict[int, float] = {}
        self._step = 0  # SYNCs into the current phase
        self._start: int | None = None  # the enabling SYNC of the current experiment
        self._first_record: dict[int, str] = {}
        self._limit_syncs = 0
        self.feedback = feedback
        self._counters: dict[int, int | None] = {}
        self._timing_survivors: dict[int, list[tuple[str, str, str, str]]] = {}
        self.timing_runs = 0  # how often the timing experiment ran (again while it left a reading open)
        self._rounding_start: dict[int, int] = {}
        self._records_sent: dict[int, int] = {}
        self._next_phase()

    # ---- driver interface ----------------------------------------------------------------------------
    @property
    def done(self) -> bool:
        return self.phase is Phase.DONE

    def next_sync_time(self) -> float:
        """When the driver sends the next SYNC."""
        return self._t + self._interval_s(self._step, self._sync + 1)

    def next_sync_times(self) -> list[float]:
        """The next SYNC's time and those of every SYNC after it that the probe already knows and that
        needs no frame of the driver in between: the rest of the latency phase, or the rest of an experiment
        once its interpolation was started. A driver with a cycle engine hands them over at once, so a
        stalled master thread cannot stretch a SYNC interval while a drive interpolates (the drive would
        report SYNC lost); the SYNCs' echoes are fed to `on_sync` as they come."""
        if self.phase is Phase.DONE:
            return []
        t, times = self._t, []
        known = self.phase is Phase.LATENCY or self._start is not None
        last = self._limit_syncs + 1 if known else self._step + 1  # the step that ends the phase
        for step in range(self._step, last):
            t += self._interval_s(step, self._sync + 1 + step - self._step)
            times.append(t)
        return times

    def _interval_s(self, step: int, count: int) -> float:
        """The interval before SYNC `count`, the phase's step `step` + 1."""
        p = self.period_ms / 1000.0
        if self.phase is Phase.LATENCY or step == 0:
            return max(4 * p, 0.02)  # (after a phase: a quiet gap, every answer of the last phase is in)
        j = self._j(count)
        if self.phase is Phase.TIMING and j is not None and j >= 1:
            return self.plan.interval_ms(j, self.period_ms) / 1000.0
        return p

    @property
    def syncs_seen(self) -> int:
        return len(self._sync_t)

    def on_sync(self, count: int, t: float, counter: int | None = None) -> list[Frame]:
        self._sync = count
        self._t = t
        self._sync_t[count] = t
        self._counters[count] = counter
        self._step += 1
        if self._step == 1:
            for r in self.rec.values():
                r.tpdo1_seen = r.tpdo2_seen = 0
        out: list[Frame] = []
        phase, step = self.phase, self._step
        if phase in (Phase.TIMING, Phase.UNDERFLOW, Phase.ROUNDING, Phase.ROUNDING_BACK):
            if step == 1:
                out += self._records_frames()
            elif self._start is None:
                # start once every FIFO reported all its records (a big cell's records take several cycles)
                if all(r.last_fill >= self._records_sent.get(n, 0) for n, r in self.rec.items()):
                    out += [Frame(self.profile.controlword_cob_id(n), cob.pack_controlword(CW_START_IP))
                            for n in self.nodes]
                    self._start = count + 1
                    self._limit_syncs += step
                elif step > 20:
                    raise ProbeError(f"records did not reach the FIFOs within 20 SYNCs (fills "
                                     f"{ {n: r.last_fill for n, r in self.rec.items()} })")
        if self._step > self._limit_syncs:
            self._finish_phase()
        return out

    def on_tpdo1(self, node: int, statusword: int, buffer_status: int, free_size: int, t: float) -> None:
        r = self.rec.get(node)
        if r is None or self.phase is Phase.DONE:
            return
        r.tpdo1_seen += 1
        answered = self._sync - self._step + r.tpdo1_seen  # the phase's k-th TPDO1 answers its k-th SYNC
        active = bool(buffer_status & codec.BS_IP_ACTIVE or statusword & codec.SW_IP_ACTIVE)
        fill = self.profile.fifo_depth - free_size
        r.last_fill = fill
        if self.phase is Phase.LATENCY:
            if answered in self._sync_t:
                r.latencies_ms.append((t - self._sync_t[answered]) * 1000.0)
            return
        j = self._j(answered)
        if j is None or j < 0:
            return
        if self.phase is Phase.TIMING:
            r.timing[j] = (active, fill)
        elif self.phase is Phase.UNDERFLOW and buffer_status & codec.BS_UNDERFLOW_ERROR and r.underflow_j is None:
            r.underflow_j = j

    def on_tpdo2(self, node: int, actual: int, demand: int, t: float) -> None:
        r = self.rec.get(node)
        if r is None or self.phase is Phase.DONE:
            return
        r.tpdo2_seen += 1
        fb = self.feedback
        if fb is not None and fb.every > 1:  # TPDO2 every n-th SYNC: the newest SYNC whose counter carries it
            answered = next((m for m in range(self._sync, self._sync - fb.every - 1, -1)
                             if fb.carries(node, self._counters.get(m))), self._sync)
        else:
            answered = self._sync - self._step + r.tpdo2_seen  # the phase's k-th TPDO2 answers its k-th SYNC
        j = self._j(answered)
        if self.phase is Phase.ROUNDING and j is not None and j >= 0:
            r.rounding_samples.append((j, self._elapsed_true_ms(j), demand))
        elif self.phase is Phase.ROUNDING_BACK and j is not None and j >= 0:
            r.back_demand = demand

    def on_emcy(self, node: int, code: int, t: float) -> None:
        r = self.rec.get(node)
        if r is None or code == codec.EMCY_ERROR_RESET:
            return
        r.emcys.append((self.phase.value, code))
        j = self._j(self._sync)
        if self.phase is Phase.UNDERFLOW and code == codec.EMCY_IP_BUFFER and r.underflow_j is None:
            r.underflow_j = j

    def enabled(self, demands: Mapping[int, int]) -> None:
        """The driver enabled the drives (and read their position demands)."""
        self.wants_enable = False
        for n, d in demands.items():
            if n in self.rec:
                self.rec[n].p0 = d

    # ---- phases --------------------------------------------------------------------------------------
    def _j(self, sync: int) -> int | None:
        return None if self._start is None else sync - self._start

    def _rounding_time(self) -> int:
        """The one-count segment: long enough that the SYNCs carrying TPDO2 split it finely (every 0.2 of it
        at most) and that a SYNC late by a fifth of it (a loaded host) or a drive clock that does not count
        from the SYNC the probe thinks leaves the verdict alone (`_rounding_verdict`); one record at most
        (255 ms: TPDO2 every 60 ms, a 24-axis cell at 10 ms, then splits it every 0.235, still one sample
        between the 0.5 where rounding to nearest shows the count and the verdict's 0.75)."""
        every = self.feedback.every if self.feedback is not None else 1
        return min(record.SEGMENT_TIME_MAX_MS, max(ROUNDING_MIN_MS, math.ceil(every * self.period_ms / 0.2)))

    def _rounding_verdict(self, n: int, r: NodeRecord) -> tuple[str | None, str]:
        """How node n rounds, from where its demand left the start count in the one-count move: the drive
        interpolates a smoothstep over the segment, so rounding to nearest shows the new count from half
        the segment, truncation only at its end. The verdict needs that on every clock the drive may run
        (SYNC-counted or its own, as the timing experiment left it) and is taken at 0.75 of the segment, so
        one SYNC misplaced or late by up to a fifth of the segment does not change it. Returns (reading or
        None, evidence)."""
        p0 = self._rounding_start.get(n, r.p0)
        clocks = {sv[3] for sv in self._timing_survivors.get(n, [])} or set(OPEN_POINTS["clock"])
        total = self._rounding_time()
        samples = sorted(r.rounding_samples)
        demands = sorted({d for _, _, d in samples})
        step = 1 if p0 >= 0 else -1

        def fracs(j: int, true_ms: float) -> list[float]:
            return [(j * self.period_ms if c == "sync" else true_ms) / total for c in clocks]

        moved = next(((j, t) for j, t, d in samples if d != p0), None)
        stayed = [(j, t) for j, t, d in samples if d == p0]
        where = "never" if moved is None else "at " + "/".join(f"{f:.2f}" for f in fracs(*moved))
        evidence = (f"rounding: one-count move from {p0} over {total} ms, demands {demands}, the new count {where} "
                    f"of the way (clock {'/'.join(sorted(clocks))})")
        if not set(demands) <= {p0, p0 + step}:
            return None, evidence
        if moved is not None and all(f <= ROUNDING_SPLIT for f in fracs(*moved)):
            return "nearest", evidence
        if moved is not None and all(f >= ROUNDING_SPLIT for f in fracs(*moved)) and any(
                all(f >= ROUNDING_SPLIT for f in fracs(j, t)) for j, t in stayed):
            return "toward_zero", evidence  # (a drive that never reached the count moved nothing: no verdict)
        return None, evidence

    def _next_phase(self) -> None:
        self._step = 0
        self._start = None
        if not self._queue:
            self.phase = Phase.DONE
            return
        self.phase = self._queue.pop(0)
        p = self.period_ms
        # SYNCs the phase lasts (after the enabling SYNC, for the experiments: added when it starts)
        if self.phase is Phase.LATENCY:
            self._limit_syncs = LATENCY_SYNCS
        elif self.phase is Phase.TIMING:
            for r in self.rec.values():
                r.timing.clear()  # a run again judges what this run shows, not a mix of both
            total = self.plan.t1 + self.plan.t2 + self.plan.t3
            self._limit_syncs = 1 + math.ceil(total / p) + 3
        elif self.phase is Phase.UNDERFLOW:
            self._limit_syncs = 1 + 6 + 4
        else:
            self._limit_syncs = 1 + math.ceil((self._rounding_time() + 2 * p) / p) + 3
        if self.phase is not Phase.LATENCY:
            self.wants_enable = True

    def _finish_phase(self) -> None:
        if self.phase is Phase.TIMING:
            self.timing_runs += 1
            self._analyse_timing()
            if self._timing_open() and self.timing_runs < TIMING_ATTEMPTS:
                self._queue.insert(0, Phase.TIMING)
        if self.phase is Phase.ROUNDING:
            self._queue.insert(0, Phase.ROUNDING_BACK)
        self._next_phase()

    def _origin(self, n: int, position: int) -> list[tuple[int, int, int]]:
        return [(position, 0, 1)] if self._first_record.get(n) == "time_zero" else []

    def _records_frames(self) -> list[Frame]:
        out: list[Frame] = []
        for n in self.nodes:
            p0 = self.rec[n].p0
            if self.phase is Phase.TIMING:
                # a second end record: a drive that counts the target out and checks every tick keeps two
                recs = [(p0, 0, self.plan.t1), (p0, 0, self.plan.t2), (p0, 0, self.plan.t3), (p0, 0, 0),
                        (p0, 0, 0)]
            elif self.phase is Phase.UNDERFLOW:
                recs = [(p0, 0, 3 * self.period_ms), (p0, 0, 3 * self.period_ms)]  # no end record
            elif self.phase is Phase.ROUNDING:
                step = 1 if p0 >= 0 else -1  # away from zero: there nearest and toward zero differ
                recs = [*self._origin(n, p0), (p0 + step, 0, self._rounding_time()),
                        (p0 + step, 0, 2 * self.period_ms), (p0 + step, 0, 0), (p0 + step, 0, 0)]
            else:  # back to where the rounding test started
                p_now = self.rec[n].p0
                target = self._rounding_start.get(n, p_now)
                recs = [*self._origin(n, p_now), (target, 0, 2 * self.period_ms), (target, 0, 0), (target, 0, 0)]
            out += [Frame(self.profile.record_cob_id(n), record.pack(r)) for r in recs]
            self._records_sent[n] = len(recs)
        if self.phase is Phase.ROUNDING:
            self._rounding_start = {n: self.rec[n].p0 for n in self.nodes}
        return out

    # ---- analysis ------------------------------------------------------------------------------------
    def _elapsed_true_ms(self, j: int) -> float:
        assert self._start is not None
        t_s = self._sync_t.get(self._start)
        t_j = self._sync_t.get(self._start + j)
        if t_s is None or t_j is None:
            return j * self.period_ms
        return (t_j - t_s) * 1000.0

    def _analyse_timing(self) -> None:
        for n, r in self.rec.items():
            survivors = []
            for sampling, count, first, clock in itertools.product(
                    *(OPEN_POINTS[k] for k in _TIMING_POINTS)):
                if all(obs in predict_timing(self.plan, sampling, count, first, clock, j,
                                             self._elapsed_true_ms(j), self.period_ms)
                       for j, obs in r.timing.items()):
                    survivors.append((sampling, count, first, clock))
            self._timing_survivors[n] = survivors
            if len(survivors) == 1:
                self._first_record[n] = survivors[0][2]

    def _timing_open(self) -> bool:
        """Did the last timing experiment leave a node unexplained or one of its readings open?"""
        return any(not sv or any(len({x[i] for x in sv}) > 1 for i in range(len(_TIMING_POINTS)))
                   for sv in self._timing_survivors.values())


    def result(self, absent: Mapping[int, tuple[int, ...]] | None = None) -> ProbeResult:
        """The readings per node (None for what was not measured or not determined)."""
        out: dict[int, NodeResult] = {}
        for n, r in self.rec.items():
            kw: dict[str, object] = {}
            evidence: list[str] = []
            unexplained: str | None = None
            if r.latencies_ms:
                kw["tpdo_latency_ms"] = round(max(r.latencies_ms), 3)
                evidence.append(f"TPDO1 answers {min(r.latencies_ms):.2f}..{max(r.latencies_ms):.2f} ms after "
                                f"its SYNC ({len(r.latencies_ms)} SYNCs 4 periods apart)")
            if Phase.TIMING in self.experiments:
                survivors = self._timing_survivors.get(n, [])
                seen = ", ".join(f"s{j:+d}:{'active' if a else 'inactive'}/{f}"
                                 for j, (a, f) in sorted(r.timing.items()))
                if not survivors:
                    unexplained = ("no reading of the manuals explains its FIFO and ip mode reports in the "
                                   f"timing experiment (SYNC: ip mode/fill: {seen})")
                else:
                    left_open: list[str] = []
                    for i, key in enumerate(_TIMING_POINTS):
                        values = {sv[i] for sv in survivors}
                        if len(values) == 1:
                            kw[key] = values.pop()
                        elif key in MUST_KNOW:  # the master cannot plan for either: no guess, a clear refusal
                            left_open.append(f"{key} ({' or '.join(sorted(values))})")
                    if left_open:
                        unexplained = (f"the timing experiment left its {', '.join(left_open)} open after "
                                       f"{self.timing_runs} runs: its SYNCs must come at the stretched intervals, "
                                       f"and a busy host that holds them back undoes that (SYNC: ip mode/fill: "
                                       f"{seen}); probe again, or state the reading in [axis.probed]")
                    runs = f" (run {self.timing_runs} times: a run left a reading open)" if self.timing_runs > 1 else ""
                    evidence.append(f"timing: records {self.plan.t1}/{self.plan.t2}/{self.plan.t3} ms of zero "
                                    f"motion, SYNC intervals {self.plan.stretched} x +{self.plan.stretch_ms:g} ms "
                                    f"after s+1; seen {seen}{runs}")
            if Phase.UNDERFLOW in self.experiments:
                first = self._first_record.get(n)
                if r.underflow_j is None:
                    unexplained = unexplained or "no underflow reported with two records and no end record"
                elif first is not None:
                    last_end = (6 if first == "segment_end" else 3) * self.period_ms
                    early = r.underflow_j * self.period_ms < last_end
                    kw["underflow_check"] = "every_tick" if early else "segment_end"
                    evidence.append(f"underflow: reported at s{r.underflow_j:+d} (the last segment ends "
                                    f"{last_end} ms after s)")
            if Phase.ROUNDING in self.experiments:
                verdict, seen = self._rounding_verdict(n, r)
                if verdict is not None:
                    kw["rounding"] = verdict
                else:
                    unexplained = unexplained or seen.replace("rounding: ", "no rounding explains the ", 1)
                evidence.append(seen)
            if absent is not None and n in absent:
                kw["absent"] = tuple(absent[n])
            emcys = [(p, hex(c)) for p, c in r.emcys if p != Phase.UNDERFLOW.value]  # that one asks for its EMCY
            if emcys:  # the cause comes first: what the drive showed after it is its fault reaction
                unexplained = f"EMCY during the probe: {emcys}" + (f"; {unexplained}" if unexplained else "")
            out[n] = NodeResult(n, DriveReadings(**kw), tuple(evidence), unexplained)  # type: ignore[arg-type]
        return ProbeResult(out)


# ---- the object survey (reading 5) ---------------------------------------------------------------------
@dataclass(frozen=True)
class ObjectReport:
    name: str
    index: int
    sub: int
    present: bool
    value: int | None
    note: str


def survey_objects(profile: DriveProfile, read: Callable[[int, int], int]) -> list[ObjectReport]:
    """Every object the product uses: present (readable) or absent, with its value. `read(index, sub)`
    raises `AbsentObject` for 0x06020000 / 0x06090011 aborts and returns the value otherwise."""
    out: list[ObjectReport] = []
    for name, ref in profile.objects.items():
        if name == "record" or name == "buffer_clear":
            continue  # write-only
        try:
            value: int | None = read(ref.index, ref.sub)
            present, note = True, ""
        except AbsentObject:
            value, present = None, False
            note = OPTIONAL_OBJECTS.get(ref.index, "ESSENTIAL: the product cannot run this drive without it")
        except WriteOnly:
            value, present, note = None, True, "write-only"
        out.append(ObjectReport(name, ref.index, ref.sub, present, value, note))
    return out


def absent_optional(reports: Iterable[ObjectReport]) -> tuple[int, ...]:
    return tuple(sorted({r.index for r in reports if not r.present and r.index in OPTIONAL_OBJECTS}))


class AbsentObject(Exception):
    """The drive answered an SDO read with 'object does not exist' (0x06020000 / 0x06090011)."""


class WriteOnly(Exception):
    """The drive answered 'attempt to read a write only object' (0x06010001)."""
