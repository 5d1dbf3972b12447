"""Job recordings: every job to MCAP (mcap_io), exports to CSV and an interactive HTML report
(export, html), and the service's per-job files with retention (files). See docs/recording.md."""

from streamer.recording.model import (
    AxisInfo,
    AxisSamples,
    Frames,
    JobRecording,
    RecordedEvent,
    RecordingError,
    build_recording,
)

__all__ = [
    "AxisInfo",
    "AxisSamples",
    "Frames",
    "JobRecording",
    "RecordedEvent",
    "RecordingError",
    "build_recording",
]
