"""The simulated drive's own data recorder (seed 004; seed 000 chapter 8), as a pure state machine.

Owns the recorder's state, the configuration latched at start, its 512-word memory as one ring per
variable and its 0.1 ms clock (`UNIT_S`). Fed by the EPOS drive (0x2010 start/stop/force, `trigger(kind)`)
and the tick loop (`advance`, called at each sample instant); answers 0x2017-0x2019 and 0x201B laid out by
seed 004's StartRingBuffer formulas. Single trigger mode keeps `preceding` samples before the trigger and
stops itself; continuous mode records until stopped. docs/drive-model.md ("Data recorder") has the choices.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import Enum

from bus.sim.od import ABORT_INVALID_VALUE, SdoAbort

TOTAL_WORDS = 512  # seed 004: "Total buffer size: 512 words"
MAX_VARIABLES = 4
UNIT_S = 1e-4  # 0x2012 counts periods of the current regulator, 0.1 ms (seed 004)
TICK_UNITS = 10  # one 1 ms position-loop tick of the simulated drive in recorder units

# 0x2010 control (seed 004 table 1)
CONTROL_START = 1 << 0
CONTROL_FORCE_TRIGGER = 1 << 1
# 0x2011 configuration: the automatic triggers (seed 004 table 2)
TRIGGER_MOVEMENT = 1 << 0
TRIGGER_ERROR = 1 << 1
TRIGGER_INPUT = 1 << 2
TRIGGER_END = 1 << 3
TRIGGER_MASK = TRIGGER_MOVEMENT | TRIGGER_ERROR | TRIGGER_INPUT | TRIGGER_END
# 0x2017 status (seed 004 table 3)
STATUS_RUNNING = 1 << 0
STATUS_TRIGGERED = 1 << 1

Reader = Callable[[int, int], int]


def words_of(bits: int) -> int:
    """Words one sample of a variable of `bits` takes in the recorder's memory (seed 004: an 8-bit
    variable takes 16 bits; the table of 0x2018 counts a 32-bit one as 2 words)."""
    if bits not in (8, 16, 32):
        raise ValueError(f"the recorder takes 8, 16 and 32-bit variables, not {bits}-bit")
    return 2 if bits == 32 else 1


def max_samples(words_per_sample: int) -> int:
    """0x2018: 512 words / the sum of the variables' sizes in words (0 without variables)."""
    return TOTAL_WORDS // words_per_sample if words_per_sample > 0 else 0


def ring_starts(words: Sequence[int], samples: int) -> tuple[int, ...]:
    """StartRingBuffer of each variable (word offsets into the memory, seed 004 "Data Buffer Segmentation")."""
    out: list[int] = []
    acc = 0
    for w in words:
        out.append(samples * acc)
        acc += w
    return tuple(out)


def substep_units(period_units: int) -> int:
    """The plant step (0.1 ms units) a drive must run at to hit every sample instant of a recording at
    `period_units`: a whole 1 ms tick when the period is whole ticks, else the gcd of the period and a tick
    (0.1 ms for 0.3 ms, 0.5 ms for 1.5 ms)."""
    return TICK_UNITS if period_units % TICK_UNITS == 0 else math.gcd(period_units, TICK_UNITS)


class RecorderState(Enum):
    STOPPED = "stopped"
    WAITING = "waiting"  # single trigger mode, before the trigger
    CONTINUOUS = "continuous"
    TRIGGERED = "triggered"  # single trigger mode (or a forced trigger), filling up


class RecorderEvent(Enum):
    START_SINGLE = "start single trigger"
    START_CONTINUOUS = "start continuous"
    STOP = "stop"
    TRIGGER = "trigger"
    FULL = "full"


S, E = RecorderState, RecorderEvent
# an event without an entry raises (STYLE.md 3); a trigger or stop where it means nothing is listed as a no-op
TRANSITIONS: dict[tuple[RecorderState, RecorderEvent], RecorderState] = {
    (S.STOPPED, E.START_SINGLE): S.WAITING,
    (S.STOPPED, E.START_CONTINUOUS): S.CONTINUOUS,
    (S.STOPPED, E.STOP): S.STOPPED,
    (S.STOPPED, E.TRIGGER): S.STOPPED,
    (S.WAITING, E.STOP): S.STOPPED,
    (S.WAITING, E.TRIGGER): S.TRIGGERED,
    (S.CONTINUOUS, E.STOP): S.STOPPED,
    (S.CONTINUOUS, E.TRIGGER): S.TRIGGERED,
    (S.TRIGGERED, E.STOP): S.STOPPED,
    (S.TRIGGERED, E.TRIGGER): S.TRIGGERED,
    (S.TRIGGERED, E.FULL): S.STOPPED,
}


class InvalidRecorderTransition(RuntimeError):
    pass


def next_state(state: RecorderState, event: RecorderEvent) -> RecorderState:
    try:
        return TRANSITIONS[(state, event)]
    except KeyError:
        raise InvalidRecorderTransition(f"recorder event {event.value!r} in state {state.value!r}") from None


@dataclass(frozen=True)
class RecordedVariable:
    index: int
    sub: int
    bits: int  # 8, 16 or 32
    signed: bool

    @property
    def words(self) -> int:
        return words_of(self.bits)


@dataclass(frozen=True)
class RecorderConfig:
    """What the recorder latches when it starts (from 0x2011-0x2016), validated."""

    variables: tuple[RecordedVariable, ...]
    period_units: int  # 0x2012, sampling period in 0.1 ms
    preceding: int  # 0x2013, as written (clamped to max_samples - 1 when used)
    triggers: int  # 0x2011 bits; 0 = continuous acquisition

    def __post_init__(self) -> None:
        if not 1 <= len(self.variables) <= MAX_VARIABLES:
            raise SdoAbort(ABORT_INVALID_VALUE, f"0x2014: the recorder takes 1..{MAX_VARIABLES} variables, "
                           f"got {len(self.variables)}")
        if self.period_units < 1:
            raise SdoAbort(ABORT_INVALID_VALUE, f"0x2012: sampling period {self.period_units} x 0.1 ms; it "
                           "must be at least 1")
        if self.triggers & ~TRIGGER_MASK:
            raise SdoAbort(ABORT_INVALID_VALUE, f"0x2011: reserved trigger bits set in 0x{self.triggers:04X}")

    @classmethod
    def build(cls, count: int, indices: Sequence[int], subs: Sequence[int], period_units: int, preceding: int,
              triggers: int, describe: Callable[[int, int], tuple[int, bool] | None]) -> RecorderConfig:
        """From the registers; `describe(index, sub)` gives (bits, signed) of a readable integer object or
        None (no such object, write-only, not an integer). Raises SdoAbort naming what is wrong."""
        if not 1 <= count <= MAX_VARIABLES:
            raise SdoAbort(ABORT_INVALID_VALUE, f"0x2014: the recorder takes 1..{MAX_VARIABLES} variables, "
                           f"got {count}")
        variables: list[RecordedVariable] = []
        for k in range(count):
            index, sub = indices[k], subs[k]
            found = describe(index, sub)
            if found is None or found[0] not in (8, 16, 32):
                raise SdoAbort(ABORT_INVALID_VALUE, f"0x2015/0x2016 sub {k + 1}: 0x{index:04X}:{sub:02X} is not "
                               "a readable 8, 16 or 32-bit object of this drive")
            variables.append(RecordedVariable(index, sub, found[0], found[1]))
        return cls(tuple(variables), period_units, preceding, triggers)

    @property
    def words_per_sample(self) -> int:
        return sum(v.words for v in self.variables)

    @property
    def max_samples(self) -> int:
        return max_samples(self.words_per_sample)

    @property
    def continuous(self) -> bool:
        return self.triggers == 0


class DataRecorder:
    """One drive's data recorder (see the module docstring)."""

    def __init__(self) -> None:
        self._state = RecorderState.STOPPED
        self.active = False  # running (waiting, continuous or triggered): a plain attribute, read every tick batch
        self.config: RecorderConfig | None = None
        self._rings: list[list[int]] = []
        self._samples = 0  # rows per ring (0x2018 of the latched configuration)
        self._write = 0  # next row to write
        self._taken = 0  # samples taken since the start
        self._since = 0  # units since the last sample
        self._trigger_row: int | None = None  # row of the trigger's sample
        self._trigger_pending = False  # triggered between two samples: the next sample is the trigger's
        self._after = 0  # samples from the trigger's on
        self._preceding = 0
        self._ever_triggered = False
        self.samples_taken = 0  # introspection: samples of the current/last run
        self.trigger_kind: str | None = None  # introspection: what triggered the current/last run
        self.trigger_sample: int | None = None  # introspection: the trigger's sample number since the start
        self.trigger_t: float | None = None  # introspection: the simulation's time of the trigger event

    # ---- objects
    @property
    def status(self) -> int:
        """0x2017: bit 0 running, bit 1 triggered (kept after the recorder stopped full, until the next start)."""
        s = 0
        if self.state != RecorderState.STOPPED:
            s |= STATUS_RUNNING
        if self.state == RecorderState.TRIGGERED or (self.state == RecorderState.STOPPED and self._ever_triggered):
            s |= STATUS_TRIGGERED
        return s

    @property
    def state(self) -> RecorderState:
        return self._state

    def _go(self, event: RecorderEvent) -> None:
        self._state = next_state(self._state, event)
        self.active = self._state != RecorderState.STOPPED

    @property
    def offset(self) -> int:
        """0x2019: the ring row of the recorded vector's first sample."""
        n = self._samples
        if n == 0:
            return 0
        if self._trigger_row is not None:
            return (self._trigger_row - self._preceding) % n
        return self._write % n if self._taken >= n else 0

    def buffer(self) -> bytes:
        """0x201B: the rings as laid out in the recorder's memory (empty before the first start)."""
        cfg = self.config
        if cfg is None:
            return b""
        out = bytearray()
        for var, ring in zip(cfg.variables, self._rings, strict=True):
            if var.words == 2:
                for v in ring:
                    out += (v & 0xFFFFFFFF).to_bytes(4, "little")
            else:
                for v in ring:
                    out += (v & 0xFFFF).to_bytes(2, "little")
        return bytes(out)

    # ---- control
    def start(self, config: RecorderConfig, read: Reader) -> None:
        """0x2010 bit 0 set while stopped: latch the configuration, clear the memory, take the first sample."""
        if self.active:
            return  # already running: writing "start" again changes nothing
        samples = config.max_samples
        self._go(E.START_CONTINUOUS if config.continuous else E.START_SINGLE)
        self.config = config
        self._samples = samples
        self._rings = [[0] * samples for _ in config.variables]
        self._write = 0
        self._taken = 0
        self._since = 0
        self._trigger_row = None
        self._trigger_pending = False
        self._after = 0
        self._preceding = min(config.preceding, samples - 1)
        self._ever_triggered = False
        self.samples_taken = 0
        self.trigger_kind = None
        self.trigger_sample = None
        self.trigger_t = None
        self._sample(read)

    def stop(self) -> None:
        if self._trigger_pending:
            # stopped between a trigger and its sample: the rings hold no trigger sample, so the recording is
            # not a triggered one (status bit 1 clear, 0x2019 as for a continuous recording)
            self._ever_triggered = False
            self.trigger_kind = None
            self.trigger_t = None
        self._go(E.STOP)
        self._trigger_pending = False

    def force_trigger(self, t: float | None = None) -> None:
        self._trigger("force", t)

    def trigger(self, bit: int, kind: str, t: float | None = None) -> None:
        """An event the 0x2011 bit `bit` selects happened (ignored unless waiting with that bit set); `t` is
        only kept for introspection (the recorder's time is the drive time it was advanced by)."""
        cfg = self.config
        if self.state == RecorderState.WAITING and cfg is not None and cfg.triggers & bit:
            self._trigger(kind, t)

    def _trigger(self, kind: str, t: float | None) -> None:
        if self.state not in (RecorderState.WAITING, RecorderState.CONTINUOUS):
            return
        self._go(E.TRIGGER)
        self._ever_triggered = True
        self.trigger_kind = kind
        self.trigger_t = t
        if self._since == 0 and self._taken > 0:
            # the last sample was taken at this very instant: it is the trigger's
            self._trigger_row = (self._write - 1) % self._samples
            self.trigger_sample = self._taken - 1
            self._after = 1
            self._check_full()
        else:
            self._trigger_pending = True

    # ---- time
    def units_to_sample(self) -> int:
        """Drive time (0.1 ms units) until the next sample; the drive never advances past it."""
        cfg = self.config
        assert cfg is not None
        return cfg.period_units - self._since

    def advance(self, units: int, read: Reader) -> None:
        """`units` of drive time passed (never beyond the next sample instant); sample if it is due now."""
        if not self.active:
            return
        cfg = self.config
        assert cfg is not None
        self._since += units
        if self._since > cfg.period_units:
            raise ValueError(f"the drive advanced the recorder {self._since - cfg.period_units} units past a sample")
        if self._since == cfg.period_units:
            self._sample(read)

    def _sample(self, read: Reader) -> None:
        cfg = self.config
        assert cfg is not None
        row = self._write
        for var, ring in zip(cfg.variables, self._rings, strict=True):
            ring[row] = read(var.index, var.sub)
        self._write = (row + 1) % self._samples
        self._taken += 1
        self.samples_taken = self._taken
        self._since = 0
        if self._trigger_pending:
            self._trigger_pending = False
            self._trigger_row = row
            self.trigger_sample = self._taken - 1
            self._after = 1
            self._check_full()
        elif self.state == RecorderState.TRIGGERED:
            self._after += 1
            self._check_full()

    def _check_full(self) -> None:
        if self._after >= self._samples - self._preceding:
            self._go(E.FULL)
