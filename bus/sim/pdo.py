"""PDOs on the simulated drive (CiA 301 7.5.2.35-38): mapping, reception, transmission and its timing.

The layer on bus/sim/cia301.py. Mapping writes follow the drive's rules (COB-ID fixed while valid, edits
only while invalid with count 0, mappable objects, at most 64 bits, short entries where the family
allows); `_rebuild_pdos` compiles the mapping once so the per-SYNC path only packs. RPDOs are
length-checked (EMCY 0x8210/0x8220); synchronous ones wait for the SYNC, record RPDOs go to the FIFO.
Synchronous TPDOs are sampled at the SYNC and sent at once or after the latency option (never overtaking);
event TPDOs (254/255) respect the inhibit time and the event timer.
"""

from __future__ import annotations

import random
import struct
from collections.abc import Callable

from bus import codec
from bus.codec import Frame, NmtState
from bus.sim import od as odm
from bus.sim.cia301 import Cia301Node, RxPdo, TxPdo
from bus.sim.od import Key, SdoAbort


def _builder(packer: struct.Struct, getters: tuple[Callable[[], int], ...]) -> Callable[[], bytes]:
    """payload = packer.pack(getter values), unrolled for the usual 1-3 entries (per-SYNC hot path)."""
    pack = packer.pack
    if len(getters) == 1:
        (g0,) = getters
        return lambda: pack(g0())
    if len(getters) == 2:
        g0, g1 = getters
        return lambda: pack(g0(), g1())
    if len(getters) == 3:
        g0, g1, g2 = getters
        return lambda: pack(g0(), g1(), g2())
    return lambda: pack(*[g() for g in getters])


class PdoLayer(Cia301Node):
    """PDO mapping and traffic of one simulated drive. See the module docstring."""

    # what a family sets (bus/sim/device.py lists the family's class attributes)
    family: str
    rtr_tpdo_types: frozenset[int]
    accepts_longer_rpdo: bool
    # the state, set in DriveDevice.__init__
    pdo_config_version: int
    _tpdo_latency_s: float
    _tpdo_jitter_s: float
    _latency_rng: random.Random

    # ---- PDO configuration (CiA 301 7.5.2.35-38)
    def _pdo_cob_writer(self, comm: int) -> Callable[[int], None]:
        def write(value: int) -> None:
            old = self._od[(comm, 1)]
            if value & (1 << 29):
                raise SdoAbort(odm.ABORT_INVALID_VALUE, "29-bit COB-IDs are not supported")
            if not old & odm.PDO_DISABLED and not value & odm.PDO_DISABLED and (old ^ value) & 0x7FF:
                raise SdoAbort(odm.ABORT_INVALID_VALUE,
                               f"0x{comm:04X}:01 cannot change the COB-ID of a valid PDO")
            self._od[(comm, 1)] = value
            self._rebuild_pdos()

        return write

    def _pdo_type_writer(self, comm: int, direction: str) -> Callable[[int], None]:
        def write(value: int) -> None:
            rtr = direction == "tx" and value in self.rtr_tpdo_types
            if not (value <= 240 or value in (254, 255) or rtr):
                raise SdoAbort(odm.ABORT_INVALID_VALUE,
                               f"{direction}PDO transmission type {value} not supported")
            self._od[(comm, 2)] = value
            self._rebuild_pdos()

        return write

    def _tpdo_timing_writer(self, comm: int, sub: int) -> Callable[[int], None]:
        """0x18xx:03 (inhibit time, 100 us) and 0x18xx:05 (event timer, ms): stored and applied to the TPDO
        as it runs, keeping when it was last sent (CiA 301 lets a master change the event timer of a valid
        PDO; a rebuild would only pick it up at the next remapping)."""
        number = comm - 0x1800 + 1

        def write(value: int) -> None:
            self._od[(comm, sub)] = value
            for p in (*self._tx_event, *self._tx_sync):
                if p.number == number:
                    if sub == 5:
                        p.event_timer_s = value * 1e-3
                    else:
                        p.inhibit_s = value * 1e-4

        return write

    def _check_mapping_editable(self, mapping: int, comm: int) -> None:
        if not self._od[(comm, 1)] & odm.PDO_DISABLED:
            raise SdoAbort(odm.ABORT_PARAMETER_INCOMPATIBLE,
                           f"0x{mapping:04X}: set 0x{comm:04X}:01 bit 31 (PDO invalid) before remapping")

    def _check_entry(self, word: int, direction: str) -> int:
        if word == 0:
            return 0
        index, sub, bits = word >> 16, (word >> 8) & 0xFF, word & 0xFF
        s = self.objects.objects.get((index, sub))
        if s is None or index in self._absent or not s.pdo or (
                bits != s.dtype.bits and not self._may_map_short((index, sub), bits, direction)):
            raise SdoAbort(odm.ABORT_CANNOT_MAP, f"0x{index:04X}:{sub:02X} ({bits} bits) cannot be mapped")
        if (direction == "rx" and not s.writable) or (direction == "tx" and not s.readable):
            raise SdoAbort(odm.ABORT_CANNOT_MAP,
                           f"0x{index:04X}:{sub:02X} cannot be mapped into a {direction}PDO")
        return bits

    def _pdo_count_writer(self, mapping: int, comm: int, direction: str) -> Callable[[int], None]:
        def write(value: int) -> None:
            self._check_mapping_editable(mapping, comm)
            total = 0
            for k in range(1, value + 1):
                word = self._od[(mapping, k)]
                if word == 0:
                    raise SdoAbort(odm.ABORT_CANNOT_MAP, f"0x{mapping:04X}:{k:02X} is empty")
                total += self._check_entry(word, direction)
            if total > 64:
                raise SdoAbort(odm.ABORT_PDO_LENGTH, f"0x{mapping:04X}: {total} bits exceed 64")
            self._od[(mapping, 0)] = value
            self._rebuild_pdos()

        return write

    def _pdo_entry_writer(self, mapping: int, k: int, comm: int, direction: str) -> Callable[[int], None]:
        def write(value: int) -> None:
            self._check_mapping_editable(mapping, comm)
            if self._od[(mapping, 0)] != 0:
                raise SdoAbort(odm.ABORT_PARAMETER_INCOMPATIBLE,
                               f"0x{mapping:04X}:00 must be 0 while entries are written")
            self._check_entry(value, direction)
            self._od[(mapping, k)] = value

        return write

    def _getter(self, key: Key) -> Callable[[], int]:
        dyn = self._dynamic.get(key)
        if dyn is not None:
            return dyn
        od = self._od
        return lambda: od[key]

    def _rebuild_pdos(self) -> None:
        od = self._od
        rx: dict[int, RxPdo] = {}
        tx_sync: list[TxPdo] = []
        tx_event: list[TxPdo] = []
        for n in range(4):
            cob = od[(0x1400 + n, 1)]
            count = od[(0x1600 + n, 0)]
            if not cob & odm.PDO_DISABLED and count:
                words = [od[(0x1600 + n, k)] for k in range(1, count + 1)]
                keys = tuple((w >> 16, (w >> 8) & 0xFF) for w in words)
                bits = tuple(w & 0xFF for w in words)
                fmt = "<" + "".join(self._entry_code(k, b) for k, b in zip(keys, bits, strict=True))
                st = struct.Struct(fmt)
                short = any(b != self.objects.objects[k].dtype.bits for k, b in zip(keys, bits, strict=True))
                rx[cob & 0x7FF] = RxPdo(n + 1, cob & 0x7FF, od[(0x1400 + n, 2)] <= 240, st.size, keys, st,
                                         self._is_record_pdo(keys), bits, short)
            cob = od[(0x1800 + n, 1)]
            count = od[(0x1A00 + n, 0)]
            if not cob & odm.PDO_DISABLED and count:
                words = [od[(0x1A00 + n, k)] for k in range(1, count + 1)]
                keys = tuple((w >> 16, (w >> 8) & 0xFF) for w in words)
                fmt = "<" + "".join(self._struct_code(k) for k in keys)
                ttype = od[(0x1800 + n, 2)]
                if ttype in (252, 253):
                    continue  # RTR only: this simulation serves no remote requests, so it is never sent
                # a family's table may lack the optional sub-indices 3/5/6 (seed 003: TPDO parameters 1-2)
                pdo = TxPdo(n + 1, cob & 0x7FF, ttype,
                             _builder(struct.Struct(fmt), tuple(self._getter(k) for k in keys)),
                             inhibit_s=od.get((0x1800 + n, 3), 0) * 1e-4,
                             event_timer_s=od.get((0x1800 + n, 5), 0) * 1e-3,
                             start_value=od.get((0x1800 + n, 6), 0))
                pdo.started = not (pdo.start_value and self._sync_counter_max)
                (tx_sync if ttype <= 240 else tx_event).append(pdo)
        self._rx_by_cob = rx
        self._tx_sync = tx_sync
        self._tx_event = tx_event
        self.pdo_config_version += 1

    # ============================================================================================
    # PDO traffic

    def _on_rpdo(self, pdo: RxPdo, data: bytes, t: float) -> None:
        if len(data) != pdo.length:
            if len(data) > pdo.length and self.accepts_longer_rpdo:
                data = data[:pdo.length]
            else:
                self.counters.pdo_length_errors += 1
                code = codec.EMCY_PDO_LENGTH if len(data) < pdo.length else codec.EMCY_PDO_LENGTH_EXCEEDED
                self._fault(code, 0, t)
                return
        if pdo.is_record and not pdo.synchronous:
            self._on_record(data)
            return
        values = pdo.unpacker.unpack(data)
        # dummy entries (index < 0x1000, CiA 301 dummy mapping) only hold the place of other data
        pairs = [(k, v, b) for k, v, b in zip(pdo.keys, values, pdo.bits, strict=True) if k[0] >= 0x1000]
        self._rpdo_received(pdo.keys, t)
        if pdo.synchronous:
            self._pending_sync[pdo.number] = pairs
        else:
            self._apply_pdo_pairs(pairs)

    def _apply_pdo_pairs(self, pairs: list[tuple[Key, int, int]]) -> None:
        objects = self.objects.objects
        for key, value, bits in pairs:
            try:
                spec = objects[key]
                if bits != spec.dtype.bits:
                    value = self._widen(key, value, bits)
                odm.check_value(spec, value)
                self._write(key, value, via_sdo=False)
            except SdoAbort:
                self.counters.pdo_writes_rejected += 1

    def _sample_sync_tpdos(self, counter: int | None) -> list[Frame]:
        """The synchronous TPDOs due at this SYNC, sampled now (CiA 301: type n = every n-th SYNC; with a
        SYNC counter and a start value, first at the SYNC whose counter equals the start value)."""
        out: list[Frame] = []
        for p in self._tx_sync:
            if not p.started:
                if counter is None or counter != p.start_value:
                    continue
                p.started = True
                p.sync_count = p.trans_type - 1
            p.sync_count += 1
            if p.trans_type == 0:
                payload = p.build()
                if payload != p.last:
                    p.last = payload
                    out.append(Frame(p.cob_id, payload))
            elif p.sync_count >= p.trans_type:
                p.sync_count = 0
                out.append(Frame(p.cob_id, p.build()))
        return out

    def _send_sync_tpdos(self, frames: list[Frame], t: float) -> None:
        """Now, or after this SYNC's latency draw (the `tpdo_latency_ms` option, plus the `tpdo_jitter_ms`
        draw; all of a SYNC's TPDOs go together, in PDO order, never before the previous SYNC's)."""
        if not frames:
            return
        if self._tpdo_latency_s <= 0.0 and self._tpdo_jitter_s <= 0.0:
            self._out.extend(frames)
            return
        at = t + self._latency_rng.uniform(0.0, self._tpdo_latency_s)
        if self._tpdo_jitter_s > 0.0:
            at += self._latency_rng.uniform(0.0, self._tpdo_jitter_s)
        # in order: a SYNC's answers never overtake the previous SYNC's (a later draw waits behind them)
        if self._held:
            at = max(at, self._held[-1][0])
        self._held.extend((at, f) for f in frames)

    def _release_held(self, t: float) -> None:
        """TPDOs whose latency ran out by t go out (in order), before anything the drive does at t."""
        held = self._held
        while held and held[0][0] <= t:
            self._out.append(held.pop(0)[1])

    def _flush_event_tpdos(self) -> None:
        """Event-driven TPDOs (types 254/255): sent when their payload changed, no sooner than the inhibit
        time after the previous one (a change inside it is sent when it ends), and at least every event
        timer period (CiA 301 0x18xx:03 / 0x18xx:05)."""
        if not self._tx_event or self._nmt != NmtState.OPERATIONAL:
            return
        t = self._t_now
        for p in self._tx_event:
            payload = p.build()
            changed = payload != p.last
            timer_due = p.event_timer_s > 0.0 and p.sent_at is not None and t >= p.sent_at + p.event_timer_s
            if not (changed or timer_due or p.pending):
                continue
            if p.sent_at is not None and t < p.sent_at + p.inhibit_s - 1e-9:
                p.pending = True
                continue
            p.last = payload
            p.sent_at = t
            p.pending = False
            self._out.append(Frame(p.cob_id, payload))

    def _event_deadline(self) -> float | None:
        if self._nmt != NmtState.OPERATIONAL:
            return None
        times: list[float] = []
        for p in self._tx_event:
            if p.sent_at is None:
                continue
            if p.pending:
                times.append(p.sent_at + p.inhibit_s)
            if p.event_timer_s > 0.0:
                times.append(p.sent_at + p.event_timer_s)
        return min(times) if times else None

    # ============================================================================================
    # what a family adds to the PDOs (the defaults: CiA 301 as written)

    def _struct_code(self, key: Key) -> str:
        return self.objects.objects[key].dtype.struct_code

    def _entry_code(self, key: Key, bits: int) -> str:
        """The struct code of a mapped entry: its object's type, or that signedness at the mapped length."""
        dtype = self.objects.objects[key].dtype
        if bits == dtype.bits:
            return self._struct_code(key)
        code = {8: "b", 16: "h", 32: "i", 64: "q"}[bits]
        return code if dtype.signed else code.upper()

    def _may_map_short(self, key: Key, bits: int, direction: str) -> bool:
        """May `key` be mapped with fewer bits than its type (seed 003: 16-bit set points)? Default no."""
        return False

    def _widen(self, key: Key, value: int, bits: int) -> int:
        """The object value an entry mapped with `bits` (< its type) carries; default: as received
        (sign-extended for a signed object)."""
        return value

    def _rpdo_received(self, keys: tuple[Key, ...], t: float) -> None:
        """An RPDO mapping `keys` arrived at `t` (accepted; synchronous ones are applied at the next SYNC)."""

    def _is_record_pdo(self, keys: tuple[Key, ...]) -> bool:
        """An RPDO whose payload goes to `_on_record` as it is (a FIFO record)."""
        return False

    def _on_record(self, data: bytes) -> None:
        raise NotImplementedError(f"{self.family} drives take no records")  # pragma: no cover
