"""The Zenoh key space of one cell; every key the service and the client use is built here.

    pvt/<cell>/submit                  get (payload: msgpack job) -> accepted reply | error reply
                                       put (payload: msgpack job with job_id) -> outcome on the events key
    pvt/<cell>/rejected                publications: every rejected put
    pvt/<cell>/jobs                    get -> list of job statuses (parameters: state, limit)
    pvt/<cell>/jobs/<job_id>           get -> status of one job
    pvt/<cell>/jobs/<job_id>/events    publications: the job's events; get -> the journalled history
    pvt/<cell>/jobs/<job_id>/cancel    get -> cancel the job
    pvt/<cell>/service                 get -> service status (ready, queue, running job)
    pvt/<cell>/reset                   get -> reset a faulted cell
    pvt/<cell>/telemetry               publications: per-axis telemetry at telemetry_hz
    pvt/<cell>/alive                   liveliness token of the service

docs/api.md is the public description of the same table; a test checks that they agree.
"""

from __future__ import annotations

import re

PREFIX = "pvt"

# A cell name or job id is one key chunk: no '/', no wildcard or reserved characters.
_CHUNK = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")
_CELL = re.compile(r"^[A-Za-z0-9_\-][A-Za-z0-9_.\-]{0,63}$")


def valid_job_id(job_id: str) -> bool:
    """1-64 characters from [A-Za-z0-9_.-]: safe as one Zenoh key chunk."""
    return bool(_CHUNK.match(job_id)) and job_id not in (".", "..")


def check_cell(cell: str) -> str:
    if not isinstance(cell, str) or not _CELL.match(cell):
        raise ValueError(f"cell name {cell!r} is not a valid key chunk (1-64 of [A-Za-z0-9_.-])")
    return cell


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
