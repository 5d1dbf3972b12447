"""Scenario 13: Zenoh client churn on the real runtime: while a 10 s job runs on the simulated drives
(the real runtime backend, `--sim`: 3 axes on python-can's virtual bus, real time), 2 clients connect
and disconnect every 100 ms; a stable events subscriber receives every event of the job, in order.

(tests/api/test_churn.py runs the same churn for 3 s against the fake backend; PVT_CHURN_S changes
this test's job length.)"""

from __future__ import annotations

import dataclasses
import os
import threading
import time
from collections.abc import Callable

import pytest
from reliability_kit import cell3

from streamer.api import keys
from streamer.api.client import MotionClient
from streamer.api.errors import MotionError
from streamer.api.service import ServiceOptions
from streamer.runtime.bus_backend import RuntimeBackend
from tests.api.conftest import Served, serve  # noqa: F401  (the fixture)
from tests.api.helpers import Collector, raw_session

CHURN_S = float(os.environ.get("PVT_CHURN_S", "10"))


@pytest.mark.slow
@pytest.mark.wallclock  # a real job with clients coming and going
def test_client_churn_during_a_real_job_loses_no_event(serve: Callable[..., Served]) -> None:  # noqa: F811
    cell = dataclasses.replace(cell3(), bus=dataclasses.replace(cell3().bus, channel=f"rel-churn-{os.getpid()}"))
    backend = RuntimeBackend(cell, sim=True)
    try:
        served = serve(backend=backend, options=ServiceOptions(progress_hz=50.0))
        stable = raw_session(served.endpoint)
        stop = threading.Event()
        cycles = [0, 0]
        errors: list[BaseException] = []
        job_id = "churned-real"

        def churn(slot: int) -> None:
            while not stop.is_set():
                t0 = time.monotonic()
                try:
                    with MotionClient(connect=served.endpoint, cell=cell.name, timeout=5) as c:
                        c.service_status()
                        sub = c.job(job_id).events  # a subscriber on the same events key, then gone
                        del sub
                    cycles[slot] += 1
                except MotionError as exc:
                    errors.append(exc)
                stop.wait(max(0.0, 0.1 - (time.monotonic() - t0)))

        events = Collector(stable, keys.job_events(cell.name, job_id))
        threads = [threading.Thread(target=churn, args=(i,)) for i in range(2)]
        try:
            with served.client() as client:
                client.wait_for_service(timeout=10)
                for t in threads:
                    t.start()
                time.sleep(0.3)
                half = CHURN_S / 2
                job = client.submit({"kind": "timed", "axes": ["j1", "j2", "j3"], "times": [0.0, half, CHURN_S],
                                     "positions": [[0.0, 0.0, 0.0], [0.4, 0.3, -0.3], [0.0, 0.0, 0.0]]},
                                    job_id=job_id)
                events.until(lambda m: m["type"] in ("done", "failed", "cancelled"), timeout=CHURN_S + 30)
                stop.set()
                for t in threads:
                    t.join(timeout=10)
                status = job.wait(timeout=10)
                assert status.state.value == "done", status
        finally:
            stop.set()
            events.close()
            stable.close()
        seqs = [m["seq"] for m in events.all]
        assert seqs == list(range(1, len(seqs) + 1)), seqs
        types = [m["type"] for m in events.all]
        assert types[:4] == ["accepted", "planned", "priming", "running"] and types[-1] == "done", types
        assert len(types) >= 100  # the runtime backend reports progress in 1% steps: ~100 events to lose
        assert errors == []
        assert min(cycles) >= CHURN_S * 5, cycles  # each churn client really cycled (~10/s)
        report = status.report
        assert report is not None and report["result"] == "done", report
        assert all(a["max_deviation_counts"] <= 1 for a in report["axes"]), report["axes"]
        print(f"[scenario 13] {len(types)} events in order during a {CHURN_S:.0f} s job; churn cycles {cycles}")
    finally:
        backend.close()
