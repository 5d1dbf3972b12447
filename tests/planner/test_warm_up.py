"""planner.plan.warm_up loads every compiled kernel a plan calls from Python (planner/jit.py), so that a
service's first job is not the one that pays for it: in a fresh process, after warm_up, planning every
example job and a random job of each kind, and every path of them jerk-limited too, compiles no kernel anew."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

_SCRIPT = """
import importlib, json, pkgutil
import numpy as np
from pathlib import Path
from numba.core.registry import CPUDispatcher
import planner
from planner.plan import plan_job, warm_up

def signatures():
    out = {}
    for info in pkgutil.walk_packages(planner.__path__, prefix="planner."):
        module = importlib.import_module(info.name)
        for name, value in vars(module).items():
            if isinstance(value, CPUDispatcher) and value.__module__ == module.__name__:
                out[f"{module.__name__}.{name}"] = len(value.signatures)
    return out

warm_up()
before = signatures()
from benchmarks.bench_planner import KINDS, benchmark_path, random_job
from planner.config import load_cell
from planner.errors import PlanningError
from planner.job import job_from_dict, load_job
cell = load_cell(Path("configs/demo.toml"))
jobs = [load_job(p, cell) for p in sorted(Path("configs/jobs").iterdir())] + [benchmark_path(cell)]
for k, kind in enumerate(KINDS):
    jobs.append(job_from_dict(random_job(kind, np.random.default_rng(k), cell), cell))
import dataclasses
from planner.job import PathData
jobs += [dataclasses.replace(j, data=dataclasses.replace(j.data, jerk_limited=flag))
         for j in list(jobs) if isinstance(j.data, PathData) for flag in (False, True)]
for job in jobs:
    plan_job(job, cell)
print(json.dumps({"before": before, "after": signatures()}))
"""


def test_after_warm_up_no_plan_compiles_a_kernel() -> None:
    out = subprocess.run([sys.executable, "-c", _SCRIPT], cwd=ROOT, capture_output=True, text=True, timeout=600,
                         check=True)
    seen = json.loads(out.stdout.strip().splitlines()[-1])
    before, after = seen["before"], seen["after"]
    assert any(n > 0 for n in before.values())  # the kernels are found at all
    assert {k: (before.get(k), n) for k, n in after.items() if n != before.get(k)} == {}


def test_the_freed_heap_is_kept_for_the_next_plan_on_glibc() -> None:
    """planner.jit.keep_heap: glibc takes the setting (mallopt answers 1); other C libraries are left alone."""
    import platform

    from planner.jit import keep_heap

    if platform.libc_ver()[0] == "glibc":
        assert keep_heap() is True
    else:
        assert keep_heap() is False
