"""The cell's queue and hold policy: the executor thread, the start check, the travel memory.

The executor takes admitted jobs one at a time unless held, emits `priming`, runs `backend.execute` with a
progress emitter and the job's `CancelToken`, has the recording written, and journals the result. A cancel
of the running job and every stop hold the queue until `resume`. A queued job must still start where the
axes stand (`current_positions()`): a move is re-planned, others fail INFEASIBLE unless `start =
"current"`. The travel memory (per axis last target and direction, travel.py's contract) goes to
`backend.plan` and `backend.change`. A recording is written by a worker before the final event.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Mapping
from typing import Any

from streamer.api import errors as E
from streamer.api.backend import Planned
from streamer.api.errors import MotionError, error_from_exception
from streamer.api.journal import Post
from streamer.api.model import EventType
from streamer.api.payload import plain
from streamer.api.progress import Emitter
from streamer.api.service_state import Queued, ServiceState

# every part of the service logs as `streamer.api.service`, the logger it always had (log filters name it)
log = logging.getLogger("streamer.api.service")


class CellQueueMixin(ServiceState):
    """The queue, the hold and the executor of `JobService`."""

    def _travel(self) -> dict[str, Any]:
        """The last commanded target and direction per axis, as keyword arguments of the backend's plan or
        change."""
        with self._cv:
            return {"last_target": dict(self._last_target), "last_direction": dict(self._last_direction)}

    def _remember(self, planned: Planned) -> None:
        """(under the lock) The accepted job's target becomes the axes' last commanded target; a velocity move
        leaves none, and where the queue ends is unknown for its axes until it is stopped."""
        target = planned.commanded_target or planned.end_positions
        for axis, x in target.items():
            self._last_target[axis] = None if x is None else float(x)
            if x is None:
                self._queue_end.pop(axis, None)
        for axis, d in planned.commanded_direction.items():
            if d:
                self._last_direction[axis] = 1 if d > 0 else -1

    # -- executor ----------------------------------------------------------------------------------
    def _executor_loop(self) -> None:
        min_interval = 1.0 / self.options.progress_hz
        while True:
            with self._cv:
                while (not self._pending or self._held) and not self._stopping:
                    self._cv.wait()
                if self._stopping:
                    return
                _, item = self._pending.popitem(last=False)
                self._current = item
            try:
                self._run_one(item, min_interval)
            except Exception:
                log.exception("executor failed on job %s", item.job_id)
            finally:
                with self._cv:
                    self._current = None
                    self._cv.notify_all()

    def _run_one(self, item: Queued, min_interval: float) -> None:
        if item.token.cancelled:
            self._journal.post_final_queued(
                item.job_id, EventType.CANCELLED, None, "cancelled before it started"
            ).wait(60)
            return
        ready, reason = self._ready()
        if not ready:
            self._journal.post_final_queued(
                item.job_id,
                EventType.FAILED,
                E.NOT_READY,
                f"cell {self.cell!r} became not ready before the job started: {reason or 'faulted'}",
            ).wait(60)
            return
        try:
            planned = self._check_start(item)
        except Exception as exc:
            err = error_from_exception(exc)
            if err.code == E.INTERNAL:
                log.exception("checking the start of job %s failed", item.job_id)
            self._journal.post_failed_queued(item.job_id, err).wait(60)
            return
        emitter = Emitter(self._journal, item.job_id, min_interval)
        priming: Post | None = None
        with self._cv:  # `started`, the emitter and the priming event together: a cancel sees all or none
            if not item.token.cancelled:
                item.started = True
                item.emitter = emitter
                priming = self._journal.post(item.job_id, [(EventType.PRIMING, {}, {"started_t": self._clock()})])
        if priming is None:
            self._journal.post_final_queued(
                item.job_id, EventType.CANCELLED, None, "cancelled before it started"
            ).wait(60)
            return
        priming.wait(60)
        try:
            report: Any = self.backend.execute(planned, emitter, item.token)
        except Exception as exc:
            err = error_from_exception(exc)
            if err.code == E.INTERNAL:
                log.exception("backend.execute raised for job %s", item.job_id)
                message = f"backend.execute raised {type(exc).__name__}: {exc}"
            else:  # a coded error (e.g. the backend's own re-plan): an ordinary failure, not a crash
                log.warning("job %s: backend.execute raised %s", item.job_id, err)
                message = err.message
            report = {
                "result": "failed",
                "error": {"code": err.code, "path": err.path, "node": None, "message": message,
                          **({"detail": err.detail} if err.detail else {})},
            }
        finally:
            with self._cv:  # a change may have handed the motion on: the report is the last owner's
                last = item
                while last.replaced_by is not None:
                    last = last.replaced_by
            (last.emitter or emitter).close()
        report = self._record(last.job_id, report)
        etype, data, updates = self._final_from_report(report)
        self._journal.post(last.job_id, [(etype, data, updates)]).wait(60)

    # -- the start of a queued job -------------------------------------------------------------------
    def _positions(self) -> dict[str, float] | None:
        """Where every axis' position demand stands (backend.current_positions()), or None if unknown."""
        try:
            got = self.backend.current_positions()
            if got is None:
                return None
            return {str(k): float(v) for k, v in dict(got).items()}
        except Exception as exc:
            log.warning("backend.current_positions() raised %s: %s", type(exc).__name__, exc)
            return None

    @staticmethod
    def _rows_field(kind: str) -> str:
        return "waypoints" if kind == "path" else "positions"

    def _with_start(self, body: Mapping[str, Any], at: Mapping[str, float]) -> dict[str, Any] | None:
        """A path body that begins where the axes stand (`at`): that position prepended to its waypoints, or
        None when its first waypoint is already there (within half a count on every axis)."""
        axes = body.get("axes")
        rows = body.get("waypoints")
        if not isinstance(axes, list) or not isinstance(rows, list) or not rows or not isinstance(rows[0], list):
            return None
        if any(a not in at for a in axes):
            return None
        here = [float(at[a]) for a in axes]
        cpu = {a.name: a.counts_per_unit for a in self.backend.cell.axes}
        try:
            if all(abs(float(v) - h) * cpu.get(a, 1.0) <= 0.5 for a, v, h in zip(axes, rows[0], here, strict=True)):
                return None
        except (TypeError, ValueError):
            return None
        return {**body, "waypoints": [here, *rows]}

    def _check_start(self, item: Queued) -> Planned:
        """The plan to run: `item.planned` when its start is where the axes stand; else a move re-planned from
        there, a `start = "current"` path re-planned through a waypoint there, anything else INFEASIBLE."""
        here = self._positions()
        planned = item.planned
        if here is None or not planned.start_positions:
            return planned
        cpu = {a.name: a.counts_per_unit for a in self.backend.cell.axes}
        off = [
            (name, here[name], start)
            for name, start in planned.start_positions.items()
            if name in here and abs(here[name] - start) * cpu.get(name, 1.0) > 0.5
        ]
        if not off:
            return planned
        kind = item.kind
        if kind == "move" or (item.start_current and kind == "path"):
            job = planned.job
            if kind == "path":
                moved = self._with_start(item.body, here)
                if moved is not None:
                    job = self.backend.validate(moved)
            replanned = self.backend.plan(job, None, **item.travel)  # from where the axes stand, same last target
            if not isinstance(replanned, Planned):
                raise MotionError(E.INTERNAL, f"backend.plan returned {type(replanned).__name__}, not Planned")
            log.info("job %s re-planned from where the axes stand (%s)", item.job_id,
                     ", ".join(f"{n} at {h:.6g}, planned from {p:.6g}" for n, h, p in off))
            return replanned
        name, at, start = off[0]
        axes = item.body.get("axes")
        j = axes.index(name) if isinstance(axes, list) and name in axes else 0
        unit = next((a.unit for a in self.backend.cell.axes if a.name == name), "")
        field_path = f"{self._rows_field(kind)}[0][{j}]"
        raise MotionError(
            E.INFEASIBLE,
            f"{field_path}: axis {name!r} stands at {at:.6g} {unit} but the job starts at {start:.6g} {unit} "
            "(it was planned from where the jobs before it would end, and the axes stopped elsewhere: a "
            "cancel or a stop); submit it again from here, or give it start = \"current\" to have a path "
            "planned from where the axes stand",
            path=field_path,
            detail={"axis": name, "position": at, "job_start": start,
                    "axes": [{"axis": n, "position": h, "job_start": p} for n, h, p in off]},
        )

    def _record(self, job_id: str, report: Any) -> Any:
        """Write the job's recording (if the backend made one); the report says where, or why not."""
        if self._writer is None:
            return report
        try:
            rec = self.backend.take_recording()
            if rec is None:
                return report
            saved = self._writer.save(job_id, rec, cell=self.cell)
            info: dict[str, Any] = saved.info()
            self.counters["recordings"] += 1
            self.counters["recordings_deleted"] += len(saved.deleted)
        except Exception as exc:
            log.exception("could not write the recording of job %s", job_id)
            info = {"error": f"{type(exc).__name__}: {exc}"[:500]}
        return {**report, "recording": info} if isinstance(report, Mapping) else report

    def _final_from_report(self, report: Any) -> tuple[EventType, dict[str, Any], dict[str, Any]]:
        rep = plain(report) if isinstance(report, Mapping) else {"result": "failed", "raw": plain(report)}
        result = rep.get("result")
        now = self._clock()
        if result == "done":
            return EventType.DONE, {"report": rep}, {"report": rep, "progress": 1.0, "finished_t": now}
        if result == "cancelled":
            return EventType.CANCELLED, {"report": rep}, {"report": rep, "finished_t": now}
        raw_err = rep.get("error")
        if result == "failed" and isinstance(raw_err, Mapping) and isinstance(raw_err.get("code"), str):
            err = {
                **raw_err,  # extras such as `detail` (emcy_code, ...) and `sync` pass through
                "code": raw_err["code"],
                "path": str(raw_err.get("path", "") or ""),
                "node": raw_err.get("node"),
                "message": str(raw_err.get("message", "")),
            }
        elif result == "failed":
            err = {
                "code": E.INTERNAL,
                "path": "",
                "node": None,
                "message": f"backend reported failure without an error code: {raw_err!r}"[:500],
            }
        else:
            err = {
                "code": E.INTERNAL,
                "path": "",
                "node": None,
                "message": f"backend returned result {result!r}, expected done, cancelled or failed"[:500],
            }
        return (
            EventType.FAILED,
            {"error": err, "report": rep},
            {"error": err, "report": rep, "finished_t": now},
        )

    # -- cancel and hold (the control verbs and close() use them) ------------------------------------
    def _cancel_running(self, item: Queued, reason: str, hold: str | None = None) -> bool:
        """Cancel the job the executor holds; True if this request had an effect (the first one does).
        `hold`: also hold the queue, for this reason, in the same step (a job that ends at once must not let
        the executor start the next one before the hold is in place)."""
        with self._cv:
            if item.cancel_requested:
                return False
            item.cancel_requested = True
            if hold is not None and not self._held:
                self._held, self._hold_reason, self._hold_t = True, hold, self._clock()
                log.info("queue of cell %r held: %s", self.cell, hold)
            emitter = item.emitter if item.started else None
        posted = emitter.mark_cancelling(reason) if emitter is not None else None
        if emitter is not None and posted is None:
            return False  # it ended meanwhile
        item.token.cancel()
        if posted is not None:
            with contextlib.suppress(Exception):
                posted.wait(timeout=10.0)  # journalled: the answer's status says `cancelling`
        return True

    def _hold(self, reason: str) -> None:
        with self._cv:
            if not self._held:
                self._held, self._hold_reason, self._hold_t = True, reason, self._clock()
                log.info("queue of cell %r held: %s", self.cell, reason)
            self._cv.notify_all()

