"""The control ticks while the data recorder samples (seed 004): every sample instant is hit.

The layer on bus/sim/plant.py. While a family's `recorder` runs, the tick loop runs to the next sample
instant (`_recorder_chunk`) and samples after each chunk (`_recorder_advance`, or `_recorder_idle` without
power). A period that is not whole ticks sub-steps the plant (`SubSteps`), the position controller staying
at 1 ms. Without an active recorder this costs one test per chunk (benchmarks/bench_sim.py).
"""

from __future__ import annotations

import functools

from bus.sim.data_recorder import TICK_UNITS, UNIT_S, RecorderConfig, substep_units
from bus.sim.motor import plant_constants
from bus.sim.plant import PlantLoop, SubSteps


class RecordedTicks(PlantLoop):
    """The data recorder's side of the tick loop. See the module docstring."""

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

    def _recorder_advance(self, ticks: int) -> None:
        """Whole ticks ran up to (never past) the next sample instant: sample if it is due."""
        rec = self.recorder
        assert rec is not None
        rec.advance(ticks * TICK_UNITS, self._recorder_read)
