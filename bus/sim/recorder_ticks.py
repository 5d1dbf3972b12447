"""The control ticks while the data recorder samples (seed 004): every sample instant is hit.

The layer on the plant (bus/sim/plant.py). A family with a data recorder (EPOS: bus/sim/recorder.py, its
objects in bus/sim/epos.py) sets `recorder`; while it runs, `_run_ticks` hands its ticks to
`_run_ticks_recorded`: the same loop in chunks that end at sample instants (`_recorder_chunk`), sampling
after each chunk. A sampling period that is not whole ticks sub-steps the plant at that period, the
position controller staying at 1 ms: the plant's integration step (`_integrate`, `_coast`) runs tick by
tick with `SubSteps` (`_prepare_recording` sets `_fine`) and samples inside the tick. Kept apart so the loop
without a recorder pays nothing for it (benchmarks/bench_sim.py). The error and halt-end triggers fire in
cia402.py and plant.py.
"""

from __future__ import annotations

import functools
import itertools
from collections.abc import Iterable

from bus import codec
from bus.sim.motor import plant_constants
from bus.sim.plant import PlantLoop, SubSteps
from bus.sim.recorder import TICK_UNITS, UNIT_S, RecorderConfig, substep_units


class RecordedTicks(PlantLoop):
    """`_run_ticks` while the data recorder runs. See the module docstring."""

    # the plant's sub-steps while the recorder samples finer than the 1 ms tick, or None (DriveDevice.__init__)
    _fine: SubSteps | None

    def _recorder_read(self, index: int, sub: int) -> int:
        """A sampled variable's value now (the recorder checked it is a readable integer object)."""
        getter = self._dynamic.get((index, sub))
        return getter() if getter is not None else self._od[(index, sub)]

    def _prepare_recording(self, config: RecorderConfig) -> None:
        """The recorder is about to start with `config`: the plant keeps its 1 ms step when the sampling
        period is whole ticks, else it runs at the sub-step that hits every sample instant."""
        units = substep_units(config.period_units)
        rec = self.recorder
        assert rec is not None
        if units == TICK_UNITS:
            self._fine = None
        else:
            constants = plant_constants(self.motor, self.counts_per_rev, units * UNIT_S)
            sample = functools.partial(rec.advance, units, self._recorder_read)
            self._fine = SubSteps(constants, TICK_UNITS // units, sample)

    def _run_ticks_recorded(self, n: int, t: float) -> None:
        """`_run_ticks` while the recorder runs: the same loop, in chunks that end at sample instants
        (`_recorder_chunk`), sampling after each chunk, or inside each tick while sub-stepping. Kept apart
        so the loop without a recorder pays nothing for it (benchmarks/bench_sim.py)."""
        rec = self.recorder
        assert rec is not None
        sub = self._fine
        while n > 0:
            k = self._recorder_chunk(n)
            src = self._src
            sampled = sub is not None  # sub-stepping samples inside the tick
            if src is None:
                if self._powered:
                    done = self._integrate_recorded(itertools.repeat(self._demand, k), sub)
                elif self._vel != 0.0:
                    done = self._coast(k, sub)
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
                done = self._integrate_recorded(src[i:i + m], sub)
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

    def _integrate_recorded(self, demands: Iterable[int], sub: SubSteps | None) -> int:
        """`_integrate` at whole ticks, through the instance's `_integrate` as without a recorder (tests and
        benchmarks wrap it with one argument), or tick by tick sub-stepped at the recorder's period (its
        following error checked after each tick)."""
        if sub is None:
            return self._integrate(demands)
        done = 0
        for demand in demands:
            done += PlantLoop._integrate(self, sub.tick(demand), sub)
            if self._fe_tripped:
                break
        return done
