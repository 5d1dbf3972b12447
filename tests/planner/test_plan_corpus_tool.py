"""tools/plan_corpus.py, the regression check for planner work that must not change what it plans: the same
code plans the same corpus to the bit, and a plan that moved is reported."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def _tool():  # type: ignore[no-untyped-def]
    spec = importlib.util.spec_from_file_location("plan_corpus", ROOT / "tools" / "plan_corpus.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_corpus_plans_the_same_twice_and_a_moved_plan_is_reported() -> None:
    tool = _tool()
    before, _cpu = tool.plan_all(1)
    after, _cpu = tool.plan_all(1)
    assert len(after) == len(before) >= 13 and tool.differences(before, after) == []
    name = "bench-20"
    dt, pos, vel, plan = after[name]
    moved = pos.copy()
    moved[0, 1] += 1
    after[name] = (dt, moved, vel, plan + np.where(np.arange(plan.shape[1]) == 5, 0.5, 0.0))
    diff = tool.differences(before, after)
    assert len(diff) == 1 and diff[0].startswith("bench-20: points")
