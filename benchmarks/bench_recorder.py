"""Benchmark: the drive's own data recorder (seed 004): uploading its buffer, and what recording costs the
simulated drive.

1. The time to upload a full 512-word buffer (0x201B, 1024 bytes) at 1 Mbit/s, SDO segmented vs block
   upload, counted from the frames each needs: the real exchange runs between canopen's SDO client (the
   master's `Recorder`) and the simulated drive's SDO servers (`SimulatedCell` on a python-can virtual
   bus), every SDO frame is captured, and the wire time is the sum of their worst-case bit lengths
   (`bus.codec.frame_bits`) at 1 Mbit/s plus one response latency per change of direction (a drive does
   not answer in zero time: 0, 0.2 and 1 ms are shown). python-can's virtual bus has no bit timing, so
   the frames, not its wall clock, give the number.
2. The simulated drive's tick rate while its recorder samples, against the same drive not recording,
   measured in the same run (interleaved, best of 3): one drive streaming a sinusoid (the stream of
   bench_sim.py) with the recorder in continuous mode at 1 ms (whole ticks: the 1 ms plant, sampled
   between chunks of ticks), 0.5 ms and 0.1 ms (the plant sub-stepped 2 and 10 times per tick).

Run: `python -m benchmarks.bench_recorder` or call `main()`.
"""

from __future__ import annotations

import itertools
import time

import can

from benchmarks.bench_sim import FIFO_TARGET, _record
from bus import cob, codec
from bus.codec import frame_bits
from bus.sim.node import SimulatedCell
from bus.sim.virtual import VirtualCell
from planner.config import BusConfig, CellConfig, default_config_path, load_cell

BITRATE = 1_000_000
LATENCIES_S = (0.0, 0.0002, 0.001)


class _Capture(can.Listener):
    def __init__(self, ids: set[int]):
        self.ids = ids
        self.frames: list[tuple[int, int]] = []  # (cob id, dlc)

    def on_message_received(self, msg: can.Message) -> None:
        if msg.arbitration_id in self.ids:
            self.frames.append((msg.arbitration_id, msg.dlc))


def upload_frames(cell: CellConfig) -> dict[str, list[tuple[int, int]]]:
    """The SDO frames of one full-buffer upload, segmented and block, from the real exchange."""
    import canopen

    from streamer.recording.drive import RecordRequest, parse_variable
    from streamer.recording.recorder_client import Recorder

    out: dict[str, list[tuple[int, int]]] = {}
    with SimulatedCell(cell, sync_gap_factor=5.0) as sim:
        net = canopen.Network()
        net.connect(interface="virtual", channel=cell.bus.channel, receive_own_messages=True)
        try:
            capture = _Capture({0x601, 0x581})
            net.notifier.add_listener(capture)  # type: ignore[union-attr]
            net.sync.start(cell.sync_period_s)
            request = RecordRequest((parse_variable("position_demand"), parse_variable("position_actual"),
                                     parse_variable("velocity_actual"), parse_variable("following_error")),
                                    trigger="continuous", period_ms=1.0)
            for method, block in (("segmented", False), ("block", True)):
                rec = Recorder.over(net, 1, block=block)
                rec.configure(request)
                rec.arm()
                deadline = time.monotonic() + 5.0
                while sim.model(1).recorder.samples_taken < 64 and time.monotonic() < deadline:
                    time.sleep(0.01)
                rec.stop()
                capture.frames.clear()
                data = rec.upload()
                if len(data) != 1024 or rec.last_upload != method:
                    raise RuntimeError(f"{method}: {len(data)} bytes by {rec.last_upload}")
                time.sleep(0.05)
                out[method] = list(capture.frames)
        finally:
            net.sync.stop()
            net.disconnect()
    return out


def wire_time_s(frames: list[tuple[int, int]], latency_s: float) -> tuple[float, int]:
    """(seconds on a 1 Mbit/s bus, changes of direction) of a frame sequence."""
    bits = sum(frame_bits(dlc) for _, dlc in frames)
    turns = sum(1 for a, b in itertools.pairwise(frames) if a[0] != b[0])
    return bits / BITRATE + turns * latency_s, turns


def tick_rate(recording_units: int | None, seconds: float = 10.0) -> float:
    """Drive ticks per wall second of one drive streaming the bench_sim sinusoid (10 ms SYNC), recording
    (continuous, 2 x 32-bit variables) at `recording_units` x 0.1 ms, or not."""
    demo = load_cell(str(default_config_path()))
    cell = demo.with_axes(1)
    vc = VirtualCell(cell)
    m = vc.model(1)
    cpr = cell.axes[0].counts_per_rev
    t = 0.0
    period = cell.sync_period_s
    for cw in (0x0006, 0x000F):
        vc.deliver(cob.rpdo1_id(1), cob.pack_controlword(cw), t)
        t += period
        vc.advance(t)
        vc.sync(t)
    vc.sdo_write(1, 0x60C4, 6, 0)
    vc.sdo_write(1, 0x60C4, 6, 1)
    syncs = round(seconds / period)
    records = [_record(k, cpr) for k in range(syncs + FIFO_TARGET + 4)]
    knot = 1
    for _ in range(FIFO_TARGET):
        vc.deliver(cob.rpdo2_id(1), records[knot], t)
        knot += 1
    if recording_units is not None:
        for index, sub, value in ((0x2011, 0, 0), (0x2012, 0, recording_units), (0x2014, 0, 2), (0x2015, 1, 0x6062),
                                  (0x2015, 2, 0x6064)):
            vc.sdo_write(1, index, sub, value)
        vc.sdo_write(1, 0x2010, 0, 1)
    vc.deliver(cob.rpdo1_id(1), cob.pack_controlword(0x001F), t)
    ticks0 = m.counters.ticks
    start = time.perf_counter()
    for _ in range(syncs):
        t += period
        frames = vc.advance(t) + vc.sync(t)
        for f in frames:
            if f.cob_id == cob.tpdo1_id(1):
                for _ in range(codec.decode_tpdo1(f.data).free_size - (64 - FIFO_TARGET)):
                    vc.deliver(cob.rpdo2_id(1), records[knot], t)
                    knot += 1
    wall = time.perf_counter() - start
    if m.counters.faults:
        raise RuntimeError(f"the benchmark stream faulted the drive: {m.fault_log}")
    if recording_units is not None and not m.recorder.active:
        raise RuntimeError("the recorder stopped")
    return (m.counters.ticks - ticks0) / wall


def main() -> int:
    print("bench_recorder: the drive's data recorder (seed 004)")
    cell = CellConfig(name="bench", sync_period_ms=10, axes=load_cell(str(default_config_path())).axes[:1],
                      bus=BusConfig("virtual", f"bench-recorder-{time.monotonic_ns()}", BITRATE))
    frames = upload_frames(cell)
    print("\n  upload of a full 512-word buffer (1024 bytes) at 1 Mbit/s, from the frames of the real exchange "
          "(canopen client <-> simulated drive), worst-case bit stuffing:")
    print(f"  {'method':<10} {'frames':>6} {'turns':>5} " + " ".join(f"{'ms @ ' + str(lat * 1000) + ' ms lat':>16}"
                                                                  for lat in LATENCIES_S))
    times: dict[str, list[float]] = {}
    for method in ("segmented", "block"):
        row = [wire_time_s(frames[method], lat) for lat in LATENCIES_S]
        times[method] = [r[0] for r in row]
        print(f"  {method:<10} {len(frames[method]):>6} {row[0][1]:>5} " +
              " ".join(f"{1000 * r[0]:>16.2f}" for r in row))
    print("  segmented / block: " + ", ".join(f"{s / b:.2f}x" for s, b in zip(times["segmented"], times["block"],
                                                                              strict=True))
          + " (at the latencies above)")
    print("\n  simulated drive tick rate while recording (1 drive, 10 ms SYNC, sinusoid; best of 3, interleaved):")
    cases: list[tuple[str, int | None]] = [("not recording", None), ("recording at 1 ms", 10),
                                           ("recording at 0.5 ms", 5), ("recording at 0.1 ms", 1)]
    best: dict[str, float] = {}
    for _ in range(3):
        for label, units in cases:
            best[label] = max(best.get(label, 0.0), tick_rate(units))
    base = best["not recording"]
    for label, _units in cases:
        print(f"  {label:<22} {best[label]:>12,.0f} ticks/s  ratio {best[label] / base:.2f}  "
              f"({best[label] / 1000:.0f}x real time)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
