"""The job trace's bus-load tally holds one cycle's count and the peak, not a count per SYNC cycle: an endless
(velocity) job runs for hours (issue 23 item 10; benchmarks/bench_endless.py measures the rest)."""

from __future__ import annotations

import sys

from bus.cob import SYNC_COB_ID
from bus.codec import frame_bits
from streamer.runtime.trace import JobTrace


def _feed(trace: JobTrace, cycles: int) -> int:
    most = 0
    for c in range(cycles):
        trace.on_frame(SYNC_COB_ID, 0)
        bits = frame_bits(0)
        for _ in range(c % 7):  # a different load every cycle
            trace.on_frame(0x401, 8)
            bits += frame_bits(8)
        most = max(most, bits)
    return most


def test_bus_load_tally_is_constant_in_size_and_exact() -> None:
    short, long = (JobTrace([(1, "j1")], sync_period_s=0.01, bitrate=1_000_000) for _ in range(2))
    most = _feed(short, 100)
    assert _feed(long, 20_000) == most
    assert short.bus_load_peak() == long.bus_load_peak() == most / (1_000_000 * 0.01)
    size = sum(sys.getsizeof(v) for v in vars(long).values())
    assert size == sum(sys.getsizeof(v) for v in vars(short).values())  # 200 x the cycles, same size
