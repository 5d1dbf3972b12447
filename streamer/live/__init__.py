"""The live view: a running cell's channels over Foxglove's WebSocket protocol (publisher.py). See
docs/recording.md#live-channels. Light on purpose: every `pvt` command line imports it for the default port."""

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765  # the Foxglove app's default
