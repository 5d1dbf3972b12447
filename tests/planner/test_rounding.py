"""The plan is encoded for each drive's rounding of its position demand (issue 11 variant 4): to nearest,
or toward zero where `pvt probe` found the drive truncates ([axis.probed] rounding = "toward_zero")."""

from __future__ import annotations

import dataclasses

import numpy as np

from planner.config import CellConfig
from planner.plan import plan_job
from planner.readings import SimDriveOptions
from streamer import demo


def truncating(cell: CellConfig) -> CellConfig:
    return dataclasses.replace(cell, axes=tuple(
        dataclasses.replace(a, probed=dataclasses.replace(a.probed, rounding="toward_zero")) for a in cell.axes))


def test_a_truncating_drive_gets_a_plan_within_tolerance_as_it_rounds() -> None:
    base, job, nearest = demo.prepare(axes=3)
    tz = plan_job(job, truncating(base))
    tol = tz.tolerance_counts
    assert np.abs(tz.deviation(toward_zero=True)).max() <= tol
    assert [s.max_deviation_counts for s in tz.stats] == [int(d) for d in np.abs(tz.deviation(True)).max(axis=1)]
    # the plan encoded for drives that round to nearest is not good enough for drives that truncate (the
    # reason the encoder must know): on this path it misses by a count
    assert np.abs(nearest.deviation(toward_zero=False)).max() <= tol
    assert np.abs(nearest.deviation(toward_zero=True)).max() > tol


def test_commission_measures_the_rounding_of_each_simulated_drive() -> None:
    base, _job, _ = demo.prepare(axes=3)
    modes = ["toward_zero", "nearest", "toward_zero"]
    cell = dataclasses.replace(base, axes=tuple(
        dataclasses.replace(a, sim=SimDriveOptions(rounding=m)) for a, m in zip(base.axes, modes, strict=True)))
    assert [a.probed.rounding for a in demo.commission(cell).axes] == modes
    assert [a.probed.tpdo_latency_ms for a in demo.commission(cell).axes] == [None] * 3  # left to the runtime
