"""Client churn: while a job runs, 2 clients connect and disconnect every 100 ms; a stable events
subscriber still receives every event of the job, in order (issue 7, scenario 13; bounded here to a
3 s job, set PVT_CHURN_S for the long version)."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable

from streamer.api import keys
from streamer.api.client import MotionClient
from streamer.api.errors import MotionError
from streamer.api.service import ServiceOptions
from tests.api.conftest import Served
from tests.api.fakes import timed_job
from tests.api.helpers import Collector, raw_session

CHURN_S = float(os.environ.get("PVT_CHURN_S", "3"))


def test_client_churn_does_not_disturb_a_stable_subscriber(serve: Callable[..., Served]) -> None:
    served = serve(options=ServiceOptions(progress_hz=50.0))
    stable = raw_session(served.endpoint)
    stop = threading.Event()
    cycles = [0, 0]
    errors: list[BaseException] = []

    def churn(slot: int) -> None:
        while not stop.is_set():
            t0 = time.monotonic()
            try:
                with MotionClient(connect=served.endpoint, cell="demo", timeout=5) as c:
                    c.service_status()
                    sub = c.job(job_id).events  # declares a subscriber on the same events key
                    del sub
                cycles[slot] += 1
            except MotionError as exc:
                errors.append(exc)
            stop.wait(max(0.0, 0.1 - (time.monotonic() - t0)))

    job_id = "churned"
    try:
        events = Collector(stable, keys.job_events("demo", job_id))
        with served.client() as client:
            client.wait_for_service(timeout=5)
            threads = [threading.Thread(target=churn, args=(i,)) for i in range(2)]
            for t in threads:
                t.start()
            time.sleep(0.3)
            job = client.submit(timed_job(CHURN_S, name="churned"), job_id=job_id)
            events.until(lambda m: m["type"] in ("done", "failed", "cancelled"), timeout=CHURN_S + 20)
            stop.set()
            for t in threads:
                t.join(timeout=10)
            assert job.wait(timeout=5).state.value == "done"
        seqs = [m["seq"] for m in events.all]
        assert seqs == list(range(1, len(seqs) + 1)), seqs
        types = [m["type"] for m in events.all]
        assert types[:4] == ["accepted", "planned", "priming", "running"] and types[-1] == "done"
        assert len(types) >= CHURN_S * 20  # progress at up to 50 Hz: plenty of events to lose
        assert errors == []
        assert min(cycles) >= CHURN_S * 5, cycles  # each churn client really cycled (~10/s)
        events.close()
    finally:
        stop.set()
        stable.close()
