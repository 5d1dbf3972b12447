"""`pvt sim` (streamer/cli/sim.py) and the simulator benchmark's scenario runner."""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import threading
from dataclasses import replace
from pathlib import Path

import canopen
import pytest
from bus_testkit import remote_network, unique_channel, wait_until

from benchmarks import bench_sim
from bus.sim.eds import EDS_PATH
from planner.config import BusConfig, load_cell
from planner.errors import PlanningError
from streamer.cli import sim as cli_sim

DEMO = Path(__file__).resolve().parents[2] / "configs" / "demo.toml"


def parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="pvt")
    cli_sim.add_parser(parser.add_subparsers(dest="command"))
    return parser.parse_args(["sim", *argv])


def test_bus_spec() -> None:
    base = BusConfig()
    assert base.with_spec("socketcan:vcan0", 500_000) == BusConfig("socketcan", "vcan0", 500_000)
    assert base.with_spec("pcan:PCAN_USBBUS1:x").channel == "PCAN_USBBUS1:x"
    assert base.with_spec(None, 250_000) == BusConfig(base.interface, base.channel, 250_000)
    for bad in ("vcan0", ":x", "socketcan:"):
        with pytest.raises(PlanningError) as e:
            base.with_spec(bad)
        assert e.value.code == "CONFIG" and e.value.path == "bus"
    with pytest.raises(PlanningError, match="udp_multicast"):
        base.with_spec("udp_multicast:239.0.0.1")


def test_pvt_sim_serves_the_cell_until_stopped(capsys: pytest.CaptureFixture[str]) -> None:
    channel = unique_channel("cli-sim")
    args = parse(["--config", str(DEMO), "--bus", f"virtual:{channel}", "--bitrate", "500000"])
    assert args.func is cli_sim.run
    stop = threading.Event()
    result: list[int] = []
    thread = threading.Thread(target=lambda: result.append(cli_sim.run(args, stop)))
    thread.start()
    try:
        with remote_network(channel) as net:
            node = net.add_node(6, str(EDS_PATH))
            assert wait_until(lambda: _answers(node), 2.0)
            assert node.sdo[0x6041].raw & 0x4F == 0x40
    finally:
        stop.set()
        thread.join(timeout=5.0)
    assert result == [0]
    out = capsys.readouterr().out
    assert "6 drives" in out and "stopped" in out


def _answers(node: canopen.RemoteNode) -> bool:
    """The drives answer SDO once `pvt sim` has started them (until then the request times out)."""
    try:
        return bool(node.sdo[0x1000].raw == 0x00020192)
    except canopen.SdoCommunicationError:
        return False


def test_pvt_sim_rejects_a_bad_config(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[cell]\nname = 'x'\n", encoding="utf-8")
    assert cli_sim.run(parse(["--config", str(bad)])) == 2
    assert "pvt sim:" in capsys.readouterr().err
    # a forbidden interface is a configuration error, refused before any bus is opened
    assert cli_sim.run(parse(["--config", str(DEMO), "--bus", "udp_multicast:x", "--duration", "0"])) == 2


def test_benchmark_scenario_runs_a_short_stream() -> None:
    demo = load_cell(DEMO)
    out = bench_sim.run(replace(demo.with_axes(2), sync_period_ms=5), 0.3)
    assert out["ticks"] == 2 * 300 and out["ratio"] > 0


def test_pvt_sim_stops_when_its_standard_input_closes() -> None:
    """`--stop-on-stdin-eof`: the drives leave the bus when the pipe they read closes."""
    stdin_r, stdin_w = os.pipe()
    args = parse(["--config", str(DEMO), "--bus", f"virtual:{unique_channel('cli-sim-eof')}", "--stop-on-stdin-eof"])
    stop = threading.Event()
    result: list[int] = []
    with os.fdopen(stdin_r, "rb") as stream:
        saved, sys.stdin = sys.stdin, stream  # type: ignore[assignment]
        try:
            thread = threading.Thread(target=lambda: result.append(cli_sim.run(args, stop)))
            thread.start()
            assert not stop.wait(1.0)  # the pipe is open: the drives stay
            os.close(stdin_w)
            thread.join(timeout=20)
        finally:
            sys.stdin = saved
            stop.set()
    assert not thread.is_alive() and result == [0]


def _gone(pid: int) -> bool:
    """True once `pid` has exited (a zombie waiting for its reaper counts: it is off the bus)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] == "Z"
    except FileNotFoundError:
        return True


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")
def test_the_demo_drive_process_leaves_the_bus_when_the_demo_is_killed(tmp_path: Path) -> None:
    """`pvt demo` killed with SIGKILL cannot stop its drive process; the child's standard input, a pipe
    from the demo, closes with it, and the drives leave the bus instead of answering the next master."""
    script = tmp_path / "killed_demo.py"
    script.write_text(
        "import os, signal\n"
        "from planner.config import load_cell\n"
        "from bus.sim.process import drives_process, joining_bus\n"
        f"cell = joining_bus(load_cell({str(DEMO)!r}))\n"
        "with drives_process(cell) as procs:\n"
        "    print(procs[0].pid, flush=True)\n"
        "    os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    parent = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120,
                            cwd=DEMO.parents[1])
    assert parent.returncode == -signal.SIGKILL, parent.stderr
    child = int(parent.stdout.split()[0])
    try:
        assert wait_until(lambda: _gone(child), timeout_s=20)
    finally:
        if not _gone(child):
            os.kill(child, signal.SIGKILL)
