"""Benchmark: the `ipc` bus (bus/ipc.py) between two processes, against python-can's `virtual` bus between
two threads of one process (the product's in-process default), measured in the same run.

Two measurements, each for both buses, interleaved, median of `REPEATS` runs:

- throughput: the sender sends `BURST_FRAMES` 8-byte frames as fast as it can; the receiver reads them
  and reports the frames it got per second, from the first frame's arrival to the last one's. The ipc
  receiver may lose frames when its socket buffer overflows (counted in `IpcBus.stats.rx_lost`, shown);
  `virtual` never loses (an unbounded queue), it makes the sender wait on the GIL instead.
- one-way latency: the sender sends one frame every `PACED_PERIOD_S` (the pace of a cell's frames around
  a SYNC), the receiver notes for each frame its receive time (`time.time()` when `recv` returns) minus
  the frame's timestamp (on ipc the sender's stamp taken in `send`; on `virtual` the same, python-can
  stamps the frame in `send`); p50 and p99.

The ratios (ipc / virtual) are the portable numbers: frames/s above 1 means the ipc bus carries more,
latency above 1 means it is slower. On ipc the sender is a separate Python process
(`python -m benchmarks.bench_ipc --sender ...`), as `pvt sim` is; the 2 cores are shared with it.

Run: `python -m benchmarks.bench_ipc` (or via `python -m benchmarks`).
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import can

import bus.ipc

ROOT = Path(__file__).resolve().parent.parent
BURST_FRAMES = 20_000
PACED_FRAMES = 1_000
PACED_PERIOD_S = 0.001
REPEATS = 3
START_TIMEOUT_S = 20.0  # the sender process's python start-up
QUIET_S = 0.5  # the burst is over when nothing arrived for this long


def send(interface: str, channel: str, mode: str, count: int) -> None:
    """The sender: `count` frames, as fast as possible ("burst") or one every PACED_PERIOD_S ("paced")."""
    with can.Bus(interface=interface, channel=channel) as b:
        frame = can.Message(arbitration_id=0x281, data=bytes(8), is_extended_id=False)
        next_at = time.perf_counter()
        for i in range(count):
            frame.data[:4] = i.to_bytes(4, "little")
            b.send(frame)
            if mode == "paced":
                next_at += PACED_PERIOD_S
                delay = next_at - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)


def receive(b: can.BusABC, count: int) -> tuple[int, float, list[float]]:
    """(frames received, s from the first to the last arrival, one-way latencies in s)."""
    latencies: list[float] = []
    first = last = 0.0
    got = 0
    timeout = START_TIMEOUT_S
    while got < count:
        m = b.recv(timeout=timeout)
        if m is None:
            break
        now = time.time()
        latencies.append(now - m.timestamp)
        last = time.perf_counter()
        if got == 0:
            first = last
            timeout = QUIET_S
        got += 1
    return got, last - first, latencies


def run(interface: str, mode: str, count: int) -> dict[str, float]:
    channel = f"bench-{os.getpid()}-{time.monotonic_ns()}"
    receiver = can.Bus(interface=interface, channel=channel)
    sender: subprocess.Popen[bytes] | threading.Thread
    try:
        if interface == "ipc":  # the sender in a process of its own
            sender = subprocess.Popen([sys.executable, "-m", "benchmarks.bench_ipc", "--sender", interface, channel,
                                       mode, str(count)], cwd=ROOT)
        else:  # virtual: a thread of this process
            sender = threading.Thread(target=send, args=(interface, channel, mode, count), name="bench-sender")
            sender.start()
        got, span_s, latencies = receive(receiver, count)
        if isinstance(sender, threading.Thread):
            sender.join()
        elif sender.wait(timeout=60) != 0:
            raise RuntimeError(f"the sender process failed ({sender.returncode})")
        lost = receiver.stats.rx_lost if isinstance(receiver, bus.ipc.IpcBus) else count - got
    finally:
        receiver.shutdown()
    if got < 2:
        raise RuntimeError(f"{interface}: only {got} of {count} frames arrived")
    latencies.sort()
    return {"frames_per_s": (got - 1) / span_s if span_s > 0 else float("inf"), "received": got, "lost": lost,
            "p50_ms": 1e3 * latencies[len(latencies) // 2], "p99_ms": 1e3 * latencies[int(len(latencies) * 0.99)]}


def median_of(runs: list[dict[str, float]], key: str) -> float:
    return statistics.median(r[key] for r in runs)


def main() -> int:
    print(f"bench_ipc: ipc bus between two processes vs python-can virtual between two threads (median of {REPEATS}; "
          f"{os.cpu_count()} cores)")
    results: dict[tuple[str, str], list[dict[str, float]]] = {}
    for _ in range(REPEATS):  # interleaved: a busy moment of the shared machine hits both
        for interface in ("virtual", "ipc"):
            results.setdefault((interface, "burst"), []).append(run(interface, "burst", BURST_FRAMES))
            results.setdefault((interface, "paced"), []).append(run(interface, "paced", PACED_FRAMES))
    fps = {i: median_of(results[(i, "burst")], "frames_per_s") for i in ("virtual", "ipc")}
    lost = {i: median_of(results[(i, "burst")], "lost") for i in ("virtual", "ipc")}
    p50 = {i: median_of(results[(i, "paced")], "p50_ms") for i in ("virtual", "ipc")}
    p99 = {i: median_of(results[(i, "paced")], "p99_ms") for i in ("virtual", "ipc")}
    paced_lost = {i: median_of(results[(i, "paced")], "lost") for i in ("virtual", "ipc")}
    print(f"  throughput, burst of {BURST_FRAMES} frames: virtual {fps['virtual']:,.0f} frames/s, ipc "
          f"{fps['ipc']:,.0f} frames/s (lost {lost['ipc']:.0f}): ratio ipc/virtual {fps['ipc'] / fps['virtual']:.2f}")
    print(f"  one-way latency, 1 frame per {PACED_PERIOD_S * 1e3:g} ms x {PACED_FRAMES}: virtual p50 "
          f"{p50['virtual']:.3f} ms p99 {p99['virtual']:.3f} ms; ipc p50 {p50['ipc']:.3f} ms p99 {p99['ipc']:.3f} ms "
          f"(lost {paced_lost['ipc']:.0f}): ratio ipc/virtual p50 {p50['ipc'] / p50['virtual']:.2f}, "
          f"p99 {p99['ipc'] / p99['virtual']:.2f}")
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 6 and sys.argv[1] == "--sender":
        send(sys.argv[2], sys.argv[3], sys.argv[4], int(sys.argv[5]))
        raise SystemExit(0)
    raise SystemExit(main())
