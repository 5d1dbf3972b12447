"""The Zenoh key space of one cell; every key the service and the client use is built here.

    pvt/<cell>/submit                  get (msgpack job) -> reply | error; put (job with job_id) -> events key
    pvt/<cell>/rejected                publications: every rejected put
    pvt/<cell>/jobs                    get -> list of job statuses (parameters: state, limit)
    pvt/<cell>/jobs/<job_id>           get -> status of one job
    pvt/<cell>/jobs/<job_id>/events    publications: the job's events; get -> the journalled history
    pvt/<cell>/jobs/<job_id>/cancel    get -> cancel the job
    pvt/<cell>/service                 get -> service status (ready, held, queue, running job, drives)
    pvt/<cell>/reset                   get -> reset a faulted cell
    pvt/<cell>/stop                    get -> stop all and hold; emergency=true: the emergency stop
    pvt/<cell>/hold                    get -> hold the queue (the running job finishes, no next one starts)
    pvt/<cell>/resume                  get -> release the hold (reset=true: clear a fault first)
    pvt/<cell>/telemetry               publications: per-axis telemetry at telemetry_hz
    pvt/<cell>/alive                   liveliness token of the service

docs/api.md is the public description of the same table; a test checks that they agree.
"""

from __future__ import annotations

from planner.config import check_name, valid_name

PREFIX = "pvt"

# A cell name or job id is one key chunk: the one rule of names (planner.config.NAME_RULE, docs/formats.md
# "Names"), so what a config or a job file accepts is what the key space accepts.


def valid_job_id(job_id: str) -> bool:
    """True when `job_id` follows the rule of names: safe as one Zenoh key chunk."""
    return valid_name(job_id)


def check_cell(cell: str) -> str:
    """`cell` if it is a valid cell name; else PlanningError (a ValueError) CONFIG saying why."""
    return check_name(cell, "cell name", path="cell", code="CONFIG")


def base(cell: str) -> str:
    return f"{PREFIX}/{check_cell(cell)}"


def submit(cell: str) -> str:
    return f"{base(cell)}/submit"


def rejected(cell: str) -> str:
    return f"{base(cell)}/rejected"


def jobs(cell: str) -> str:
    return f"{base(cell)}/jobs"


def job(cell: str, job_id: str) -> str:
    return f"{base(cell)}/jobs/{job_id}"


def job_events(cell: str, job_id: str) -> str:
    return f"{base(cell)}/jobs/{job_id}/events"


def job_cancel(cell: str, job_id: str) -> str:
    return f"{base(cell)}/jobs/{job_id}/cancel"


def service(cell: str) -> str:
    return f"{base(cell)}/service"


def reset(cell: str) -> str:
    return f"{base(cell)}/reset"


def stop(cell: str) -> str:
    return f"{base(cell)}/stop"


def hold(cell: str) -> str:
    return f"{base(cell)}/hold"


def halt(cell: str) -> str:
    return f"{base(cell)}/halt"


def resume(cell: str) -> str:
    return f"{base(cell)}/resume"


def telemetry(cell: str) -> str:
    return f"{base(cell)}/telemetry"


def alive(cell: str) -> str:
    return f"{base(cell)}/alive"


# Wildcard forms the service declares its queryables on.
def job_any(cell: str) -> str:
    return f"{base(cell)}/jobs/*"


def job_events_any(cell: str) -> str:
    return f"{base(cell)}/jobs/*/events"


def job_cancel_any(cell: str) -> str:
    return f"{base(cell)}/jobs/*/cancel"


def alive_any() -> str:
    """Every service's liveliness token (all cells)."""
    return f"{PREFIX}/*/alive"


def job_id_from_key(key: str, cell: str) -> str | None:
    """The job id chunk of `pvt/<cell>/jobs/<job_id>[/...]`, or None if the key is not concrete."""
    prefix = f"{base(cell)}/jobs/"
    if not key.startswith(prefix):
        return None
    chunk = key[len(prefix) :].split("/", 1)[0]
    return chunk if valid_job_id(chunk) else None
