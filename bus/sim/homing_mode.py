"""Homing mode (6) on the simulated drive: searches as demand sources, then the home position.

The layer on bus/sim/recorder_ticks.py; bus/sim/homing.py is the pure part. Controlword bit 4 rising in
operation enabled starts method 0x6098 (unknown: homing error, bit 13) with 0x6099 / 0x609A; each search
is a demand source ending at the tick its input changes; at the end the drive returns to the edge, which
becomes 0x607C (`_home_shift`). Statusword bits 12 / 13 / 10 per seed 003. `referenced` holds until a
reset or power-on. Bit 4 falling, halt or leaving operation enabled interrupt.
"""

from __future__ import annotations

from bus import codec
from bus.sim import homing as hm
from bus.sim.plant import ST, Source
from bus.sim.recorder_ticks import RecordedTicks


class HomingMode(RecordedTicks):
    """The drive's homing mode. See the module docstring."""

    # what a family sets
    homing_methods: frozenset[int]
    # what the layer above provides (bus/sim/cia402.py)
    _cw: int
    _mode: int
    # the state, set in DriveDevice.__init__
    inputs: hm.Inputs
    referenced: bool
    homing_error_reason: str
    _homing_travel: float
    _home_shift: int
    _hm_state: str
    _hm_phases: list[hm.Phase]
    _hm_phase: hm.Phase | None
    _hm_stage: str
    _hm_outcome: str
    _hm_v: float
    _hm_speeds: tuple[float, float, float]
    _hm_edge: int

    @property
    def homing_state(self) -> str:
        """idle, running, attained, error or interrupted."""
        return self._hm_state

    @property
    def machine_position(self) -> float:
        """The actual position in the machine's frame (where the switches are), counts."""
        return self._pos - self._home_shift

    @property
    def inputs_word(self) -> int:
        """The home and limit switch inputs now (seed 000 table 3-11 bits), read at the position demand."""
        return self.inputs.word(self._demand - self._home_shift)

    def _homing_status(self) -> int:
        if self._mode != hm.HOMING_MODE:
            return 0
        if self._hm_state == "error":
            return hm.SW_HOMING_ERROR
        # "Bit 12 is reset at 0 ... when bit 4 of the Control Word is at 0"
        return hm.SW_HOMING_ATTAINED if self._hm_state == "attained" and self._cw & codec.CW_ENABLE_IP else 0

    def _homing_control(self, cw: int, prev: int) -> None:
        """A controlword in homing mode: bit 4 rising starts, falling (or halt, bit 8) interrupts."""
        rising = cw & ~prev
        running = self._hm_state == "running"
        if running and (not cw & codec.CW_ENABLE_IP or cw & codec.CW_HALT):
            self._hm_state = "interrupted"  # "can be interrupted when clear"; seed 000: 0x011F halt homing
            self._homing_stop_motion("stopping")
            return
        if not rising & codec.CW_ENABLE_IP or cw & codec.CW_HALT:
            return
        method = self._od.get((0x6098, 0), 0)
        if self._state != ST.OPERATION_ENABLED and method not in hm.CURRENT_POSITION_METHODS:
            # "homing launched whereas the drive is not in 'operation enabled' (except for homing method 35)"
            self._homing_fail(f"homing started in {self._state.value}")
            return
        self._homing_start(method)

    def _homing_start(self, method: int) -> None:
        self.homing_error_reason = ""
        self._hm_state = "running"
        plan = hm.phases(method, self.inputs, self._demand - self._home_shift) \
            if method in self.homing_methods else None
        if plan is None:
            self._homing_fail(f"method {method} is not implemented")  # "an unimplemented selected method"
            return
        od = self._od
        self._hm_speeds = (self._velocity_cpms(od[(0x6099, 1)]), self._velocity_cpms(od[(0x6099, 2)]),
                           self._acc_limit((0x609A, 0)))
        self._hm_phases = list(plan)
        self._hm_v = 0.0
        if not plan:
            self._homing_reference(self._demand)  # 35/37: the current position is the home position
            return
        self._homing_phase()

    def _homing_phase(self) -> None:
        ph = self._hm_phases.pop(0)
        self._hm_phase = ph
        search_v, zero_v, acc = self._hm_speeds
        v = ph.direction * (search_v if ph.speed == "search" else zero_v)
        shift, inputs = self._home_shift, self.inputs
        limit_signal = "positive" if ph.direction > 0 else "negative"

        def done(d: float) -> bool:
            return inputs.state(ph.signal, d - shift) == ph.until

        def limit(d: float) -> bool:
            return ph.signal != limit_signal and inputs.state(limit_signal, d - shift)

        s = hm.search(float(self._demand), self._hm_v, v, acc, done, limit, self._homing_travel, self._round)
        self._hm_stage, self._hm_outcome, self._hm_v = "search", s.outcome, s.velocity
        self._set_source(s.demands, Source.HOMING)

    def _homing_next(self) -> None:
        """A homing source ran to its end."""
        stage = self._hm_stage
        if stage == "failing":
            self._hm_v = 0.0
            self._hm_state = "error"
            return
        if stage == "stopping":
            self._hm_v = 0.0
            return
        if stage == "return":
            self._homing_reference(self._hm_edge)
            return
        ph = self._hm_phase
        assert ph is not None
        outcome = self._hm_outcome
        if outcome == "limit" and ph.on_limit is not None:
            self._hm_phases = list(ph.on_limit)
            self._homing_phase()
        elif outcome != "found":
            what = "a limit switch" if outcome == "limit" else f"no {ph.signal} switch edge within the travel"
            self._homing_fail(f"{what} (method {self._od.get((0x6098, 0), 0)})")
        elif self._hm_phases:
            self._homing_phase()
        else:
            # the home position: the edge just found; stop and come back to it at the zero speed
            self._hm_edge = self._demand
            _, zero_v, acc = self._hm_speeds
            ramp = hm.stop(float(self._demand), self._hm_v, acc, self._round)
            end = ramp[-1] if ramp else self._demand
            back = hm.move_to(float(end), self._hm_edge, zero_v, acc)
            self._hm_stage, self._hm_v = "return", 0.0
            if ramp or back:
                self._set_source(ramp + back, Source.HOMING)
            else:
                self._homing_reference(self._hm_edge)

    def _homing_reference(self, at: int) -> None:
        """The drive stands at the home position `at` (counts, reported frame): it becomes 0x607C."""
        offset = round(self._position_counts(self._od.get((0x607C, 0), 0)))
        delta = offset - at
        self._pos += delta
        self._demand += delta
        self._home_shift += delta
        self.referenced = True
        self._hm_state = "attained"

    def _homing_fail(self, reason: str) -> None:
        self.homing_error_reason = reason
        self._hm_state = "error"
        self._homing_stop_motion("failing")

    def _homing_stop_motion(self, stage: str) -> None:
        """Ramp down at 0x609A from the current homing motion (the state is already set)."""
        if self._src is None or self._src_kind != Source.HOMING:
            return
        v = self._demand_velocity()
        ramp = hm.stop(float(self._demand), v, self._hm_speeds[2] or self._acc_limit((0x609A, 0)), self._round)
        self._hm_stage = stage  # bit 13 with bit 10 clear while it ramps down: "error occurred, velocity is not 0"
        self._set_source(ramp, Source.HOMING)
        if not ramp:
            self._src = None
            self._homing_next()

    def _homing_abort(self) -> None:
        """Mode changed away from homing: the demand holds where it is."""
        if self._src is not None and self._src_kind == Source.HOMING:
            self._src = None
        if self._hm_state == "running":
            self._hm_state = "interrupted"

    def _velocity_cpms(self, value: int) -> float:
        """A velocity object's value (the family's unit: rpm here) as counts/ms."""
        return value * self._rpm_to_cpms

    def _position_counts(self, value: int) -> float:
        """A position object's value (the family's unit: counts here) as counts."""
        return float(value)
