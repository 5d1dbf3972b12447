"""What goes on the wire in a cycle: a FIFO axis' next batch of records (`_feed`: up to the lockstep prefix,
within its free space, the overflow watermark and this cycle's frame budget; an axis behind the others
catches up one record per cycle from the budget's spare part), and the cyclic axes' set point frames
(`_send_setpoints`: one per axis or multiplexed group every SYNC, bit 4 for an XtrapulsPac once SYNC has run
its `sync_lock_ms`). Every frame sent is counted in the cycle's bits and the report's frame counts.
"""

from __future__ import annotations

from bus.budget import RECORD_FRAME_BITS, setpoint_frame_bits
from streamer.core.axis_state import FeederInput, FeederState
from streamer.core.cyclic_feeder import CyclicFeeder, pack_frame
from streamer.core.fifo_feeder import FifoFeeder
from streamer.core.job_core import JobCore
from streamer.core.job_state import CW_ENABLE_OPERATION, CW_START_IP, CYCLIC_SENDING, JobState


class Sending(JobCore):
    """Sending records and set points within the cycle's budget."""

    def _feed(self, f: FifoFeeder, fill: int, free: int) -> None:
        if f.pending:
            return
        lo = f.confirmed
        hi = f.stream_prefix(self._lockstep)
        n = min(hi - lo, free, self._o - fill)
        if n <= 0:
            return
        # keep batches as small as this cycle's lockstep step (>= 1): an axis behind the others (after a
        # repair or a missed TPDO) catches up one record per cycle, not in one large batch whose partial
        # loss could not be repaired, unless its fill needs more to stay >= U for repair_syncs SYNCs
        cap = max(1, self._lockstep - self._lock_prev, f.stream_prefix(self._safe_prefix) - lo)
        if n > cap:
            n = cap
        catch = min(n, f.stream_prefix(self._lock_prev) - lo)
        if catch > 0:
            afford = int(self._extra_bits // RECORD_FRAME_BITS)
            if afford < catch:
                n = afford  # only what the spare budget allows; the regular part must wait (order)
            self._extra_bits -= min(catch, n) * RECORD_FRAME_BITS
            if n <= 0:
                return
        newest = max(s for s in (self._sync, self._wire_sync) if s is not None) if (
            self._sync is not None or self._wire_sync is not None) else -1
        sends = f.take(n, newest + 1)
        self._out.extend(sends)
        self._cycle_used_bits += n * RECORD_FRAME_BITS
        self._frames_sent += n
        self._record_frames += n
        self._emitted_any = True

    def _sync_ran_ms(self, m: int) -> float:
        """How long SYNC had run at SYNC m (since the producer's run began, as far as the core knows)."""
        t = self._sync_times.get(m)
        if t is None or self._sync_since is None:
            return 0.0
        return 1000.0 * (t - self._sync_since)

    def _request_ip(self, f: CyclicFeeder, m: int) -> None:
        """Controlword bit 4 to an XtrapulsPac after SYNC m, once SYNC has run long enough at the SYNC that
        applies it (m + 1) for the drive's PLL to have locked: `sync_lock_ms` before SYNC m, one period to
        spare (a drive refuses bit 4 before that, seed 003: "At least 180 ms are necessary for the
        servo-drive to start the synchronisation"; the manual gives no synchronisation state to read, so
        statusword bit 12 after bit 4 is the check)."""
        ran = self._sync_ran_ms(m)
        if ran + 1e-6 < f.spec.sync_lock_ms:
            return
        self._emit_cw(f, CW_START_IP)
        f.ip_requested(m, round(ran + self._period))

    def _send_setpoints(self, m: int) -> None:
        """After SYNC m: every cyclic frame whose axes are being fed, each axis' set point for SYNC m + 1;
        an XtrapulsPac that has reached its last set point gets bit 4 cleared (ip mode off)."""
        s = self._start_sync
        values: dict[int, tuple[int, int]] = {}
        sending: set[int] = set()
        for f in self._cyclic:
            j = f.index_after(m, s) if f.state is not FeederState.FINISHED else f.n
            values[f.node_id] = f.value(j)
            if f.state in CYCLIC_SENDING:
                sending.add(f.node_id)
                f.sent(j)
                if f.state is FeederState.STREAMING and j >= f.n and self._open_plan is None:
                    f.fire(FeederInput.END_QUEUED)
            if (f.state is FeederState.DRAINING and f.spec.starts_with_bit4 and f.bit4_off_sync is None
                    and s is not None and m >= s + f.n):
                self._emit_cw(f, CW_ENABLE_OPERATION)  # the drive is at its last set point: ip mode off
                f.ip_released(m + 1)
        if self._state is JobState.HALTING:
            return  # the cyclic axes were quick-stopped: they take no set points
        for members in self._groups.values():
            if not any(node in sending for node in members):
                continue
            frame = pack_frame({n: self._settings.cyclic[n].slot for n in members}, members, values)
            self._out.append(frame)
            self._cycle_used_bits += float(setpoint_frame_bits((len(frame.data),)))
            self._frames_sent += 1
            self._record_frames += 1
            self._emitted_any = True
