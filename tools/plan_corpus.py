"""Plan a fixed corpus of jobs and save or compare every plan: the regression check for work on the planner
that must not change what it plans (a faster kernel, a refactoring).

    .venv/bin/python tools/plan_corpus.py save /tmp/before.pkl      # on the commit before the change
    .venv/bin/python tools/plan_corpus.py compare /tmp/before.pkl   # after it: "0 of 208 plans differ"

The corpus: every example job of configs/jobs/, the benchmark's 20-waypoint path and `--per-kind` random
jobs of each kind of benchmarks/bench_planner.py (paths, sharp-corner paths, moves, timed, pvt; fixed
seeds), on configs/demo.toml. A plan is the same when its segment times, positions and velocities are
equal to the bit (a refused job: the same error code). Prints the CPU time of the planning too.
"""

from __future__ import annotations

import argparse
import pickle
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.bench_planner import KINDS, benchmark_path, example_jobs, random_job  # noqa: E402
from planner.config import load_cell  # noqa: E402
from planner.errors import PlanningError  # noqa: E402
from planner.job import job_from_dict, with_jerk_limited  # noqa: E402
from planner.plan import plan_job, warm_up  # noqa: E402


def plan_all(per_kind: int, jerk_limited: bool | None = None) -> tuple[dict[str, Any], float]:
    """Plan the corpus; `jerk_limited` forces the path jobs' field (None: the jobs' own, or the default)."""
    cell = load_cell(ROOT / "configs" / "demo.toml")
    jobs = example_jobs(cell, jerk_limited)
    jobs.append(("bench-20", benchmark_path(cell, jerk_limited=jerk_limited)))
    for k, kind in enumerate(KINDS):
        rng = np.random.default_rng(1000 + k)
        jobs += [(f"{kind}-{i}", job_from_dict(with_jerk_limited(random_job(kind, rng, cell), jerk_limited), cell))
                 for i in range(per_kind)]
    plans: dict[str, Any] = {}
    cpu = 0.0
    for name, job in jobs:
        t0 = time.thread_time()
        try:
            traj = plan_job(job, cell)
            plans[name] = (traj.dt_ms, traj.positions, traj.velocities, traj.plan.positions)
        except PlanningError as e:
            plans[name] = ("error", e.code, e.message)
        cpu += time.thread_time() - t0
    return plans, cpu


def differences(before: dict[str, Any], after: dict[str, Any]) -> list[str]:
    out = []
    for name, new in after.items():
        old = before.get(name)
        if old is None:
            out.append(f"{name}: not in the saved corpus")
        elif isinstance(old[0], str) or isinstance(new[0], str):
            if not (isinstance(old[0], str) and isinstance(new[0], str) and old[1] == new[1]):
                out.append(f"{name}: {old[:2]} -> {new[:2]}")
        elif not all(a.shape == b.shape and np.array_equal(a, b) for a, b in zip(old[:3], new[:3], strict=True)):
            dev = float(np.abs(old[3] - new[3]).max()) if old[3].shape == new[3].shape else float("inf")
            out.append(f"{name}: points {old[0].size + 1} -> {new[0].size + 1}, duration {old[0].sum()} -> "
                       f"{new[0].sum()} ms, plan moved by up to {dev:.3g} counts")
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("action", choices=("save", "compare"))
    parser.add_argument("file", type=Path)
    parser.add_argument("--per-kind", type=int, default=40, help="random jobs per kind (default 40)")
    parser.add_argument("--jerk-limited", choices=("job", "true", "false"), default="job",
                        help="the path jobs' jerk_limited: as the job has it (default), or forced true/false")
    args = parser.parse_args(argv)
    warm_up()
    forced = None if args.jerk_limited == "job" else args.jerk_limited == "true"
    plans, cpu = plan_all(args.per_kind, forced)
    print(f"{len(plans)} jobs planned in {cpu:.2f} s of CPU")
    if args.action == "save":
        args.file.write_bytes(pickle.dumps(plans))
        return 0
    diff = differences(pickle.loads(args.file.read_bytes()), plans)
    for line in diff:
        print("differs:", line)
    print(f"{len(diff)} of {len(plans)} plans differ")
    return 1 if diff else 0


if __name__ == "__main__":
    sys.exit(main())
