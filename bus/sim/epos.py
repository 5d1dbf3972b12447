"""The EPOS family: maxon's interpolated position mode with its 64-entry PVT FIFO (seed 000 chapter 4,
seed 001), on the shared CiA 402 drive (bus/sim/device.py).

Adds the FIFO of PVT records 0x20C1, the buffer status 0x20C4:01 (watermark warnings, latched errors),
0x60C4, activation on controlword bit 4 (>= 2 records), one Hermite segment per record
(planner.encoding.hermite, the encoder's formula), the end record, underflow and overflow, the ip
velocity and acceleration limits, halt; the open-point readings (`fifo_count`, `first_record`,
`underflow_check`) change how records are counted. And maxon's data recorder's objects (0x2010-0x201B;
the state machine is bus/sim/data_recorder.py) with the triggers this family raises. docs/drive-model.md
has the behaviours and their seed references.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from typing import Any

from bus import codec
from bus.codec import (
    BS_ACCELERATION_ERROR,
    BS_ACCELERATION_WARNING,
    BS_BUFFER_ENABLED,
    BS_IP_ACTIVE,
    BS_OVERFLOW_ERROR,
    BS_OVERFLOW_WARNING,
    BS_UNDERFLOW_ERROR,
    BS_UNDERFLOW_WARNING,
    BS_VELOCITY_ERROR,
    BS_VELOCITY_WARNING,
    CW_ENABLE_IP,
    CW_HALT,
    Frame,
)
from bus.sim import od as odm
from bus.sim.data_recorder import (
    CONTROL_FORCE_TRIGGER,
    CONTROL_START,
    TRIGGER_END,
    TRIGGER_INPUT,
    TRIGGER_MOVEMENT,
    DataRecorder,
    RecorderConfig,
)
from bus.sim.device import DriveDevice, Source, first_violation
from bus.sim.homing import HOMING_MODE
from bus.sim.od import Key, SdoAbort
from planner.config import HOMING_METHODS
from planner.encoding import hermite, record
from planner.encoding.record import PvtRecord

IP_MODE = 7


class EposDrive(DriveDevice):
    """A simulated maxon-EPOS-like drive in interpolated position mode (see the module docstring)."""

    family = "epos-ipm"
    supported_modes = frozenset({0, HOMING_MODE, IP_MODE})
    homing_methods = HOMING_METHODS["epos-ipm"]
    interpolation_mode = IP_MODE
    not_stored = frozenset({(0x20C1, 0), (0x60C4, 6), (0x60C4, 4), (0x2010, 0)})
    recorder: DataRecorder  # a new one at every reset (`_reset_family`)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._fifo: deque[PvtRecord] = deque()
        self._buffer_enabled = False
        self._latched = 0
        self._prev_warn = 0
        self._seg_target: PvtRecord | None = None
        self._digital_inputs = 0
        super().__init__(*args, **kwargs)

    @property
    def ready_for_job(self) -> bool:
        return super().ready_for_job and self._buffer_enabled

    # ---- hooks of the shared drive
    def _object_table(self) -> odm.ObjectTable:
        return odm.EPOS_TABLE

    def _family_dynamic(self) -> dict[Key, Callable[[], int]]:
        depth = self.profile.fifo_depth
        return {
            (0x20C4, 1): self._get_buffer_status,
            (0x60C4, 2): lambda: depth - len(self._fifo),
            (0x60C4, 4): lambda: len(self._fifo),
            (0x2017, 0): lambda: self.recorder.status,
            (0x2018, 0): self._recorder_max_samples,
            (0x2019, 0): lambda: self.recorder.offset,
        }

    def _family_handlers(self) -> dict[Key, Callable[[int], None]]:
        return {
            (0x20C1, 0): lambda v: self._append_record(record.unpack(v.to_bytes(8, "little"))),
            (0x60C4, 6): self._write_buffer_clear,
            (0x60C4, 4): lambda v: None,  # "writing to this object has no effect" (seed 000 4.3.6.5)
            (0x2010, 0): self._write_recorder_control,
        }

    def _reset_family(self) -> None:
        self.recorder = DataRecorder()
        self._fifo.clear()
        self._buffer_enabled = False
        self._latched = 0
        self._prev_warn = 0

    def _refresh_family(self, od: dict[Key, int]) -> None:
        self._uw = od[(0x20C4, 2)]
        self._ow = od[(0x20C4, 3)]

    def _check_write(self, key: Key, via_sdo: bool) -> None:
        if key == (0x20C1, 0) and via_sdo and not self._buffer_enabled:
            raise SdoAbort(odm.ABORT_DEVICE_STATE, "interpolation buffer access is disabled (0x60C4:06)")

    def _mode_changed(self, old: int, new: int) -> None:
        if new == IP_MODE:
            self._fifo.clear()  # seed 000 table 4-26 transition I: ip mode selected -> clear data buffer

    def _is_record_pdo(self, keys: tuple[Key, ...]) -> bool:
        return keys == ((0x20C1, 0),)

    def _on_record(self, data: bytes) -> None:
        self._append_record(record.unpack(data))

    def _after_sync_rpdos(self, t: float) -> None:
        warn = self._get_buffer_status() & (BS_UNDERFLOW_WARNING | BS_OVERFLOW_WARNING)
        rising = warn & ~self._prev_warn
        if rising & BS_UNDERFLOW_WARNING:
            self.counters.underflow_warnings += 1
        if rising & BS_OVERFLOW_WARNING:
            self.counters.overflow_warnings += 1
        self._prev_warn = warn

    def _segment_done(self, t: float) -> None:
        target = self._seg_target
        if not self._count_started and self._fifo and self._fifo[0] is target:
            self._fifo.popleft()  # until_segment_end: the target left the FIFO when its segment ended
        assert target is not None
        self._next_segment(target, t)

    def _mode_control(self, cw: int, prev: int) -> None:
        rising = cw & ~prev
        falling = prev & ~cw
        if cw & CW_HALT:
            if self._ip_active or (self._src is not None and self._src_kind == Source.SEGMENT):
                self._start_ramp(Source.HALT, (0x6084, 0))
            return
        if rising & CW_ENABLE_IP:
            self._activate()
        elif falling & CW_ENABLE_IP and self._ip_active:
            self._stop_interpolation()

    def _latch(self, bit: int) -> None:
        self._latched |= bit

    def _clear_latched(self) -> None:
        self._latched = 0

    def _emcy_status(self) -> int:
        return self._get_buffer_status()

    # ---- the FIFO and its segments
    @property
    def buffer_enabled(self) -> bool:
        return self._buffer_enabled

    @property
    def fifo_fill(self) -> int:
        return len(self._fifo)

    @property
    def free_size(self) -> int:
        return self.profile.fifo_depth - len(self._fifo)

    @property
    def fifo_records(self) -> tuple[PvtRecord, ...]:
        return tuple(self._fifo)

    @property
    def buffer_status(self) -> int:
        return self._get_buffer_status()

    def _get_buffer_status(self) -> int:
        bs = self._latched
        if self._buffer_enabled:
            bs |= BS_BUFFER_ENABLED
            fill = len(self._fifo)
            if fill < self._uw:
                bs |= BS_UNDERFLOW_WARNING
            if fill > self._ow:
                bs |= BS_OVERFLOW_WARNING
        if self._ip_active:
            bs |= BS_IP_ACTIVE
        return bs

    def _write_buffer_clear(self, value: int) -> None:
        if value == 0:
            self._fifo.clear()
            self._buffer_enabled = False
            self._latched &= ~codec.BS_ERRORS
        else:
            self._buffer_enabled = True

    def _limit_event(self, bit: int, t: float) -> None:
        if bit == BS_VELOCITY_WARNING:
            self.counters.velocity_warnings += 1
            self._latched |= bit
        elif bit == BS_ACCELERATION_WARNING:
            self.counters.acceleration_warnings += 1
            self._latched |= bit
        elif bit == BS_VELOCITY_ERROR:
            self._fault(codec.EMCY_IP_VELOCITY, bit, t)
        elif bit == BS_ACCELERATION_ERROR:
            self._fault(codec.EMCY_IP_ACCELERATION, bit, t)

    def _next_segment(self, prev: PvtRecord, t: float) -> None:
        if not self._fifo:
            self._fault(codec.EMCY_IP_BUFFER, BS_UNDERFLOW_ERROR, t)
            return
        head = self._fifo[0]
        if head.time_ms == 0:
            self._fifo.popleft()
            self._ip_active = False  # seed 000 4.3.6.1: time 0 -> interpolation inactive, no error
            self.recorder.trigger(TRIGGER_END, "end of profile", self._t_now)
            return
        self._begin_segment(prev.position, prev.velocity * self._rpm_to_cpms, head)

    def _begin_segment(self, p_prev: int, v_prev: float, target: PvtRecord) -> None:
        n_ms = target.time_ms
        v_end = target.velocity * self._rpm_to_cpms
        coeffs = hermite.coefficients(p_prev, v_prev, target.position, v_end, n_ms)
        self._seg_target = target
        self._start_segment(coeffs, n_ms)
        if self._count_started and self._fifo and self._fifo[0] is target:
            self._fifo.popleft()  # until_segment_start: the target leaves the FIFO as its segment starts
        if self._tick_underflow and len(self._fifo) < 2:
            # every_tick: "at least two data records have to be in the FIFO" while ip mode is active; the
            # count only drops when a segment starts, so checking here is checking at every tick
            self._fault(codec.EMCY_IP_BUFFER, BS_UNDERFLOW_ERROR, self._t_now)

    def _segment_limit_events(self, coeffs: tuple[float, float, float, float], n_ms: int) -> list[tuple[int, int]]:
        """Ticks (1..n_ms) at which the segment first exceeds 0x6081/0x607F (velocity) and
        0x6083/0x60C5 (acceleration), as (tick, buffer status bit), sorted."""
        a, b, c, _ = coeffs
        # fast path: bounds on |V| and |A| over the whole segment below every limit -> no event
        tau1 = 1.0 - n_ms
        v_bound = max(abs((3.0 * a * tau1 + 2.0 * b) * tau1 + c), abs(c))
        if a != 0.0:
            tau_star = -b / (3.0 * a)
            if tau1 < tau_star < 0.0:
                v_bound = max(v_bound, abs((3.0 * a * tau_star + 2.0 * b) * tau_star + c))
        a_bound = max(abs(6.0 * a * tau1 + 2.0 * b), abs(2.0 * b))
        if v_bound <= self._v_limit_min and a_bound <= self._a_limit_min:
            return []

        def vel(k: int) -> float:
            tau = k - n_ms
            return (3.0 * a * tau + 2.0 * b) * tau + c

        def acc(k: int) -> float:
            return 6.0 * a * (k - n_ms) + 2.0 * b

        cands = {1, n_ms}
        if a != 0.0:
            k_star = n_ms - b / (3.0 * a)
            for k in (math.floor(k_star), math.ceil(k_star)):
                if 1 <= k <= n_ms:
                    cands.add(k)
        events: list[tuple[int, int]] = []
        for fn, limit_key, bit, cand in (
            (vel, (0x6081, 0), BS_VELOCITY_WARNING, cands),
            (vel, (0x607F, 0), BS_VELOCITY_ERROR, cands),
            (acc, (0x6083, 0), BS_ACCELERATION_WARNING, {1, n_ms}),
            (acc, (0x60C5, 0), BS_ACCELERATION_ERROR, {1, n_ms}),
        ):
            limit = self._rpm_limit(limit_key) if fn is vel else self._acc_limit(limit_key)
            k = first_violation(fn, n_ms, limit, cand)
            if k:
                events.append((k, bit))
        events.sort()
        return events

    def _append_record(self, rec: PvtRecord) -> None:
        self.counters.records_received += 1
        if not self._buffer_enabled:
            self.counters.records_rejected += 1
            return
        if len(self._fifo) >= self.profile.fifo_depth:
            self.counters.records_rejected += 1
            self._fault(codec.EMCY_IP_BUFFER, BS_OVERFLOW_ERROR, self._t_now)
            return
        self._fifo.append(rec)

    def _activate(self) -> None:
        """Controlword bit 4 rising edge in operation enabled, mode 7 (seed 000 table 4-26 III)."""
        if len(self._fifo) < 2:
            self._fault(codec.EMCY_IP_BUFFER, BS_UNDERFLOW_ERROR, self._t_now)
            return
        self.counters.activations += 1
        self._latched &= ~(BS_VELOCITY_WARNING | BS_ACCELERATION_WARNING)
        self._ip_active = True
        self.recorder.trigger(TRIGGER_MOVEMENT, "movement start", self._t_now)
        if self._clock is not None:
            self._clock.anchor(self._t_now)  # the own clock's tick grid starts at the enabling SYNC
        if self._first_is_origin:
            # time_zero: the first record is the path's point at time zero; the demand starts there
            origin = self._fifo.popleft()
            self._demand = origin.position
            self._next_segment(origin, self._t_now)
            return
        head = self._fifo[0]
        if head.time_ms == 0:
            self._fifo.popleft()
            self._ip_active = False
            return
        self._begin_segment(self._demand, 0.0, head)

    # ---- the data recorder's objects and triggers (seed 004; the ticks that sample: bus/sim/recorder_ticks.py)
    def set_digital_inputs(self, word: int, t: float) -> list[Frame]:
        """The drive's digital inputs change (the simulation has no I/O: tests and tools set the word);
        an edge of any input is the recorder's digital-input trigger (0x2011 bit 2)."""
        self._start_entry(t)
        if word != self._digital_inputs:
            self._digital_inputs = word
            self.recorder.trigger(TRIGGER_INPUT, "digital input", t)
        return self._out

    @property
    def digital_inputs(self) -> int:
        return self._digital_inputs

    def read_domain(self, index: int, sub: int) -> bytes:
        """SDO upload of a domain object (0x201B, the data recorder's memory): its bytes."""
        s = self._spec(index, sub)
        if s.dtype != odm.DataType.DOMAIN:
            raise SdoAbort(odm.ABORT_UNSUPPORTED_ACCESS, f"0x{index:04X}:{sub:02X} is not a domain")
        return self.recorder.buffer()

    def _recorder_describe(self, index: int, sub: int) -> tuple[int, bool] | None:
        """(bits, signed) of a readable integer object the recorder can sample, else None."""
        if index in self._absent:
            return None
        s = self.objects.objects.get((index, sub))
        if s is None or not s.readable or s.dtype in (odm.DataType.VISIBLE_STRING, odm.DataType.DOMAIN):
            return None
        return s.dtype.bits, s.dtype.signed

    def _recorder_config(self) -> RecorderConfig:
        od = self._od
        return RecorderConfig.build(
            od[(0x2014, 0)], [od[(0x2015, k)] for k in range(1, 5)], [od[(0x2016, k)] for k in range(1, 5)],
            od[(0x2012, 0)], od[(0x2013, 0)], od[(0x2011, 0)], self._recorder_describe)

    def _recorder_max_samples(self) -> int:
        """0x2018, from the configuration as it stands (0 while it names no valid variable)."""
        try:
            return self._recorder_config().max_samples
        except SdoAbort:
            return 0

    def _write_recorder_control(self, value: int) -> None:
        """0x2010: bit 0 = 1 starts the recorder (if stopped), 0 stops it; bit 1 forces a trigger (so 3
        forces one while running). Reads back bit 0 as written."""
        rec = self.recorder
        if value & CONTROL_START:
            if not rec.active:
                config = self._recorder_config()  # SdoAbort names what is wrong; nothing changes then
                self._prepare_recording(config)
                rec.start(config, self._recorder_read)
        else:
            rec.stop()
        self._od[(0x2010, 0)] = value & CONTROL_START
        if value & CONTROL_FORCE_TRIGGER:
            rec.force_trigger(self._t_now)
