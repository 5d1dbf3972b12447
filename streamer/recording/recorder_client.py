"""`Recorder`: one drive's data recorder (seed 004) over SDO: configure, arm, wait, upload, decode.

    rec = Recorder.over(network, 2); rec.configure(request); rec.arm()
    ...                                    # move the axis
    rec.wait(timeout_s=5.0); node_recording = rec.read()

Objects go through an `SdoAccess`: `CanopenSdo` (a `RemoteNode`) or `ModelSdo` (a simulated drive, in
virtual time). 0x201B is uploaded by SDO block upload where the drive has it, else segmented. Every SDO
failure raises `DriveRecordingError(RECORDER)` naming the node, object and abort code.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, Protocol

from streamer.recording.drive import (
    CONTROL_FORCE,
    CONTROL_START,
    CONTROL_STOP,
    RECORDER,
    STATUS_RUNNING,
    STATUS_TRIGGERED,
    DriveRecordingError,
    NodeRecording,
    RecordRequest,
    decode_buffer,
)

BUFFER = (0x201B, 0)


class SdoAccess(Protocol):
    """SDO reads and writes of one node; `upload` gives a domain's bytes. Raise on failure."""

    node_id: int

    def read(self, index: int, sub: int) -> int: ...

    def write(self, index: int, sub: int, value: int) -> None: ...

    def upload(self, index: int, sub: int, *, block: bool) -> bytes: ...


class BlockRefused(Exception):
    """The drive does not do block upload (it answered something else, or aborted)."""


class CanopenSdo:
    """Through a canopen `RemoteNode` (its SDO client; canopen is untyped, hence Any)."""

    def __init__(self, node: Any):
        self.node = node
        self.node_id = int(node.id)

    def _var(self, index: int, sub: int) -> Any:
        obj = self.node.sdo[index]
        import canopen

        if isinstance(self.node.object_dictionary[index], canopen.objectdictionary.ODVariable):
            return obj
        return obj[sub]

    def read(self, index: int, sub: int) -> int:
        value = self._var(index, sub).raw
        if not isinstance(value, int):
            raise DriveRecordingError(RECORDER, f"node {self.node_id}: 0x{index:04X}:{sub:02X} is not an integer")
        return value

    def write(self, index: int, sub: int, value: int) -> None:
        self._var(index, sub).raw = value

    def upload(self, index: int, sub: int, *, block: bool) -> bytes:
        from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

        sdo = self.node.sdo
        if not block:
            return bytes(sdo.upload(index, sub))
        try:
            with sdo.open(index, sub, "rb", block_transfer=True) as f:
                return bytes(f.read())
        except SdoCommunicationError as e:
            raise BlockRefused(str(e)) from None
        except SdoAbortedError as e:
            if e.code in (0x05040001, 0x06010000):  # invalid command specifier, unsupported access
                raise BlockRefused(str(e)) from None
            raise


class ModelSdo:
    """Straight into a simulated `bus.sim.epos.EposDrive` (virtual time). Frames the drive answers a
    write with (an EMCY) go to `emit`."""

    def __init__(self, model: Any, *, clock: Callable[[], float] | None = None,
                 emit: Callable[[list[Any]], None] | None = None):
        self.model = model
        self.node_id = int(model.node_id)
        self._clock = clock
        self._emit = emit

    def read(self, index: int, sub: int) -> int:
        value: int = self.model.sdo_read(index, sub)
        return value

    def write(self, index: int, sub: int, value: int) -> None:
        frames = self.model.sdo_write(index, sub, value, self._clock() if self._clock is not None else None)
        if frames and self._emit is not None:
            self._emit(frames)

    def upload(self, index: int, sub: int, *, block: bool) -> bytes:
        data: bytes = self.model.read_domain(index, sub)
        return data


def _sdo_failure(e: Exception) -> str:
    """Why an SDO transfer failed, for an error message: the abort code when the drive gave one."""
    code = _abort_code(e)
    return f"abort 0x{code:08X}" if code is not None else f"{type(e).__name__}: {e}"


def _abort_code(e: BaseException) -> int | None:
    code = getattr(e, "code", None)
    return code if isinstance(code, int) else None


class Recorder:
    """One node's data recorder (see the module docstring)."""

    def __init__(self, sdo: SdoAccess, *, block: bool | None = None, direct: bool = False):
        self.sdo = sdo
        self.node_id = sdo.node_id
        self.block = block  # None: try block upload first, fall back to segmented
        self.direct = direct  # the access reads the model's memory directly (no transfer at all)
        self.request: RecordRequest | None = None
        self.last_upload: str = ""
        self.last_upload_s: float = 0.0

    @classmethod
    def over(cls, network: Any, node: Any, *, eds: str | None = None, block: bool | None = None) -> Recorder:
        """Over a canopen `Network`: `node` is a node id (added as a `RemoteNode` with `eds`, by default the
        drive's configs/drives/epos-ipm.eds, unless the network has it) or a `RemoteNode`."""
        if isinstance(node, int):
            if node in network:
                remote = network[node]
            else:
                from bus.sim.eds import EDS_PATH

                remote = network.add_node(node, str(eds or EDS_PATH))
        else:
            remote = node
        return cls(CanopenSdo(remote), block=block)

    # ---- SDO with errors that say where
    def _write(self, index: int, sub: int, value: int, what: str) -> None:
        try:
            self.sdo.write(index, sub, value)
        except DriveRecordingError:
            raise
        except Exception as e:
            raise DriveRecordingError(RECORDER, f"node {self.node_id} refused {what} (0x{index:04X}:{sub:02X} = "
                                      f"{value}): {_sdo_failure(e)}", f"0x{index:04X}:{sub:02X}") from None

    def _read(self, index: int, sub: int, what: str) -> int:
        try:
            return self.sdo.read(index, sub)
        except DriveRecordingError:
            raise
        except Exception as e:
            raise DriveRecordingError(RECORDER, f"node {self.node_id}: cannot read {what} (0x{index:04X}:{sub:02X}):"
                                      f" {_sdo_failure(e)}", f"0x{index:04X}:{sub:02X}") from None

    # ---- control
    def configure(self, request: RecordRequest) -> None:
        """Stop the recorder, write the configuration, and check 0x2018 agrees with the request's layout."""
        self._write(0x2010, 0, CONTROL_STOP, "recorder stop")
        for index, sub, value in request.registers():
            self._write(index, sub, value, "the recorder configuration")
        samples = self._read(0x2018, 0, "max samples")
        if samples != request.max_samples:
            raise DriveRecordingError(RECORDER, f"node {self.node_id}: 0x2018 says {samples} samples per variable; "
                                      f"{request.max_samples} expected for "
                                      f"{', '.join(v.name for v in request.variables)} (the words per sample differ)")
        self.request = request

    def arm(self) -> None:
        """Start the recorder (0x2010 = 1): it waits for its trigger, or records continuously."""
        if self.request is None:
            raise DriveRecordingError(RECORDER, f"node {self.node_id}: configure the recorder before arming it")
        self._write(0x2010, 0, CONTROL_START, "recorder start")

    def force_trigger(self) -> None:
        self._write(0x2010, 0, CONTROL_FORCE, "force trigger")

    def stop(self) -> None:
        self._write(0x2010, 0, CONTROL_STOP, "recorder stop")

    def status(self) -> int:
        return self._read(0x2017, 0, "recorder status")

    def running(self) -> bool:
        return bool(self.status() & STATUS_RUNNING)

    def triggered(self) -> bool:
        return bool(self.status() & STATUS_TRIGGERED)

    def wait(self, timeout_s: float, *, poll_s: float = 0.05, sleep: Callable[[float], None] = time.sleep,
             clock: Callable[[], float] = time.monotonic) -> bool:
        """Poll 0x2017 until the recorder stopped (True) or `timeout_s` passed (False)."""
        end = clock() + timeout_s
        while True:
            if not self.running():
                return True
            if clock() >= end:
                return False
            sleep(poll_s)

    # ---- the data
    def upload(self) -> bytes:
        """0x201B: block upload unless the drive refused it (then, and from then on, segmented)."""
        t0 = time.perf_counter()
        try:
            if self.direct:
                data = self.sdo.upload(*BUFFER, block=False)
                self.last_upload = "direct"
            elif self.block is not False:
                try:
                    data = self.sdo.upload(*BUFFER, block=True)
                    self.last_upload = "block"
                    self.block = True
                except BlockRefused:
                    self.block = False
                    data = self.sdo.upload(*BUFFER, block=False)
                    self.last_upload = "segmented"
            else:
                data = self.sdo.upload(*BUFFER, block=False)
                self.last_upload = "segmented"
        except DriveRecordingError:
            raise
        except Exception as e:
            code = _abort_code(e)
            why = f"abort 0x{code:08X}" if code is not None else f"{type(e).__name__}: {e}"
            raise DriveRecordingError(RECORDER, f"node {self.node_id}: cannot upload the recorder buffer 0x201B: "
                                      f"{why}", "0x201B:00") from None
        self.last_upload_s = time.perf_counter() - t0
        return data

    def read(self) -> NodeRecording:
        """0x2018, 0x2019, 0x2017 and 0x201B, decoded (the recorder should have stopped: `wait`, `stop`)."""
        request = self.request
        if request is None:
            raise DriveRecordingError(RECORDER, f"node {self.node_id}: nothing configured, nothing to read")
        samples = self._read(0x2018, 0, "max samples")
        offset = self._read(0x2019, 0, "offset of the recorded vector")
        status = self.status()
        data = self.upload()
        return decode_buffer(data, request.variables, samples=samples, offset=offset, status=status,
                             preceding=request.preceding_samples, period_s=request.period_s, node=self.node_id)


class RecorderGroup:
    """The recorders of several nodes run together around a job (what `pvt record` and a job's `record`
    section do): `start` configures and arms every one, lets the preceding time pass (the samples before
    the trigger must exist before anything can trigger) and forces the trigger for "force"; `finish`
    waits until every recorder stopped by itself (continuous: until the buffer spans its time once, then
    stops them), stops those that did not within `timeout_s`, and reads every one.

    `idle(s)` lets time pass (a sleep in real time, SYNC cycles in virtual time), `now()` reads that clock;
    `on_status(node, status)` sees every 0x2017 read (a progress display)."""

    def __init__(self, recorders: dict[int, Recorder], request: RecordRequest, *,
                 idle: Callable[[float], None] = time.sleep, now: Callable[[], float] = time.monotonic,
                 on_status: Callable[[int, int], None] | None = None):
        self.recorders = recorders
        self.request = request
        self._idle = idle
        self._now = now
        self._on_status = on_status
        self.armed_at: float | None = None
        self.forced_at: float | None = None
        self.not_triggered: list[int] = []

    def start(self) -> None:
        req = self.request
        for r in self.recorders.values():
            r.configure(req)
        for r in self.recorders.values():
            r.arm()
        self.armed_at = self._now()
        self._idle(req.preceding_samples * req.period_s + 2 * req.period_s)
        if req.trigger == "force":
            self.forced_at = self._now()
            for r in self.recorders.values():
                r.force_trigger()

    def finish(self, timeout_s: float) -> dict[int, NodeRecording]:
        req = self.request
        if req.trigger == "continuous":
            armed = self.armed_at if self.armed_at is not None else self._now()
            self._idle(req.span_s - (self._now() - armed) + req.period_s)
            for r in self.recorders.values():
                r.stop()
        waiting = set(self.recorders)
        end = self._now() + timeout_s
        while waiting:
            for n in sorted(waiting):
                status = self.recorders[n].status()
                if self._on_status is not None:
                    self._on_status(n, status)
                if not status & STATUS_RUNNING:
                    waiting.discard(n)
            if not waiting or self._now() >= end:
                break
            self._idle(min(0.05, max(req.period_s, 0.01)))
        self.not_triggered = sorted(waiting)
        for n in self.not_triggered:
            self.recorders[n].stop()
        out = {}
        for n, r in self.recorders.items():
            out[n] = r.read()
            if self._on_status is not None:
                self._on_status(n, r.status())
        return out
