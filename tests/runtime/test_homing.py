"""Homing (issue 14): the simulated drives' homing mode per family and method, a homing error, the home job in
virtual time, and `require_homing` (streamer/runtime/homing.py `Referencing`)."""

from __future__ import annotations

import dataclasses
import math

import pytest

from planner.config import HOMING_METHODS, CellConfig, load_cell
from planner.errors import PlanningError
from planner.job import job_from_dict
from planner.plan import plan_job
from streamer.api.errors import MotionError
from streamer.runtime.homing import HOMING_ERROR, NOT_HOMED, Referencing
from streamer.runtime.virtual import VirtualRuntime

INF = math.inf
# family -> a one-axis cell of it
FAMILIES = {"epos-ipm": ("configs/demo.toml", 0), "xtrapuls-ip": ("configs/xtrapuls.toml", 0),
            "cia402-csp": ("configs/demo.toml", 0)}
# method -> (home switch, limit switches, where the home position is in the machine frame)
GEOMETRY = {
    17: (None, (-0.3, 0.4), -0.3),
    18: (None, (-0.3, 0.4), 0.4),
    19: ((0.05, INF), (-0.3, 0.4), 0.05),
    20: ((0.05, INF), (-0.3, 0.4), 0.05),
    21: ((-INF, -0.05), (-0.3, 0.4), -0.05),
    22: ((-INF, -0.05), (-0.3, 0.4), -0.05),
    23: ((0.05, 0.1), (-0.3, 0.4), 0.05),  # the cam met moving positive, left at its negative edge
    27: ((-0.1, -0.05), (-0.3, 0.4), -0.05),  # met moving negative, left at its positive edge
    35: (None, None, 0.0),
    37: (None, None, 0.0),
}


def one_axis(family: str, home: tuple[float, float] | None, limits: tuple[float, float] | None,
             travel: float = 0.0, require_homing: bool = False) -> CellConfig:
    path, k = FAMILIES[family]
    cell = load_cell(path)
    ax = cell.axes[k]
    if family == "cia402-csp":
        ax = dataclasses.replace(ax, profile="cia402-csp")
    sim = dataclasses.replace(ax.sim, home_switch=home, limit_switches=limits, homing_travel=travel)
    return dataclasses.replace(cell, axes=(dataclasses.replace(ax, sim=sim),), require_homing=require_homing)


def home(rt: VirtualRuntime, method: int, offset: float = 0.02, **kw: object) -> dict[str, object]:
    cell = rt.cell
    body = {"kind": "home", "axes": [cell.axes[0].name], "method": method, "offset": offset,
            "search_speed": 0.2, "zero_speed": 0.02, "acceleration": 2.0, "timeout_s": 30.0, **kw}
    return rt.home(job_from_dict(body, cell))


CASES = [(f, m) for f in FAMILIES for m in sorted(HOMING_METHODS[f])]


@pytest.mark.parametrize(("family", "method"), CASES)
def test_each_family_homes_with_each_of_its_methods(family: str, method: int) -> None:
    switch, limits, edge = GEOMETRY[method]
    cell = one_axis(family, switch, limits)
    rt = VirtualRuntime(cell)
    rep = home(rt, method)
    assert rep["result"] == "done", rep
    ax = cell.axes[0]
    m = rt.vcell.models[ax.node_id]
    rt.idle(0.3)  # settle
    assert m.referenced and m.homing_state in ("attained", "idle")
    # the home position is the switch edge of the machine, and the drive now reports 0x607C there
    assert m.machine_position / ax.counts_per_unit == pytest.approx(edge, abs=30 / ax.counts_per_unit)
    assert m.position_actual / ax.counts_per_unit == pytest.approx(0.02, abs=30 / ax.counts_per_unit)
    assert m.mode == m.interpolation_mode and m.ready_for_job  # back in the streaming mode, enabled
    # a move from the home position streams normally afterwards
    job = job_from_dict({"kind": "move", "axes": [ax.name], "target": [0.1], "tolerance_counts": 20}, cell)
    res = rt.run(plan_job(job, cell, start=[m.position_demand / ax.counts_per_unit]))
    assert res.coordinator.state.value == "done"
    assert m.position_actual / ax.counts_per_unit == pytest.approx(0.1, abs=5 / ax.counts_per_unit)


def test_cam_method_reverses_on_the_limit_switch() -> None:
    # method 23 searches positive first; the cam is on the negative side: the positive limit switch turns it
    # round, it crosses the cam and comes back to the cam's negative edge
    cell = one_axis("epos-ipm", (-0.1, -0.05), (-0.3, 0.2))
    rt = VirtualRuntime(cell)
    assert home(rt, 23, offset=0.0)["result"] == "done"
    ax = cell.axes[0]
    m = rt.vcell.models[ax.node_id]
    assert m.machine_position / ax.counts_per_unit == pytest.approx(-0.1, abs=30 / ax.counts_per_unit)


@pytest.mark.parametrize("family", list(FAMILIES))
def test_switch_never_found_is_a_homing_error(family: str) -> None:
    cell = one_axis(family, None, None, travel=0.2)  # no home switch: the search runs out of travel
    rt = VirtualRuntime(cell)
    rep = home(rt, 19)
    assert rep["result"] == "failed"
    err = rep["error"]
    assert isinstance(err, dict) and err["code"] == HOMING_ERROR and cell.axes[0].name in err["message"]
    m = rt.vcell.models[cell.axes[0].node_id]
    assert not m.referenced and "travel" in m.homing_error_reason
    assert m.ready_for_job  # back in the streaming mode after the error


def test_limit_switch_met_by_a_home_switch_method_is_an_error() -> None:
    cell = one_axis("epos-ipm", (0.5, INF), (-0.3, 0.2))  # the switch lies beyond the positive limit
    rep = home(VirtualRuntime(cell), 19)
    assert rep["result"] == "failed" and rep["error"]["code"] == HOMING_ERROR  # type: ignore[index]


def test_statusword_bits_and_reset_unreferences() -> None:
    cell = one_axis("epos-ipm", (0.05, INF), None)
    rt = VirtualRuntime(cell)
    m = rt.vcell.models[cell.axes[0].node_id]
    rt.enable_drives(rt.now)
    m.sdo_write(0x6060, 0, 6)
    m.sdo_write(0x6098, 0, 1)  # a method this drive does not perform: homing error at the start
    m.sdo_write(0x6040, 0, 0x001F)
    assert m.statusword & (1 << 13) and not m.statusword & (1 << 12)
    m.sdo_write(0x6098, 0, 35)
    m.sdo_write(0x6040, 0, 0x000F)
    m.sdo_write(0x6040, 0, 0x001F)
    assert m.statusword & (1 << 12) and not m.statusword & (1 << 13) and m.referenced
    m.sdo_write(0x6040, 0, 0x000F)  # "Bit 12 is reset at 0 ... when bit 4 of the Control Word is at 0"
    assert not m.statusword & (1 << 12) and m.referenced
    m.on_frame(0, bytes((0x81, m.node_id)), rt.now)  # NMT reset node: the drive forgot its reference
    assert not m.referenced


def test_home_job_validation_names_axis_and_value() -> None:
    cell = load_cell("configs/xtrapuls.toml")
    name = cell.axes[0].name
    with pytest.raises(PlanningError) as e:
        job_from_dict({"kind": "home", "axes": [name], "method": 37}, cell)
    assert e.value.code == "SCHEMA" and name in e.value.message and "37" in e.value.message
    with pytest.raises(PlanningError) as e:
        job_from_dict({"kind": "home", "axes": [name], "method": 35, "search_speed": -1.0}, cell)
    assert e.value.code == "LIMITS" and name in e.value.message and "-1" in e.value.message
    with pytest.raises(PlanningError) as e:
        job_from_dict({"kind": "home", "axes": [name], "method": 35, "offset": 1e9}, cell)
    assert e.value.code == "POSITION_LIMIT"


def test_require_homing_refuses_then_accepts_after_homing() -> None:
    cell = one_axis("epos-ipm", (0.05, INF), None, require_homing=True)
    name = cell.axes[0].name
    ref = Referencing(cell)
    move = job_from_dict({"kind": "move", "axes": [name], "target": [0.1]}, cell)
    with pytest.raises(MotionError) as e:
        ref.check(move)
    assert e.value.code == NOT_HOMED and name in e.value.message
    homing = job_from_dict({"kind": "home", "axes": [name], "method": 19}, cell)
    ref.check(homing)  # a home job is never refused
    ref.planned(homing)
    ref.check(move)  # accepted behind the home job that will reference the axis ...
    with pytest.raises(MotionError):
        ref.check(move, at_start=True)  # ... but not run before it
    rt = VirtualRuntime(cell)
    ref.finished(homing, rt.home(homing))
    ref.check(move, at_start=True)
    assert name in ref.referenced
    ref.finished(move, {"result": "failed", "error": {"code": "DRIVE_FAULT", "node": cell.axes[0].node_id}})
    assert name not in ref.referenced  # a drive fault un-references
    ref.finished(homing, rt.home(homing))
    ref.forget([cell.axes[0].node_id])  # a boot-up
    with pytest.raises(MotionError):
        ref.check(move)


def test_example_home_job_runs_on_the_demo_cell() -> None:
    from planner.job import load_job

    cell = load_cell("configs/demo.toml")  # as shipped: j1's simulated drive has a home switch at 0.05 rad
    assert cell.axes[0].sim.home_switch == (0.05, INF)
    rt = VirtualRuntime(cell)
    rep = rt.home(load_job("configs/homing/home-demo.toml", cell))
    assert rep["result"] == "done" and all(r["result"] == "attained" for r in rep["axes"])  # type: ignore[union-attr]
    j1 = rt.vcell.models[cell.axes[0].node_id]
    assert j1.machine_position / cell.axes[0].counts_per_unit == pytest.approx(0.05, abs=1e-3)  # the switch edge
