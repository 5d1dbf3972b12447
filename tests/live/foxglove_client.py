"""A minimal client of Foxglove's WebSocket protocol (subprotocol `foxglove.sdk.v1`) over a plain socket, for the
tests: RFC 6455 framing (masked client frames, fragmented and control frames), the protocol's JSON ops
(serverInfo, advertise, subscribe) and its binary MessageData (opcode 0x01: subscription id u32, log time u64,
payload). Nothing of it talks to anything but the address it is given (the tests use 127.0.0.1)."""

from __future__ import annotations

import base64
import json
import os
import socket
import struct
import time
from typing import Any

SUBPROTOCOL = "foxglove.sdk.v1"


class FoxgloveClient:
    def __init__(self, host: str, port: int, *, timeout_s: float = 10.0, path: str = "/",
                 subprotocol: str | None = SUBPROTOCOL):
        self.sock = socket.create_connection((host, port), timeout=timeout_s)
        key = base64.b64encode(os.urandom(16)).decode()
        proto = f"Sec-WebSocket-Protocol: {subprotocol}\r\n" if subprotocol else ""
        self.sock.sendall((f"GET {path} HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n"
                           f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                           f"{proto}\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(4096)
            if not chunk:
                raise ConnectionError("closed during the handshake")
            head += chunk
        head, self._buf = head.split(b"\r\n\r\n", 1)
        lines = head.decode().split("\r\n")
        if " 101 " not in lines[0]:
            raise ConnectionError(f"handshake refused: {lines[0]}")
        self.protocol = next((line.split(":", 1)[1].strip() for line in lines
                              if line.lower().startswith("sec-websocket-protocol")), "")
        self.channels: dict[int, dict[str, Any]] = {}  # id -> the advertised channel
        self.server_info: dict[str, Any] = {}
        self._subs: dict[int, int] = {}  # subscription id -> channel id
        self.closed = False

    # ---- framing
    def _read(self, n: int) -> bytes:
        while len(self._buf) < n:
            chunk = self.sock.recv(65536)
            if not chunk:
                raise ConnectionError("closed")
            self._buf += chunk
        out, self._buf = self._buf[:n], self._buf[n:]
        return out

    def send_text(self, text: str) -> None:
        self._send(1, text.encode())

    def _send(self, opcode: int, payload: bytes) -> None:
        mask = os.urandom(4)
        n = len(payload)
        head = bytes([0x80 | opcode])
        if n < 126:
            head += bytes([0x80 | n])
        elif n < 1 << 16:
            head += bytes([0x80 | 126]) + struct.pack(">H", n)
        else:
            head += bytes([0x80 | 127]) + struct.pack(">Q", n)
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload)))

    def recv_frame(self) -> tuple[int, bytes]:
        """The next data message (opcode 1 text or 2 binary, reassembled); answers pings; (8, b"") on close."""
        data = b""
        first_opcode = 0
        while True:
            b0, b1 = self._read(2)
            fin, opcode = b0 & 0x80, b0 & 0x0F
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._read(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._read(8))[0]
            mask = self._read(4) if b1 & 0x80 else None
            payload = self._read(n)
            if mask:
                payload = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
            if opcode == 9:
                self._send(10, payload)
                continue
            if opcode == 10:
                continue
            if opcode == 8:
                self.closed = True
                return 8, b""
            if opcode != 0:
                first_opcode = opcode
            data += payload
            if fin:
                return first_opcode, data

    # ---- the protocol
    def next_message(self) -> tuple[str, Any]:
        """('json', obj) for a JSON op (advertise is also remembered), ('data', (topic, log_time_ns, obj)) for a
        message on a subscribed json channel, ('binary', bytes) for another binary op, ('close', None)."""
        opcode, data = self.recv_frame()
        if opcode == 8:
            return "close", None
        if opcode == 1:
            obj = json.loads(data)
            if obj.get("op") == "advertise":
                for ch in obj["channels"]:
                    self.channels[int(ch["id"])] = ch
            elif obj.get("op") == "serverInfo":
                self.server_info = obj
            elif obj.get("op") == "unadvertise":
                for cid in obj.get("channelIds", []):
                    self.channels.pop(int(cid), None)
            return "json", obj
        if data[:1] == b"\x01":
            sub, log_time = struct.unpack("<IQ", data[1:13])
            channel = self.channels.get(self._subs.get(sub, -1), {})
            return "data", (channel.get("topic", ""), log_time, json.loads(data[13:]))
        return "binary", data

    def wait_channels(self, topics: list[str], timeout_s: float) -> dict[str, int]:
        """Read until every topic was advertised; topic -> channel id."""
        end = time.monotonic() + timeout_s
        while True:
            have = {ch["topic"]: cid for cid, ch in self.channels.items()}
            if all(t in have for t in topics):
                return {t: have[t] for t in topics}
            if time.monotonic() > end:
                raise TimeoutError(f"not advertised within {timeout_s} s: {sorted(set(topics) - set(have))}")
            kind, _ = self.next_message()
            if kind == "close":
                raise ConnectionError("closed before the channels were advertised")

    def subscribe(self, channel_ids: list[int]) -> None:
        subs = []
        for cid in channel_ids:
            sid = len(self._subs) + 1
            self._subs[sid] = cid
            subs.append({"id": sid, "channelId": cid})
        self._send(1, json.dumps({"op": "subscribe", "subscriptions": subs}).encode())

    def close(self) -> None:
        try:
            if not self.closed:
                self._send(8, struct.pack(">H", 1000))
        except OSError:
            pass
        self.sock.close()


def connect(host: str, port: int, *, timeout_s: float = 60.0) -> FoxgloveClient:
    """Connect, retrying while the server is not up yet."""
    end = time.monotonic() + timeout_s
    while True:
        try:
            return FoxgloveClient(host, port)
        except OSError:
            if time.monotonic() > end:
                raise
            time.sleep(0.1)
