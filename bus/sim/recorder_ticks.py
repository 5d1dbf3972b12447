"""The control ticks while the data recorder samples (seed 004): every sample instant is hit.

The layer on the plant (bus/sim/plant.py). A family with a data recorder (EPOS: bus/sim/recorder.py, its
objects in bus/sim/epos.py) sets `recorder`; while it runs, `_run_ticks` hands its ticks to
`_run_ticks_recorded`: the same loop in chunks that end at sample instants (`_recorder_chunk`), sampling
after each chunk. A sampling period that is not whole ticks sub-steps the plant at that period, the
position controller staying at 1 ms (`_integrate_fine`, `_coast_fine`, which sample inside the tick).
Kept apart so the loop without a recorder pays nothing for it (benchmarks/bench_sim.py). The error and
halt-end triggers fire in cia402.py and plant.py.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable

from bus import codec
from bus.sim.motor import plant_constants
from bus.sim.plant import COAST_STOP_COUNTS_PER_MS, ST, PlantLoop
from bus.sim.recorder import TICK_UNITS, UNIT_S, RecorderConfig, substep_units
from planner import hermite


class RecordedTicks(PlantLoop):
    """`_run_ticks` while the data recorder runs. See the module docstring."""

    # the plant's sub-step while the recorder samples finer than the 1 ms tick (set in DriveDevice.__init__):
    # (plant constants, sub-steps per tick, units per sub-step), or None
    _fine: tuple[tuple[float, float, float, float], int, int] | None

    def _recorder_read(self, index: int, sub: int) -> int:
        """A sampled variable's value now (the recorder checked it is a readable integer object)."""
        getter = self._dynamic.get((index, sub))
        return getter() if getter is not None else self._od[(index, sub)]

    def _prepare_recording(self, config: RecorderConfig) -> None:
        """The recorder is about to start with `config`: the plant keeps its 1 ms step when the sampling
        period is whole ticks, else it runs at the sub-step that hits every sample instant."""
        units = substep_units(config.period_units)
        if units == TICK_UNITS:
            self._fine = None
        else:
            self._fine = plant_constants(self.motor, self.counts_per_rev, units * UNIT_S), TICK_UNITS // units, units

    def _run_ticks_recorded(self, n: int, t: float) -> None:
        """`_run_ticks` while the recorder runs: the same loop, in chunks that end at sample instants
        (`_recorder_chunk`), sampling after each chunk, or inside each tick while sub-stepping. Kept apart
        so the loop without a recorder pays nothing for it (benchmarks/bench_sim.py)."""
        rec = self.recorder
        assert rec is not None
        fine = self._fine is not None
        integrate = self._integrate_fine if fine else self._integrate
        while n > 0:
            k = self._recorder_chunk(n)
            src = self._src
            sampled = fine  # the fine integrators sample inside the tick
            if src is None:
                if self._powered:
                    done = integrate(itertools.repeat(self._demand, k))
                elif self._vel != 0.0:
                    done = self._coast_fine(k) if fine else self._coast(k)
                else:
                    self.counters.ticks += k
                    done = k
                    self._recorder_idle(k)
                    sampled = True
            else:
                i = self._src_i
                m = min(k, self._next_event - i)
                if m <= 0:
                    self._on_source_event(t)
                    continue
                done = integrate(src[i:i + m])
                self._src_i = i + done
            n -= done
            if not sampled:
                rec.advance(done * TICK_UNITS, self._recorder_read)
            if self._fe_tripped:
                self._fe_tripped = False
                self._fault(codec.EMCY_FOLLOWING_ERROR, 0, t)
                continue
            if self._src is not None and self._src_i == self._next_event:
                self._on_source_event(t)

    def _recorder_chunk(self, n: int) -> int:
        """Ticks to run before the next sample instant (at most n; 1 while sub-stepping)."""
        rec = self.recorder
        if rec is None or not rec.active:
            return n
        if self._fine is not None:
            return 1
        return max(1, min(n, rec.units_to_sample() // TICK_UNITS))

    def _recorder_idle(self, ticks: int) -> None:
        """Ticks in which nothing moves (power off, standing): the samples due see the same state."""
        rec = self.recorder
        assert rec is not None
        units = ticks * TICK_UNITS
        while units > 0 and rec.active:
            step = min(units, rec.units_to_sample())
            rec.advance(step, self._recorder_read)
            units -= step

    def _integrate_fine(self, demands: Iterable[int]) -> int:
        """`_integrate` with the plant sub-stepped at the recorder's period (the position controller
        still runs once per 1 ms tick, its current held over the sub-steps); samples at every instant."""
        assert self._fine is not None and self.recorder is not None
        (phi, gam, psi, eta), steps, units = self._fine
        c = self._c
        cou, imax = c.coulomb_a, c.i_max
        rec, read = self.recorder, self._recorder_read
        few = self._fe_window if self._state is not ST.FAULT_REACTION_ACTIVE else math.inf
        done = 0
        for d in demands:
            e = d - self._pos
            integ = min(imax, max(-imax, self._integ + c.ki * e))
            dterm = c.kd_f * self._dterm + c.kd_g * (e - self._eprev)
            i = min(imax, max(-imax, c.kp * e + integ + dterm))
            self._integ, self._dterm, self._eprev, self._current, self._demand = integ, dterm, e, i, d
            for _ in range(steps):
                vel = self._vel
                ie = i - self.disturbance_current_a
                if vel > 0.0:
                    ie -= cou
                elif vel < 0.0:
                    ie += cou
                elif ie > cou:
                    ie -= cou
                elif ie < -cou:
                    ie += cou
                else:
                    ie = 0.0
                nv = phi * vel + gam * ie
                self._pos += psi * vel + eta * ie
                if cou and ((vel > 0.0 and nv < 0.0) or (vel < 0.0 and nv > 0.0)):
                    nv = 0.0
                self._vel = nv
                rec.advance(units, read)
            done += 1
            if e > few or e < -few:
                self._fe_tripped = True
                break
        self.counters.ticks += done
        return done

    def _coast_fine(self, n: int) -> int:
        """`_coast` with the plant sub-stepped at the recorder's period; samples at every instant."""
        assert self._fine is not None and self.recorder is not None
        (phi, gam, psi, eta), steps, units = self._fine
        cou = self._c.coulomb_a
        rec, read = self.recorder, self._recorder_read
        self._current = 0.0
        for _ in range(n):
            for _ in range(steps):
                vel = self._vel
                if vel != 0.0:
                    ie = -self.disturbance_current_a - (cou if vel > 0.0 else -cou)
                    nv = phi * vel + gam * ie
                    self._pos += psi * vel + eta * ie
                    stopped = (vel > 0.0 and nv <= 0.0) or (vel < 0.0 and nv >= 0.0)
                    self._vel = 0.0 if stopped or abs(nv) < COAST_STOP_COUNTS_PER_MS else nv
                    self._demand = hermite.round_counts(self._pos)
                rec.advance(units, read)
        self.counters.ticks += n
        return n
