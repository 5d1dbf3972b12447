"""`pvt probe`: commission the drives of a cell before trusting them (the first step on real hardware).

    pvt probe --config CELL [--bus IF:CH] [--node N ...] [--write]      # the cell's real drives
    pvt probe --config CELL --sim | --fast                               # its simulated drives

Per node: identity (0x1018), every object the product uses, and the readings of the manuals' open points
measured at standstill (bus/probe.py; only a one-count step moves, and the underflow test faults and
resets the drive). `--write` puts them into the cell file as `[axis.probed]` (layout kept). Exit 0 all
measured, 1 a drive no reading explains or lacking an object, 2 bad config or bus.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from planner.config import default_config_path, load_cell
from planner.errors import PlanningError


def add_parser(sub: Any) -> None:
    p = sub.add_parser("probe", help="measure how each drive settles the manuals' open points (commissioning)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", type=Path, default=None, help="cell config TOML (default: configs/demo.toml)")
    p.add_argument("--bus", default=None, help="INTERFACE:CHANNEL, e.g. socketcan:can0 (default: the cell's)")
    p.add_argument("--bitrate", type=int, default=None, help="CAN bitrate (default: the cell's)")
    p.add_argument("--node", type=int, action="append", default=None,
                   help="probe only this node id (repeat for several; default: every axis)")
    p.add_argument("--write", action="store_true", help="write the measured readings into the cell file")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--sim", action="store_true",
                      help="start the cell's simulated drives in this process (real time) and probe them")
    mode.add_argument("--fast", action="store_true",
                      help="probe the cell's simulated drives in virtual time")
    p.set_defaults(func=run)


def _objects_table(rt: Any, nodes: Sequence[int]) -> tuple[dict[int, dict[str, Any]], dict[int, tuple[int, ...]]]:
    from bus.probe import AbsentObject, absent_optional, survey_objects

    profiles = rt.profiles if hasattr(rt, "profiles") else rt.adapter.profiles
    out: dict[int, dict[str, Any]] = {}
    absent: dict[int, tuple[int, ...]] = {}
    for n in nodes:
        profile = profiles[n]
        identity: dict[str, Any] = {}
        for key in ("vendor", "product", "revision", "serial"):
            ref = profile.obj(f"identity_{key}")
            try:
                identity[key] = rt.read_object(n, ref.index, ref.sub)
            except AbsentObject:
                identity[key] = None
        reports = survey_objects(profile, lambda i, s, n=n: rt.read_object(n, i, s))
        out[n] = {"identity": identity, "objects": reports}
        absent[n] = absent_optional(reports)
    return out, absent


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    from bus.errors import BusError
    from bus.probe import ALL_EXPERIMENTS, ProbeError

    console = Console()
    config = args.config or default_config_path()
    try:
        cell = load_cell(config)
        cell = replace(cell, bus=cell.bus.with_spec(args.bus, args.bitrate))
        nodes = args.node or [a.node_id for a in cell.axes]
        unknown = sorted(set(nodes) - {a.node_id for a in cell.axes})
        if unknown:
            raise PlanningError("CONFIG", f"--node {unknown} not in cell {cell.name!r} (nodes "
                                f"{[a.node_id for a in cell.axes]})", path="node")
    except PlanningError as e:
        print(f"pvt probe: {e.code}: {e.message}", file=sys.stderr)
        return 2
    probe_cell = replace(cell, axes=tuple(a for a in cell.axes if a.node_id in nodes))
    try:
        if args.fast:
            from bus.sim.virtual import VirtualCell
            from streamer.runtime.virtual import VirtualRuntime

            vcell = VirtualCell(probe_cell, feedback_every=1)
            rt: Any = VirtualRuntime(probe_cell, vcell=vcell)
            rt.idle(0.05)
            objects, absent = _objects_table(rt, nodes)
            result = rt.probe(ALL_EXPERIMENTS)
        else:
            objects, absent, result = _probe_realtime(probe_cell, nodes, sim=args.sim)
    except (BusError, ProbeError) as e:
        print(f"pvt probe: {getattr(e, 'code', 'PROBE')}: {e}", file=sys.stderr)
        return 2
    return _report(console, cell, config, nodes, objects, absent, result, write=args.write)


def _probe_realtime(cell: Any, nodes: Sequence[int], *, sim: bool) -> tuple[Any, Any, Any]:
    from bus.network import MasterAdapter
    from bus.probe import ALL_EXPERIMENTS
    from bus.sim.node import SimulatedCell
    from streamer.runtime.realtime import RealtimeRuntime

    sim_cell = SimulatedCell(cell).start() if sim else None
    try:
        with MasterAdapter(None, cell) as adapter:
            adapter.configure_drives(feedback_every=1)  # TPDO2 every SYNC while probing
            rt = RealtimeRuntime(cell, adapter)
            try:
                objects, absent = _objects_table(rt, nodes)
                result = rt.probe(ALL_EXPERIMENTS)
            finally:
                rt.close()
    finally:
        if sim_cell is not None:
            sim_cell.stop()
    return objects, absent, result


def _report(console: Any, cell: Any, config: Path, nodes: Sequence[int], objects: dict[int, dict[str, Any]],
            absent: dict[int, tuple[int, ...]], result: Any, *, write: bool) -> int:
    from rich.table import Table

    from planner.readings import OPEN_POINTS

    status = 0
    names = {a.node_id: a.name for a in cell.axes}
    readings = {}
    for n in nodes:
        r = result.nodes[n].readings
        readings[n] = replace(r, absent=absent[n])
        ident = objects[n]["identity"]
        console.print(f"[bold]node {n}[/bold] (axis {names[n]!r}): vendor 0x{ident['vendor'] or 0:08X}, product "
                      f"0x{ident['product'] or 0:08X}, revision 0x{ident['revision'] or 0:08X}, serial "
                      f"{ident['serial']}")
        t = Table(show_header=True, header_style="bold", box=None, pad_edge=False)
        for col in ("object", "index", "present", "value / note"):
            t.add_column(col, overflow="fold")
        for o in objects[n]["objects"]:
            essential_missing = not o.present and o.note.startswith("ESSENTIAL")
            status = 1 if essential_missing else status
            t.add_row(o.name, f"0x{o.index:04X}:{o.sub:02X}", "yes" if o.present else "[red]no[/red]",
                      str(o.value) if o.present and o.value is not None else o.note)
        console.print(t)
        rt = Table(show_header=True, header_style="bold", box=None, pad_edge=False)
        for col in ("open point", "reading"):
            rt.add_column(col, overflow="fold")
        for key in OPEN_POINTS:
            rt.add_row(key, str(getattr(r, key) or "not determined"))
        rt.add_row("tpdo_latency_ms", f"{r.tpdo_latency_ms}")
        console.print(rt)
        for line in result.nodes[n].evidence:
            console.print(f"  [dim]{line}[/dim]", overflow="fold")
        if result.nodes[n].unexplained:
            status = 1
            console.print(f"[red]node {n}: {result.nodes[n].unexplained}[/red]", overflow="fold")
    console.print("\nTOML for the cell (each under its [[axis]]):", markup=False)
    for n in nodes:
        console.print(f"# axis {names[n]!r}\n[axis.probed]", markup=False)
        for key, value in readings[n].to_toml().items():
            console.print(f"{key} = {_toml_value(value)}", markup=False)
    if write and status == 0:
        _write(config, readings)
        console.print(f"wrote [axis.probed] of nodes {list(nodes)} into {config}", markup=False)
    elif write:
        console.print("[red]not written: a drive was not fully explained (see above)[/red]")
    return status


def _toml_value(value: Any) -> str:
    import tomlkit

    return str(tomlkit.item(value).as_string())


def _write(config: Path, readings: dict[int, Any]) -> None:
    """Put `[axis.probed]` of each probed node into the cell file, keeping its comments and layout
    (tomlkit: the only way to edit a user's TOML without rewriting it)."""
    import tomlkit

    doc = tomlkit.parse(Path(config).read_text(encoding="utf-8"))
    for ax in doc.get("axis", []):
        n = ax.get("node_id")
        if n in readings:
            table = tomlkit.table()
            for key, value in readings[n].to_toml().items():
                table[key] = value
            table.add(tomlkit.nl())
            ax["probed"] = table
    Path(config).write_text(tomlkit.dumps(doc), encoding="utf-8")
