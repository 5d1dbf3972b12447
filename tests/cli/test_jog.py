"""`pvt jog AXIS +|- [--speed V] [--for S]` (issue 14, section 2): a velocity move of one axis while the
command runs (until Ctrl-C or `--for`), then a stop; run as a subprocess at 80 columns against a served cell
with simulated drives (the real backend, real time)."""

from __future__ import annotations

import signal
import time
from collections.abc import Callable, Iterator

import pytest

from planner.config import CellConfig
from tests.api.conftest import Served
from tests.cli.conftest import assert_fits, flat, pvt, start_pvt

Serve = Callable[..., Served]


@pytest.fixture
def real(serve: Serve, demo_cell: CellConfig) -> Iterator[Served]:
    from streamer.runtime.bus_backend import RuntimeBackend

    backend = RuntimeBackend(demo_cell.with_axes(3), sim=True)
    try:
        served = serve(backend=backend)
    except BaseException:
        backend.close()
        raise
    try:
        yield served
    finally:
        served.service.close()
        backend.close()


def position(served: Served, axis: str) -> float:
    return float(served.backend.current_positions()[axis])  # type: ignore[attr-defined]


def test_jog_for_seconds_moves_the_axis_its_way_then_stops_and_leaves_the_queue_open(real: Served) -> None:
    before = position(real, "j2")
    t0 = time.monotonic()
    out = pvt("jog", "j2", "-", "--speed", "0.2", "--for", "2.5", "--connect", real.endpoint)
    ran_s = time.monotonic() - t0
    assert out.returncode == 0, out.stderr
    assert_fits(out.stdout)
    said = flat(out.stdout)
    assert "jogging j2 at -0.2 rad/s" in said and "stops after 2.5 s" in said and "j2 stopped at" in said
    moved = position(real, "j2") - before
    # at least the 2.5 s the command waits once it sees the jog running (less the ramp), and no more than the
    # command's whole run at 0.2: its --for is timed by the command, so a loaded machine (the halt's query late)
    # stretches the motion, never past the command's own wall time (it waits until the jog has ended)
    assert -0.2 * ran_s < moved < -0.2 * 2.5 * 0.9, (moved, ran_s)
    time.sleep(0.3)
    assert position(real, "j2") - before == moved  # at rest
    with real.client() as client:
        status = client.service_status()
        assert status["held"] is False and status["running_job"] is None  # a jog does not hold the queue


def test_jog_until_interrupted_stops_on_ctrl_c(real: Served) -> None:
    before = position(real, "j1")
    # toward the farther software limit: the other tests of this module leave j1 anywhere, and near a limit the jog
    # would stop there before a Ctrl-C sent on a loaded machine arrives
    way, sign = ("-", -1.0) if before > 0.0 else ("+", 1.0)
    proc = start_pvt("jog", "j1", way, "--connect", real.endpoint)  # default speed: 10 % of the limit
    try:
        deadline = time.monotonic() + 30
        while sign * (position(real, "j1") - before) < 0.05 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert sign * (position(real, "j1") - before) >= 0.05, "the jog did not move the axis"
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, stderr
    assert_fits(stdout)
    said = flat(stdout)
    assert f"jogging j1 at {way}0.2 rad/s" in said and "Ctrl-C stops it" in said and "interrupted: stopped" in said
    here = position(real, "j1")
    time.sleep(0.3)
    assert position(real, "j1") == here and sign * (here - before) > 0.0


def test_jog_refusals_and_help(real: Served) -> None:
    out = pvt("jog", "j9", "+", "--connect", real.endpoint)
    assert out.returncode == 2 and "has no axis 'j9'" in flat(out.stderr) and "j1, j2, j3" in flat(out.stderr)
    out = pvt("jog", "j1", "+", "--speed", "-1", "--connect", real.endpoint)
    assert out.returncode == 2 and "--speed must be a positive" in flat(out.stderr)
    out = pvt("jog", "j1", "+", "--speed", "50", "--for", "1", "--connect", real.endpoint)  # over the limit
    assert out.returncode == 2 and "velocity" in flat(out.stderr), out.stderr
    out = pvt("jog", "j1", "up", "--connect", real.endpoint)
    assert out.returncode == 2 and "invalid choice" in flat(out.stderr)
    out = pvt("jog", "--help")
    assert out.returncode == 0
    assert_fits(out.stdout)
    assert "--speed V" in out.stdout and "--for S" in out.stdout
    out = pvt("jog", "j1", "+", "--connect", "tcp/127.0.0.1:9", "--connect-timeout", "1")
    assert out.returncode == 5, (out.returncode, out.stderr)


def test_ctrl_c_while_jogging_sets_a_flag_instead_of_raising() -> None:
    """While a jog polls its job, SIGINT only sets a flag (seen at the next poll), so that no KeyboardInterrupt can
    be lost inside the Zenoh binding's wait (CI: a jog ran on to its software limit after a Ctrl-C); the handler
    before it is back afterwards."""
    import os

    from streamer.cli.jog import _interrupt_flag

    before = signal.getsignal(signal.SIGINT)
    with _interrupt_flag() as ctrl_c:
        assert not ctrl_c.is_set()
        os.kill(os.getpid(), signal.SIGINT)
        assert ctrl_c.wait(2.0)  # no KeyboardInterrupt raised here
    assert signal.getsignal(signal.SIGINT) is before
