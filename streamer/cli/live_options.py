"""`--live [PORT]`, shared by `pvt demo` and `pvt serve`: the live channels over Foxglove's WebSocket protocol
(streamer/live/publisher.py), on 127.0.0.1 only."""

from __future__ import annotations

from typing import Any

from streamer.live import DEFAULT_PORT


def add_live_option(p: Any) -> None:
    p.add_argument("--live", nargs="?", type=int, const=DEFAULT_PORT, default=None, metavar="PORT",
                   help=f"publish the channels of the job recording live on ws://127.0.0.1:PORT (Foxglove; "
                        f"default port {DEFAULT_PORT}): docs/recording.md#live-channels")
