"""Reliability suite fixtures: every FaultModel a test creates through `faults` has its seed printed
when the test fails (replay with PVT_FAULT_SEED=<seed>); `variant` runs a scenario on the reference
drive and on the drive variants issue 11 names for it (TPDO sampled before the RPDOs, FIFO counted
without the target, the drive's own clock, TPDO latency), and on answers later than the drive states
(issue 22: past the next SYNC)."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any

import pytest
from reliability_kit import SEED

from bus.faults import FaultModel, FaultRule


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Any:
    rep = yield
    setattr(item, f"rep_{rep.when}", rep)
    return rep


@pytest.fixture
def faults(request: pytest.FixtureRequest) -> Iterator[Callable[..., FaultModel]]:
    """faults(rules, seed=SEED, **kw) -> FaultModel; seeds are printed if the test fails."""
    made: list[FaultModel] = []

    def make(rules: Sequence[FaultRule], seed: int = SEED, **kw: Any) -> FaultModel:
        model = FaultModel(list(rules), seed=seed, **kw)
        made.append(model)
        return model

    yield make
    rep = getattr(request.node, "rep_call", None)
    if rep is not None and rep.failed:
        for m in made:
            print(f"[reliability] {m.describe()} -- replay with PVT_FAULT_SEED={m.seed}")


VARIANTS: dict[str, dict[str, Any]] = {
    "reference": {},
    "tpdo_before_rpdo": {"tpdo_sampling": "before_rpdo"},
    "fifo_until_start": {"fifo_count": "until_segment_start"},
    "own_clock": {"clock": "own", "clock_drift_ppm": 200.0},
    "tpdo_latency": {"tpdo_latency_ms": 9.0},
    # answers later than the drive states (a busy bus or host): some past the next SYNC, a few later than
    # 1.5 x the stated latency (the attribution is by content: streamer/core/attribution.py)
    "tpdo_late": {"tpdo_latency_ms": 9.0, "tpdo_jitter_ms": 6.0},
}


@pytest.fixture(params=list(VARIANTS))
def variant(request: pytest.FixtureRequest) -> dict[str, Any]:
    """The simulated drives' readings of the manuals' open points (planner/readings.py) for a scenario."""
    return VARIANTS[request.param]
