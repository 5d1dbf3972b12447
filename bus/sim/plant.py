"""The plant of the simulated drive: the position loop and motor, tick by tick, and the demand it follows.

The layer on bus/sim/pdo.py. `_run_ticks(n, t)` runs n 1 ms control ticks: the PID position controller
drives the motor model (bus/sim/motor.py); with the power stage off the motor coasts and the demand
follows. The demand comes from a `Source` (an interpolation segment through planner.encoding.hermite, a
stop ramp, a homing search), else holds; per-source work (the demand list, the family's limit crossings:
`_segment_limit_events`) is done once, and the loop runs from event to event. `_integrate` is the hot
spot (on locals); sub-steps finer than 1 ms only while the data recorder samples finer (`SubSteps`). A
following error beyond 0x6065 faults (EMCY 0x8611).
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from enum import Enum

from bus import codec
from bus.codec import Cia402State, Internal
from bus.sim.data_recorder import TRIGGER_END, DataRecorder
from bus.sim.motor import LoopConstants, MotorParams
from bus.sim.od import Key
from bus.sim.pdo import PdoLayer
from planner.encoding import hermite

ST = Cia402State
MAX_RAMP_TICKS = 600_000  # a stop ramp longer than 10 min of drive time ends with an abrupt stop
COAST_STOP_COUNTS_PER_MS = 1e-4  # below this a coasting motor is taken as standing still


class Source(Enum):
    """Where the position demand comes from while a demand list is being played."""

    SEGMENT = "ip segment"
    HALT = "halt ramp"
    QUICK_STOP = "quick stop ramp"
    FAULT = "fault reaction ramp"
    HOMING = "homing"


@dataclass(frozen=True, slots=True)
class SubSteps:
    """The plant sub-stepped inside each 1 ms tick (the data recorder sampling finer than a tick): its
    constants over one sub-step (bus/sim/motor.py `plant_constants`), the sub-steps of a tick, and what runs
    after each sub-step, the drive's state written back (the recorder's sampling)."""

    constants: tuple[float, float, float, float]
    steps: int
    sample: Callable[[], None]

    def tick(self, demand: int) -> list[int | None]:
        """The items of one tick for `PlantLoop._integrate`: the demand, then None per further sub-step."""
        return [demand] + [None] * (self.steps - 1)


def first_violation(
    values: Callable[[int], float], ticks: int, limit: float, candidates: Iterable[int]
) -> int:
    """First tick k in 1..ticks with |values(k)| > limit, or 0. `candidates` contain the maximiser."""
    if max(abs(values(k)) for k in candidates) <= limit:
        return 0
    for k in range(1, ticks + 1):
        if abs(values(k)) > limit:
            return k
    return 0  # pragma: no cover - the candidates found one


class PlantLoop(PdoLayer):
    """Position loop, motor and demand sources. See the module docstring."""

    # what the layers above provide (bus/sim/recorder_ticks.py, homing_mode.py, cia402.py)
    _fine: SubSteps | None
    _recorder_chunk: Callable[[int], int]
    _recorder_idle: Callable[[int], None]
    _recorder_advance: Callable[[int], None]
    _homing_next: Callable[[], None]
    _transition: Callable[[Internal], None]
    _state: Cia402State
    recorder: DataRecorder | None
    # the state, set in DriveDevice.__init__
    motor: MotorParams
    disturbance_current_a: float
    _c: LoopConstants
    _round: Callable[[float], int]
    _toward_zero: bool
    _pos: float
    _vel: float
    _integ: float
    _dterm: float
    _eprev: float
    _current: float
    _demand: int
    _powered: bool
    _fe_tripped: bool
    _src: list[int] | None
    _src_i: int
    _src_kind: Source
    _next_event: int
    _seg_events: list[tuple[int, int]]
    _seg_coeffs: tuple[float, float, float, float]
    _ramp_v0: float
    _ramp_dec: float

    # ---- introspection ---------------------------------------------------------------------------
    @property
    def position_demand(self) -> int:
        return self._demand

    @property
    def position_actual(self) -> int:
        return self._get_position_actual()

    @property
    def position_actual_exact(self) -> float:
        return self._pos

    @property
    def velocity_actual_rpm(self) -> float:
        return self._vel / self._rpm_to_cpms

    @property
    def velocity_actual_rpm_int(self) -> int:
        return round(self._vel / self._rpm_to_cpms)

    @property
    def demand_velocity_rpm(self) -> float:
        return self._demand_velocity() / self._rpm_to_cpms

    @property
    def current_a(self) -> float:
        return self._current

    @property
    def following_error(self) -> int:
        return self._demand - self.position_actual

    @property
    def drive_time_ms(self) -> int:
        return self.counters.ticks

    def _get_position_actual(self) -> int:
        x = self._pos
        return math.floor(x + 0.5) if x >= 0 else -math.floor(-x + 0.5)

    # ============================================================================================
    # the control ticks

    def _run_ticks(self, n: int, t: float) -> None:
        """Run n ticks from source event to source event. While the data recorder samples (it is active at
        the call) the ticks run in chunks that end at its sample instants (`_recorder_chunk`), sampled
        after each chunk (`_recorder_advance`), or sub-stepped and sampled inside each tick (`_fine`)."""
        rec = self.recorder
        recording = rec is not None and rec.active
        sub = self._fine if recording else None
        integrate = self._integrate if sub is None else functools.partial(self._integrate_substepped, sub=sub)
        while n > 0:
            k = self._recorder_chunk(n) if recording else n
            src = self._src
            if src is None:
                if self._powered:
                    done = integrate(itertools.repeat(self._demand, k))
                elif self._vel != 0.0:
                    done = self._coast(k, sub)
                else:  # standing without power: nothing moves
                    self.counters.ticks += k
                    if not recording:
                        return
                    self._recorder_idle(k)
                    n -= k
                    continue
            else:
                i = self._src_i
                m = min(k, self._next_event - i)
                if m <= 0:
                    self._on_source_event(t)
                    continue
                done = integrate(src[i:i + m])
                self._src_i = i + done
            n -= done
            if recording and sub is None:
                self._recorder_advance(done)
            if self._fe_tripped:
                self._fe_tripped = False
                self._fault(codec.EMCY_FOLLOWING_ERROR, 0, t)
                continue
            if self._src is not None and self._src_i == self._next_event:
                self._on_source_event(t)

    def _integrate(self, demands: Iterable[int | None], sub: SubSteps | None = None) -> int:
        """The integration step: one step of the plant per item, the position controller on the items that
        are demands (a new tick), its current held over the None items (the sub-steps of that tick). A tick's
        following error beyond 0x6065 stops the loop after the tick and sets _fe_tripped. Without `sub` every
        item is a tick of one step; with `sub` the items are one tick in sub-steps (`SubSteps.tick`) and
        `sub.sample` runs after each, the state written back. Returns the ticks run."""
        c = self._c
        kp, ki, kdf, kdg, imax, cou = c.kp, c.ki, c.kd_f, c.kd_g, c.i_max, c.coulomb_a
        few = self._fe_window if self._state is not ST.FAULT_REACTION_ACTIVE else math.inf
        if sub is None:
            phi, gam, psi, eta = c.phi, c.gam, c.psi, c.eta
            sample, few_step = None, few  # a step is a tick: its following error is checked after it
        else:
            (phi, gam, psi, eta), sample, few_step = sub.constants, sub.sample, math.inf  # checked after the loop
        dist = self.disturbance_current_a
        pos, vel, integ, dterm, ep = self._pos, self._vel, self._integ, self._dterm, self._eprev
        i = self._current
        demand = self._demand
        e = ep
        done = 0
        for d in demands:
            if d is not None:
                demand = d
                e = d - pos
                integ += ki * e
                if integ > imax:
                    integ = imax
                elif integ < -imax:
                    integ = -imax
                dterm = kdf * dterm + kdg * (e - ep)
                ep = e
                i = kp * e + integ + dterm
                if i > imax:
                    i = imax
                elif i < -imax:
                    i = -imax
                done += 1
            ie = i - dist
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
            pos += psi * vel + eta * ie
            if cou and ((vel > 0.0 and nv < 0.0) or (vel < 0.0 and nv > 0.0)):
                nv = 0.0
            vel = nv
            if sample is not None:
                self._pos, self._vel, self._integ, self._dterm, self._eprev = pos, vel, integ, dterm, ep
                self._current, self._demand = i, demand
                sample()
            if e > few_step or e < -few_step:
                break
        if done and (e > few or e < -few):
            self._fe_tripped = True
        self._pos, self._vel, self._integ, self._dterm, self._eprev = pos, vel, integ, dterm, ep
        self._current = i
        self._demand = demand
        self.counters.ticks += done
        return done

    def _coast(self, n: int, sub: SubSteps | None = None) -> int:
        """Power stage off: the motor runs down on friction; the demand follows the actual position. Without
        `sub`, n ticks of one step, returning at the tick the motor stops; with `sub`, all n ticks in
        sub-steps, `sub.sample` after each. Returns the ticks run."""
        c = self._c
        cou = c.coulomb_a
        if sub is None:
            phi, gam, psi, eta = c.phi, c.gam, c.psi, c.eta
            sample, steps = None, n
        else:
            (phi, gam, psi, eta), sample, steps = sub.constants, sub.sample, n * sub.steps
        dist = self.disturbance_current_a
        pos, vel = self._pos, self._vel
        self._current = 0.0
        done = 0
        while done < steps:
            if vel != 0.0:
                ie = -dist - (cou if vel > 0.0 else -cou)
                nv = phi * vel + gam * ie
                pos += psi * vel + eta * ie
                if (vel > 0.0 and nv <= 0.0) or (vel < 0.0 and nv >= 0.0) or abs(nv) < COAST_STOP_COUNTS_PER_MS:
                    nv = 0.0
                vel = nv
            done += 1
            if sample is not None:
                self._pos, self._vel, self._demand = pos, vel, hermite.round_counts(pos)
                sample()
            elif vel == 0.0:
                break
        self._pos, self._vel = pos, vel
        self._demand = hermite.round_counts(pos)
        ticks = done if sub is None else n
        self.counters.ticks += ticks
        return ticks

    def _integrate_substepped(self, demands: Iterable[int], sub: SubSteps) -> int:
        """`_integrate` in sub-steps, tick by tick (each tick's following error checked after it)."""
        done = 0
        for demand in demands:
            done += PlantLoop._integrate(self, sub.tick(demand), sub)
            if self._fe_tripped:
                break
        return done

    def _clock_deadline(self) -> float | None:
        """With an own clock, the time of the next tick at which the active source has an event
        (segment end, limit event), so underflows and pops happen at their tick, not at the next frame."""
        clock = self._clock
        if clock is None or self._src is None:
            return None
        return clock.time_of_tick(max(1, self._next_event - self._src_i))

    def _power_on_stage(self) -> None:
        self._powered = True
        self._demand = hermite.round_counts(self._pos)
        self._integ = 0.0
        self._dterm = 0.0
        self._eprev = 0.0
        self._src = None
        self._ip_active = False

    def _power_off(self) -> None:
        self._powered = False
        self._src = None
        self._ip_active = False
        self._current = 0.0
        self._demand = hermite.round_counts(self._pos)

    # ============================================================================================
    # demand sources: ip segments and stop ramps

    def _set_source(self, demands: list[int], kind: Source) -> None:
        self._src = demands
        self._src_i = 0
        self._src_kind = kind
        self._seg_events = []
        self._next_event = len(demands)

    def _on_source_event(self, t: float) -> None:
        """The tick `_next_event` was just run: fire its limit events and/or complete the source."""
        src = self._src
        assert src is not None
        k = self._src_i
        while self._seg_events and self._seg_events[0][0] == k:
            _, bit = self._seg_events.pop(0)
            self._limit_event(bit, t)
            if self._src is not src:
                return  # an error aborted the trajectory
        if k >= len(src):
            self._source_done(t)
        else:
            self._next_event = self._seg_events[0][0] if self._seg_events else len(src)

    def _source_done(self, t: float) -> None:
        kind = self._src_kind
        self._src = None
        if kind == Source.HOMING:
            self._homing_next()
        elif kind == Source.SEGMENT:
            self.counters.segments_completed += 1
            self._segment_done(t)
        elif kind == Source.QUICK_STOP:
            if self._qs_option < 5:  # CiA 402: 1-3 then switch on disabled, 5-8 stay in quick stop
                self._transition(Internal.QUICK_STOP_DONE)
        elif kind == Source.FAULT:
            self._transition(Internal.FAULT_REACTION_DONE)
        elif kind == Source.HALT and self.recorder is not None:
            self.recorder.trigger(TRIGGER_END, "end of profile (halt)", self._t_now)

    def _start_segment(self, coeffs: tuple[float, float, float, float], n_ms: int) -> None:
        """Interpolate the demand along the seed's cubic (planner.encoding.hermite) over the next n_ms ticks,
        rounded as the drive rounds; the family's limit checks become events at their ticks."""
        self._set_source(hermite.demand_from_coefficients(coeffs, n_ms, self._toward_zero), Source.SEGMENT)
        self._seg_coeffs = coeffs
        self._seg_events = self._segment_limit_events(coeffs, n_ms)
        if self._seg_events:
            self._next_event = self._seg_events[0][0]

    def _segment_limit_events(self, coeffs: tuple[float, float, float, float], n_ms: int) -> list[tuple[int, int]]:
        """(tick, status bit) at which the segment first crosses a limit the family checks."""
        return []

    def _limit_event(self, bit: int, t: float) -> None:
        """A limit crossing of `_segment_limit_events` came due."""

    def _segment_done(self, t: float) -> None:
        """An interpolation segment (`_start_segment`) ran to its end."""

    def _demand_velocity(self) -> float:
        """The interpolator's current velocity demand, counts/ms."""
        if self._src is None:
            return 0.0
        if self._src_kind == Source.SEGMENT:
            return hermite.evaluate(self._seg_coeffs, float(self._src_i - len(self._src)))[1]
        if self._src_kind == Source.HOMING:
            i, src = self._src_i, self._src
            return float(src[i - 1] - src[i - 2]) if i >= 2 else float(src[0] - self._demand) if i == 0 else 0.0
        v = abs(self._ramp_v0) - self._ramp_dec * self._src_i
        return math.copysign(max(0.0, v), self._ramp_v0)

    def _start_ramp(self, kind: Source, dec_key: Key) -> None:
        """Decelerate from the current demand velocity to standstill with `dec_key` (rpm/s)."""
        self._ramp(kind, self._acc_limit(dec_key))

    def _ramp(self, kind: Source, deceleration: float) -> None:
        """Decelerate from the current demand velocity to standstill at `deceleration` counts/ms^2."""
        v0 = self._demand_velocity()
        dec = max(deceleration, 1e-9)
        self._ip_active = False
        p0 = float(self._demand)
        demands: list[int] = []
        if v0 != 0.0:
            t_stop = abs(v0) / dec
            steps = min(MAX_RAMP_TICKS, math.ceil(t_stop))
            s = 1.0 if v0 > 0 else -1.0
            rnd = self._round
            for k in range(1, steps + 1):
                tk = min(float(k), t_stop)
                demands.append(rnd(p0 + v0 * tk - s * dec * tk * tk / 2.0))
        self._ramp_v0 = v0
        self._ramp_dec = dec
        self._set_source(demands, kind)
        if not demands:
            self._src = None
            self._on_ramp_done_immediately(kind)

    def _on_ramp_done_immediately(self, kind: Source) -> None:
        if kind == Source.QUICK_STOP and self._qs_option < 5:
            self._transition(Internal.QUICK_STOP_DONE)
        elif kind == Source.FAULT:
            self._transition(Internal.FAULT_REACTION_DONE)

    def _stop_interpolation(self) -> None:
        """ip mode disabled (bit 4 falling, mode change): the demand stays where it is."""
        self._ip_active = False
        if self._src is not None and self._src_kind == Source.SEGMENT:
            self._src = None
