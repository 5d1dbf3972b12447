"""`pvt plan JOB --config CELL [--out pvt.csv] [--plot pvt.png] [--json]`: plan and encode one job.

Prints the summary (duration, points, deviation per axis in counts, peaks against the limits) and how the
motion follows its geometry (blends and exact stops, spline, along the line or not); `--out` writes the
PVT points as CSV (docs/formats.md, section 4), `--plot` the per-axis curves, `--json` the summary. A
rejected job prints its code, path and message (status 2). A home job prints what the drives will do.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "plan",
        help="plan a job and encode it as PVT points (no bus needed)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("job", type=Path, help="job file (TOML or JSON)")
    p.add_argument("--config", type=Path, default=None, help="cell config TOML (default: configs/demo.toml)")
    p.add_argument("--out", type=Path, default=None, help="write the PVT points as CSV")
    p.add_argument(
        "--plot",
        type=Path,
        default=None,
        help="write a PNG with position/velocity/acceleration/deviation per axis",
    )
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from planner.config import default_config_path, load_cell
    from planner.errors import PlanningError
    from planner.job import load_job
    from planner.plan import plan_job, warm_up

    try:
        cell = load_cell(args.config or default_config_path())
        job = load_job(args.job, cell)
        if job.kind == "home":  # nothing to plan: say what the drives will do
            return home_summary(args, job, cell)
        warm_up()  # the solvers' first import (~0.7 s) is not planning: `planned in` is what a service takes
        t0 = time.perf_counter()
        traj = plan_job(job, cell)
        planning_s = time.perf_counter() - t0
    except PlanningError as e:
        if args.json:
            print(json.dumps({"error": e.to_dict()}, indent=2))
        else:
            print(f"error {e.code}" + (f" at {e.path}" if e.path else "") + f": {e.message}", file=sys.stderr)
        return 2
    summary = traj.summary()
    summary["geometry"] = geometry_note(job, traj.info)
    summary["job"] = str(args.job)
    summary["cell"] = cell.name
    summary["planning_ms"] = round(planning_s * 1000.0, 3)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(traj.to_csv(), encoding="utf-8")
        summary["csv"] = str(args.out)
    units = [cell.axis(name).unit for name in traj.axis_names]
    if args.plot is not None:
        plot(traj, args.plot, title=f"{args.job.name} on {cell.name}", units=units)
        summary["plot"] = str(args.plot)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        _print_table(summary, units)
    return 0


def home_summary(args: argparse.Namespace, job: Any, cell: Any) -> int:
    """A home job plans nothing (the drives search their home positions in homing mode): print what it will do,
    per axis the method, speeds, acceleration and home position; exit 0. `--out`/`--plot` have no PVT points to
    write: refused, exit 2."""
    from rich.console import Console
    from rich.text import Text

    from streamer.cli.tables import Col, fit_table, number
    from streamer.runtime.homing import method_note

    if args.out is not None or args.plot is not None:
        print(f"error SCHEMA at kind: {args.job} is a home job: it plans no PVT points, so there is nothing to "
              "write with --out or draw with --plot; `pvt plan` without them shows what it will do", file=sys.stderr)
        return 2
    d = job.data
    axes = [cell.axis(name) for name in job.axes]
    summary: dict[str, Any] = {
        "kind": "home", "job": str(args.job), "cell": cell.name, "timeout_s": d.timeout_s, "planned": False,
        "note": "nothing is planned: the master switches the drives to homing mode (6), starts all of them at "
                "once, waits for homing attained or a homing error (up to timeout_s), then returns them to their "
                "streaming mode; each axis then stands at its home position",
        "axes": [{"name": a.name, "node_id": a.node_id, "profile": a.profile, "unit": a.unit, "method": d.method[j],
                  "method_note": method_note(d.method[j]), "search_speed": d.search_speed[j],
                  "zero_speed": d.zero_speed[j], "acceleration": d.acceleration[j], "home_position": d.offset[j]}
                 for j, a in enumerate(axes)],
    }
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    console = Console()
    console.print(Text(f"home job on cell {cell.name}: {len(axes)} axis(es), homing mode (6), at most "
                       f"{d.timeout_s:g} s (timeout_s)"))
    console.print(Text(f"job file {args.job}"))
    console.print(Text(summary["note"]))
    units = {a.unit for a in axes}
    same = units.pop() if len(units) == 1 else None

    def short(x: float, unit: str) -> str:  # 0.2, not 0.2000; the unit after the value when the axes differ
        text = number(x)
        text = text.rstrip("0").rstrip(".") if "." in text else text
        return text + (f" {unit}" if same is None else "")

    u = f" [{same}/s]" if same else ""
    columns = [Col("axis"), Col("node", justify="right", drop=1), Col("method", justify="right"),
               Col(f"search{u}", justify="right"), Col(f"zero{u}", justify="right"),
               Col(f"acceleration [{same}/s²]" if same else "acceleration", justify="right"),
               Col(f"home position [{same}]" if same else "home position", justify="right")]
    rows = [[r["name"], str(r["node_id"]), str(r["method"]), short(r["search_speed"], f"{r['unit']}/s"),
             short(r["zero_speed"], f"{r['unit']}/s"), short(r["acceleration"], f"{r['unit']}/s²"),
             short(r["home_position"], r["unit"])] for r in summary["axes"]]
    console.print(fit_table(columns, rows, console.width), highlight=False)
    for m in sorted({r["method"] for r in summary["axes"]}):
        names = ", ".join(r["name"] for r in summary["axes"] if r["method"] == m)
        console.print(Text(f"method {m} ({names}): {method_note(m)}"))
    return 0


def geometry_note(job: Any, info: dict[str, float]) -> str:
    """One sentence on how the planned motion follows the job's geometry (path and move jobs)."""
    from planner.job import MoveData, PathData

    d = job.data
    if isinstance(d, PathData):
        if d.geometry == "spline":
            pchip = " (one axis: the shape-preserving cubic, the spline left the limits)"
            return "through the waypoints on a cubic spline" + (pchip if "path_shape_pchip" in info else "")
        if "blended_corners" not in info:
            return "a straight move (the path spans less than a count)"
        return (f"along the straight segments: {int(info['blended_corners'])} corner(s) blended within "
                f"path_tolerance, {int(info.get('exact_stops', 0))} exact stop(s)")
    if isinstance(d, MoveData) and d.mode == "velocity":  # planner/motion/travel.py: no line, a ramp and a cruise
        if info.get("position_limit_stop", 0.0) == 1.0:
            return "endless travel: a ramp to the velocities, then it stops before the software position limits"
        return ("endless travel: a ramp to the velocities, then cruising (the first chunk of an open-ended plan; "
                "the service extends it while it runs)")
    if isinstance(d, MoveData):
        if info.get("straight_line", 0.0) == 1.0:
            return (f"along the straight line from start to target (the drive within "
                    f"{info.get('line_deviation_counts', 0.0):.1f} counts of it)")
        return (f"NOT along the straight line: every axis reaches the target at the same time, but off the "
                f"line by up to {info.get('line_deviation_counts', 0.0):.0f} counts (ruckig could not plan it "
                f"along the line)")
    return ""


def _print_table(s: dict[str, Any], units: list[str]) -> None:
    """The summary at the terminal's width (80 columns too): units in the headers (the axes' `unit` when
    they share one, else after each value), numbers without exponents, no value cut."""
    from rich.console import Console
    from rich.text import Text

    from streamer.cli.tables import Col, fit_table, number

    console = Console()
    seg = s["segment_ms"]
    console.print(Text(f"{s['kind']} job on cell {s['cell']}: {s['duration_s']:.3f} s, {s['points']} points per "
                       f"axis ({s['points_per_second']:.1f} per s)"))
    console.print(Text(f"segments {seg['min']}..{seg['max']} ms (mean {seg['mean']:.1f}), tolerance "
                       f"{s['tolerance_counts']} count(s), planned in {s['planning_ms']:.1f} ms"))
    console.print(Text(f"job file {s['job']}"))
    if s.get("geometry"):
        console.print(Text(f"geometry: {s['geometry']}"))
    info = s.get("info", {})
    if info.get("optimal_s", 0.0) > 0.0:
        how = "jerk-limited" if info.get("jerk_limited", 0.0) == 1.0 else "acceleration-only"
        if "jerk_fastest_runs" in info:  # jerk_timing = "fastest"
            how += (f" (fastest: {info['jerk_fastest_runs']:.0f} of {info.get('runs', 0.0):.0f} run(s) at the "
                    "third-order optimum)")
        console.print(Text(f"{how}: {s['duration_s']:.3f} s = {s['duration_s'] / info['optimal_s']:.3f} x the "
                           f"acceleration-only optimum ({info['optimal_s']:.3f} s)"))
    if info.get("jerk_limited", 0.0) == 1.0:
        # the drive's jerk inside its segments, and its acceleration steps at the knots over the 1 ms tick
        parts = [f"{a['name']} {a['peak_jerk'] / a['jerk_limit']:.2f}/"
                 f"{a['knot_acceleration_step'] * 1000.0 / a['jerk_limit']:.2f}" for a in s["axes"]]
        console.print(Text("drive jerk / limit (in segments / at knots over 1 ms): " + ", ".join(parts)))
    same = units[0] if len(set(units)) == 1 else None
    u = f" [{same}/s]" if same else ""
    u2 = f" [{same}/s²]" if same else ""
    u3 = f" [{same}/s³]" if same else ""
    columns = [
        Col("axis"), Col("node", justify="right", drop=3), Col("max dev [counts]", justify="right"),
        Col(f"velocity{u} peak/limit", justify="right"), Col("rpm peak/0x607F", justify="right", drop=2),
        Col(f"acceleration{u2} plan/drive/limit", justify="right"),
        Col(f"0x60C5{u2}", justify="right", drop=1), Col("acc. excess [% of limit]", justify="right"),
        Col(f"jerk{u3} plan/drive/limit", justify="right", drop=4),
    ]
    rows = []
    for a, unit in zip(s["axes"], units, strict=True):
        tail = "" if same else f" {unit}/s"
        rows.append([
            a["name"],
            str(a["node_id"]),
            str(a["max_deviation_counts"]),
            f"{number(a['peak_velocity'])}/{number(a['velocity_limit'])}{tail}",
            f"{a['peak_velocity_rpm']:.0f}/{a['drive_velocity_limit_rpm']:.0f}",
            f"{number(a['planned_peak_acceleration'])}/{number(a['peak_acceleration'])}/"
            f"{number(a['acceleration_limit'])}{tail + '²' if tail else ''}",
            f"{number(a['drive_acceleration_limit'])}",
            f"{100 * a['acceleration_excess_share']:.1f}",
            f"{number(a['planned_peak_jerk'])}/{number(a['peak_jerk'])}/{number(a['jerk_limit'])}"
            f"{tail + '³' if tail else ''}",
        ])
    console.print(fit_table(columns, rows, console.width), highlight=False)
    for key in ("csv", "plot"):
        if key in s:
            console.print(f"wrote {s[key]}", markup=False, highlight=False)


def plot(traj: Any, path: Path, *, title: str = "", units: list[str] | None = None) -> None:
    """Position, velocity, acceleration and deviation (plan vs drive) per axis, one column per axis;
    `units`: each axis' user unit (the cell's `unit`) for the labels."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    n = traj.n_axes
    m = traj.duration_ms
    t = np.arange(m + 1) / 1000.0
    plan = traj.plan
    _pos, vel, acc = traj.drive_profile()
    dev = traj.deviation()
    cpu = traj.counts_per_unit
    fig, axs = plt.subplots(4, n, figsize=(max(4.0, 3.4 * n), 10), squeeze=False, sharex=True)
    knots = traj.knot_times_s
    for i in range(n):
        c = cpu[i]
        a = axs[0, i]
        a.plot(t, plan.positions[i] / c, lw=1.2, label="plan")
        a.plot(knots, traj.positions[i] / c, ".", ms=3, label="PVT points")
        a.set_title(f"{traj.axis_names[i]} (node {traj.node_ids[i]})")
        a = axs[1, i]
        a.plot(t, plan.velocities[i] * 1000.0 / c, lw=1.2, label="plan")
        a.plot(t, vel[i] * 1000.0 / c, lw=0.8, ls="--", label="drive")
        lim = traj.stats[i].velocity_limit
        a.axhline(lim, color="r", lw=0.6)
        a.axhline(-lim, color="r", lw=0.6)
        a = axs[2, i]
        a.plot(t, plan.acc_right[i] * 1.0e6 / c, lw=1.2, label="plan")
        a.plot(t, acc[i] * 1.0e6 / c, lw=0.6, label="drive")
        alim = traj.stats[i].acceleration_limit
        a.axhline(alim, color="r", lw=0.6)
        a.axhline(-alim, color="r", lw=0.6)
        a = axs[3, i]
        a.plot(t, dev[i], lw=0.8, drawstyle="steps-mid")
        a.axhline(traj.tolerance_counts, color="r", lw=0.6)
        a.axhline(-traj.tolerance_counts, color="r", lw=0.6)
        a.set_xlabel("time [s]")
        unit = units[i] if units is not None and i < len(units) else "rad"
        for row, label in enumerate((f"position [{unit}]", f"velocity [{unit}/s]", f"acceleration [{unit}/s²]",
                                     "deviation [counts]")):
            if i == 0 or (units is not None and unit != units[0]):
                axs[row, i].set_ylabel(label)
    axs[0, 0].legend(fontsize=7)
    axs[1, 0].legend(fontsize=7)
    axs[2, 0].legend(fontsize=7)
    fig.suptitle(
        f"{title}: {traj.duration_s:.3f} s, {traj.n_points} points per axis, drive demand vs planned "
        f"demand within {traj.tolerance_counts} count(s)"
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
