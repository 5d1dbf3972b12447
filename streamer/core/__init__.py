"""The streamer core: pure state machines (no I/O, no clock) that stream PVT records to drive FIFOs.

A runtime creates one `Coordinator(plan, settings, stop_planner)` per job and feeds it `bus.events`;
each `handle(event)` returns the frames to send and the job's state changes. See coordinator.py for
the life cycle, the contract with the runtime and its parts (job_core, sending, splices, open_stream,
feedback, scheduling), axis_state.py for the two axis kinds' states and tables, fifo_fifo_feeder.py and cyclic_feeder.py
for each kind (the FIFO accounting and loss repair; one set point per SYNC), schedule.py for the fill
model, bus/budget.py for the frame budget.
"""

from bus.codec import frame_bits
from streamer.core.axis_state import FeederState, InvalidTransition
from streamer.core.coordinator import (
    Coordinator,
    JobReport,
    JobState,
    Reaction,
    StateChange,
    UnexpectedEvent,
)
from streamer.core.fifo_feeder import AxisTelemetry, FifoFeeder
from streamer.core.outcome import FAILURE_CODES, JobOutcome, JobResult
from streamer.core.plan_source import PvtTrajectoryLike, StopPlanner, StopRequest, StreamPlan
from streamer.core.settings import StreamerSettings

__all__ = [
    "FAILURE_CODES",
    "AxisTelemetry",
    "Coordinator",
    "FeederState",
    "FifoFeeder",
    "InvalidTransition",
    "JobOutcome",
    "JobReport",
    "JobResult",
    "JobState",
    "PvtTrajectoryLike",
    "Reaction",
    "StateChange",
    "StopPlanner",
    "StopRequest",
    "StreamPlan",
    "StreamerSettings",
    "UnexpectedEvent",
    "frame_bits",
]
