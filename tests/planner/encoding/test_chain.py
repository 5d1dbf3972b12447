"""The Hermite chain's search (planner/encoding/chain.py) on seeded paths: what its shortcuts rely on.

The greedy search tries the candidates in their order of preference and samples only those that pass
the cheap limit checks (`_first_passing`); this must place the same knots as checking every candidate
fully. And the chain it returns stays within its budget of the path at every ms and inside the box.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

import planner.encoding.chain as chain_mod
from planner import plan_job
from planner.config import CellConfig
from planner.job import job_from_dict


def _path_job(cell: CellConfig, seed: int, rows: int, axes: int, tolerance: float | None) -> Any:
    rng = np.random.default_rng(seed)
    names = list(cell.axis_names())[:axes]
    lo = np.array([cell.axis(a).position_min for a in names])
    hi = np.array([cell.axis(a).position_max for a in names])
    wp = lo + (hi - lo) * rng.uniform(0.2, 0.8, (rows, axes))
    # the chain is the acceleration-only plan's (a jerk-limited path has none)
    job: dict[str, Any] = {"kind": "path", "job_id": f"chain-{seed}", "axes": names, "waypoints": wp.tolist(),
                           "jerk_limited": False}
    if tolerance is not None:
        job["path_tolerance"] = tolerance
    return job_from_dict(job, cell)


@pytest.mark.parametrize(
    ("seed", "rows", "axes", "tolerance"), [(1, 6, 2, None), (6, 8, 3, 0.005), (7, 8, 3, 0.005), (3, 12, 6, None)]
)
def test_lazy_search_chooses_what_the_full_check_chooses(
    cell: CellConfig, seed: int, rows: int, axes: int, tolerance: float | None, monkeypatch: pytest.MonkeyPatch
) -> None:
    greedy = chain_mod._greedy
    seen = {"fits": 0, "fallbacks": 0}

    def checked(path: Any, mand: Any, min_seg: int, max_seg: int, allow_short: bool, lazy: bool) -> Any:
        knots, fallbacks = greedy(path, mand, min_seg, max_seg, allow_short, lazy)
        full, _ = greedy(path, mand, min_seg, max_seg, allow_short, False)
        np.testing.assert_array_equal(knots, full)
        seen["fits"] += 1
        # the case the lazy search exists for: the preferred one passes the limits, not the samples
        seen["fallbacks"] += fallbacks
        return knots, fallbacks

    fits: list[chain_mod.ChainFit] = []
    fit = chain_mod.fit_chain

    def recording(*args: Any, **kwargs: Any) -> chain_mod.ChainFit:
        out = fit(*args, **kwargs)
        fits.append(out)
        budget, box = np.maximum(args[5], 1e-12), args[11]
        # every ms of every segment of at least 2 ms is within the budget of the exact profile (a blend's
        # conservative bound, which also bounds the distance from a line) or of its line, inside the box
        q, direction, curved = args[0], args[2], args[3]
        d = (out.positions - q) / budget[:, None]
        ty = direction / budget[:, None]
        t = ty / np.maximum(np.linalg.norm(ty, axis=0), 1e-300)[None, :]
        perp = np.abs(d - t * np.einsum("it,it->t", d, t)[None, :]).max(axis=0)
        err = np.where(curved, np.abs(d).max(axis=0), perp)
        long = np.repeat(np.diff(out.knots) >= 2, np.diff(out.knots))
        assert float(err[1:][long].max(initial=0.0)) <= 1.0 + 1e-9
        assert np.all(out.positions >= box[0][:, None]) and np.all(out.positions <= box[1][:, None])
        return out

    monkeypatch.setattr(chain_mod, "_greedy", checked)
    monkeypatch.setattr(chain_mod, "fit_chain", recording)
    plan_job(_path_job(cell, seed, rows, axes, tolerance), cell)
    assert fits and seen["fits"] == len(fits)
    if tolerance is not None:  # tight blends: chosen so that the fallback to the next candidate happens
        assert seen["fallbacks"] > 0
