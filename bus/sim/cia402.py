"""CiA 402 on the simulated drive: the power state machine, modes of operation, faults and EMCY.

The top shared layer (bus/sim/device.py). The controlword drives bus.codec.TRANSITIONS
(`_apply_controlword`); power stage on or off starts or stops the position loop, and quick stop and fault
reaction ramp down first (0x605A). In operation enabled the mode bits go to homing or the family's
interpolation (`_mode_control`). `_fault` latches the status, records a `FaultRecord`, sets 0x603F /
0x1001, sends an EMCY (CiA 301 7.2.7) and starts the fault reaction; fault reset (bit 7 rising) clears it
and sends EMCY 0x0000. The statusword is composed from the state and the mode's bits.
"""

from __future__ import annotations

from dataclasses import dataclass

from bus import codec
from bus.codec import CW_FAULT_RESET, Cia402State, Command, Frame, Internal, InvalidTransition, NmtState
from bus.sim import homing as hm
from bus.sim import od as odm
from bus.sim.data_recorder import TRIGGER_ERROR
from bus.sim.homing_mode import HomingMode
from bus.sim.od import SdoAbort
from bus.sim.plant import ST, Source

QUICK_STOP_OPTIONS = frozenset({0, 1, 2, 5, 6})

_EMCY_REGISTER = {
    codec.EMCY_FOLLOWING_ERROR: codec.ER_GENERIC | codec.ER_DEVICE_PROFILE,
    codec.EMCY_IP_BUFFER: codec.ER_GENERIC | codec.ER_DEVICE_PROFILE,
    codec.EMCY_SYNC_LOST: codec.ER_GENERIC | codec.ER_COMMUNICATION,
    codec.EMCY_HEARTBEAT: codec.ER_GENERIC | codec.ER_COMMUNICATION,
    codec.EMCY_PDO_LENGTH: codec.ER_GENERIC | codec.ER_COMMUNICATION,
    codec.EMCY_PDO_LENGTH_EXCEEDED: codec.ER_GENERIC | codec.ER_COMMUNICATION,
    codec.EMCY_IP_VELOCITY: codec.ER_GENERIC | codec.ER_MANUFACTURER,
    codec.EMCY_IP_ACCELERATION: codec.ER_GENERIC | codec.ER_MANUFACTURER,
}


@dataclass(frozen=True)
class FaultRecord:
    t: float
    code: int
    name: str
    buffer_status: int
    state: Cia402State


class Cia402Drive(HomingMode):
    """The CiA 402 device control of one simulated drive. See the module docstring."""

    # what a family sets
    supported_modes: frozenset[int]
    interpolation_mode: int
    quick_stop_options: frozenset[int]
    # the state, set in DriveDevice.__init__
    fault_log: list[FaultRecord]
    _error_code: int
    _error_register: int

    # ---- introspection ---------------------------------------------------------------------------
    @property
    def state(self) -> Cia402State:
        return self._state

    @property
    def controlword(self) -> int:
        return self._cw

    @property
    def mode(self) -> int:
        return self._mode

    @property
    def ip_active(self) -> bool:
        return self._ip_active

    @property
    def error_code(self) -> int:
        return self._error_code

    @property
    def statusword(self) -> int:
        return self._get_statusword()

    @property
    def ready_for_job(self) -> bool:
        """Operation enabled and whatever else the family needs before a job (EPOS: the buffer enabled)."""
        return self._state == ST.OPERATION_ENABLED

    def _get_statusword(self) -> int:
        sw = self._state.statusword_bits | codec.SW_REMOTE
        if self._powered:
            sw |= codec.SW_VOLTAGE_ENABLED
        if self._ip_active:
            sw |= codec.SW_IP_ACTIVE
        if self._target_reached():
            sw |= codec.SW_TARGET_REACHED
        return sw | self._homing_status()

    # ============================================================================================
    # modes of operation and the quick stop option

    def _write_mode(self, value: int) -> None:
        if value not in self.supported_modes:
            raise SdoAbort(odm.ABORT_INVALID_VALUE, f"mode of operation {value} is not supported (0x6502)")
        old = self._mode
        if old == hm.HOMING_MODE and value != old:
            self._homing_abort()
        self._store((0x6060, 0), value)
        if value != old:
            self._mode_changed(old, value)
        if old == self.interpolation_mode and value != old:
            self._stop_interpolation()  # the demand holds where it is (seed 000 table 4-26 II)

    def _write_quick_stop_option(self, value: int) -> None:
        if value not in self.quick_stop_options:
            raise SdoAbort(odm.ABORT_INVALID_VALUE, f"quick stop option code {value} not supported")
        self._store((0x605A, 0), value)

    # ============================================================================================
    # CiA 402 device control

    def _apply_controlword(self, cw: int) -> None:
        prev = self._cw
        self._cw = cw
        command = codec.decode_command(cw)
        if command == Command.FAULT_RESET:
            if not prev & CW_FAULT_RESET and self._state == ST.FAULT:
                self._fault_reset()
            return
        state = self._state
        try:
            new = codec.next_state(state, command)
        except InvalidTransition:
            self.counters.ignored_commands += 1
            new = state
        if state == ST.QUICK_STOP_ACTIVE and new == ST.OPERATION_ENABLED and self._qs_option < 5:
            self.counters.ignored_commands += 1
            new = state
        if new != state:
            self._enter(new)
        if self._mode == hm.HOMING_MODE:
            self._homing_control(cw, prev)
            return
        if self._state != ST.OPERATION_ENABLED or self._mode != self.interpolation_mode:
            return
        self._mode_control(cw, prev)

    def _transition(self, trigger: Internal) -> None:
        self._enter(codec.next_state(self._state, trigger))

    def _enter(self, new: Cia402State) -> None:
        old = self._state
        self._state = new
        if old == ST.OPERATION_ENABLED and new != old and self._hm_state == "running":
            self._hm_state = "interrupted"  # the state machine's stop (quick stop, fault, disable) takes over
        if new.power_enabled and not old.power_enabled:
            self._power_on_stage()
        elif not new.power_enabled and old.power_enabled:
            self._power_off()
        if old == ST.OPERATION_ENABLED and new == ST.QUICK_STOP_ACTIVE:
            if self._qs_option == 0:
                self._transition(Internal.QUICK_STOP_DONE)
            else:
                self._ramp(Source.QUICK_STOP, self._quick_stop_deceleration())
        elif old == ST.QUICK_STOP_ACTIVE and new == ST.OPERATION_ENABLED:
            self._src = None
            self._ip_active = False

    def _fault(self, code: int, bit: int, t: float) -> None:
        """An error: latch its status bit (a family's buffer status), send EMCY, start the fault reaction."""
        self._latch(bit)
        if self._state in (ST.FAULT_REACTION_ACTIVE, ST.FAULT):
            return
        self.counters.faults += 1
        self._error_code = code
        self._error_register |= _EMCY_REGISTER.get(code, codec.ER_GENERIC)
        before = self._state
        self._state = codec.next_state(self._state, Internal.FAULT_DETECTED)
        self._ip_active = False  # the EMCY reports the status of the aborted trajectory
        bs = self._emcy_status()
        self.fault_log.append(FaultRecord(t, code, codec.EMCY_NAMES.get(code, hex(code)), bs, before))
        if self.recorder is not None:
            self.recorder.trigger(TRIGGER_ERROR, f"error 0x{code:04X}", t)
        self._emit_emcy(code, bs)
        if self._powered:
            self._fault_reaction()
        else:
            self._transition(Internal.FAULT_REACTION_DONE)

    def _fault_reset(self) -> None:
        if self._hm_state == "error":
            self._hm_state = "idle"  # bit 13 "is reset ... on rising edge of bit 7 of the Control Word"
        self._enter(codec.next_state(self._state, Command.FAULT_RESET))
        self._clear_latched()
        self._error_code = 0
        self._error_register = 0
        self._emit_emcy(codec.EMCY_ERROR_RESET, self._emcy_status())

    def _emit_emcy(self, code: int, status: int) -> None:
        if self._nmt not in (NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL) or not self._emcy_enabled(code):
            return
        if self._emcy_cob & odm.PDO_DISABLED:
            return
        self.counters.emcy_sent += 1
        self._out.append(Frame(self._emcy_cob & 0x7FF, codec.encode_emcy(
            code, self._error_register, codec.emcy_manufacturer_bytes(status))))

    def _target_reached(self) -> bool:
        state = self._state
        if state == ST.OPERATION_ENABLED and self._mode == hm.HOMING_MODE:
            # seed 003's homing table: "If Bit 10 is set, this indicates that the velocity is 0"
            return self._src is None and abs(self._vel) < hm.STANDSTILL_COUNTS_PER_MS
        if state == ST.OPERATION_ENABLED:
            if self._cw & codec.CW_HALT:
                return self._src is None
            if self._ip_active or self._src is not None:
                return False
            return abs(self._demand - self._pos) <= self._pos_window
        if state == ST.QUICK_STOP_ACTIVE:
            return self._src is None
        return False

    # ============================================================================================
    # what a family adds to CiA 402 (the defaults: a drive with no interpolation of its own)

    def _emcy_enabled(self, code: int) -> bool:
        """Is the EMCY with `code` sent (0x0000 = error reset)? Default: all."""
        return True

    def _quick_stop_deceleration(self) -> float:
        """The quick stop ramp for the option code 0x605A, counts/ms^2 (CiA 402: 1/5 slow down ramp =
        0x6084, 2/6 quick stop ramp 0x6085)."""
        return self._acc_limit((0x6084, 0) if self._qs_option in (1, 5) else self._qs_dec_key)

    def _fault_reaction(self) -> None:
        """The power stage is on and a fault was detected: ramp down with the quick stop deceleration,
        then fault (a family may switch off at once: `_transition(Internal.FAULT_REACTION_DONE)`)."""
        self._start_ramp(Source.FAULT, self._qs_dec_key)

    def _mode_changed(self, old: int, new: int) -> None:
        """Modes of operation changed."""

    def _mode_control(self, cw: int, prev: int) -> None:
        """A controlword in operation enabled, in the interpolation mode: the mode-specific bits."""

    def _latch(self, bit: int) -> None:
        """An error's status bit (the EPOS buffer status' error bits)."""

    def _clear_latched(self) -> None:
        """Fault reset: the latched status bits are cleared."""

    def _emcy_status(self) -> int:
        """The 16 bits an EMCY carries in its manufacturer bytes 0-1 (EPOS: the buffer status)."""
        return 0
