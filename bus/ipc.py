"""`ipc`: a python-can interface that joins the processes of one user on one machine into one CAN bus.

Real-time runs keep the simulated drives out of the master's process. python-can's `virtual` bus stays in
one process, vcan needs a kernel module, `udp_multicast` may leave the host, and unix datagram sockets
queue too few datagrams per receiver for one SYNC of a big cell; UDP on 127.0.0.1 has none of these
limits. Each instance registers in a per-channel directory and sends every frame as one datagram to every
peer, stamped by the sender (the frame's time on the wire); `IpcBus` has the format and the guarantees.
No arbitration, error frames or bit timing. Importing this module registers "ipc" with python-can.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import re
import secrets
import select
import socket
import struct
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
from can.typechecking import AutoDetectedConfig

from bus.errors import CONFIG, BusError

__all__ = ["INTERFACE", "IpcBus", "IpcChannelError", "IpcStats", "channel_directory", "register"]

LOG = logging.getLogger(__name__)

INTERFACE = "ipc"
HOST = "127.0.0.1"
MAGIC = b"PVTC"
VERSION = 1
# magic, version, flags, dlc, reserved, sender id, sequence, arbitration id, sender stamp (time.time())
HEADER = struct.Struct("<4sBBBBIIId")
MAX_DATA = 64  # CAN FD
BUFFER_BYTES = 4 * 1024 * 1024  # asked for; the kernel caps it at net.core.rmem_max / wmem_max
RESCAN_CHECK_S = 0.002  # how often a sender looks at the directory's mtime
RACY_S = 0.1  # a listing taken this close to the directory's mtime may miss a change in the same tick
REGISTER_ATTEMPTS = 5  # the directory may vanish between its mkdir and our entry (its last instance left)
MAX_SENDERS_TRACKED = 1024  # sequence state kept for this many senders (reset beyond: closed senders pile up)
CHANNEL_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
ENTRY_RE = re.compile(r"(\d+)-(\d+)")

FLAG_EXTENDED = 0x01
FLAG_REMOTE = 0x02
FLAG_ERROR = 0x04
FLAG_FD = 0x08
FLAG_BRS = 0x10
FLAG_ESI = 0x20

# Linux values (include/uapi/linux/in.h, socket.h); Python's socket module lacks IP_RECVERR
IP_RECVERR = getattr(socket, "IP_RECVERR", 11)
MSG_ERRQUEUE = getattr(socket, "MSG_ERRQUEUE", 0x2000)
SEQ_MOD = 1 << 32
SEQ_HALF = 1 << 31


class IpcChannelError(BusError, ValueError):
    """A channel name that cannot name a bus directory (code CONFIG; `detail` names the field and value)."""

    def __init__(self, channel: object):
        super().__init__(
            CONFIG,
            f"ipc channel must be 1-64 characters of A-Z a-z 0-9 _ . - starting with a letter or digit "
            f"(it names a directory), got {channel!r}",
            detail={"field": "channel", "value": repr(channel)},
        )


@dataclass
class IpcStats:
    """Counters of one bus instance. The tx_* ones are written under the send lock, the rx_* ones by the
    receiving thread (python-can reads a bus from one thread)."""

    sent: int = 0  # frames sent (each to every peer)
    tx_dropped: int = 0  # datagrams the kernel would not take for a peer (our send buffer full): lost for it
    peers_dropped: int = 0  # registry entries removed: dead pid, or nothing bound to the port any more
    received: int = 0  # frames delivered by recv
    rx_lost: int = 0  # gaps in a sender's sequence: frames that never arrived (this receiver's buffer was full)
    rx_late: int = 0  # frames arriving after a later one of their sender: dropped, order is kept
    malformed: int = 0  # datagrams that were not frames of this protocol version: ignored


def register() -> None:
    """Make `can.Bus(interface="ipc", ...)` find this module when the installed entry points predate it
    (an editable install whose metadata was written before the entry point was added)."""
    import can.interfaces
    import can.util

    modules = (can.interfaces, can.util, can)  # each holds its own copy of the frozenset (can.util checks it)
    if INTERFACE in can.interfaces.BACKENDS and all(INTERFACE in vars(m)["VALID_INTERFACES"] for m in modules):
        return
    can.interfaces.BACKENDS.setdefault(INTERFACE, (__name__, "IpcBus"))
    valid = frozenset(can.interfaces.BACKENDS)
    for module in modules:
        vars(module)["VALID_INTERFACES"] = valid


def validate_channel(channel: object) -> str:
    if not isinstance(channel, str) or CHANNEL_RE.fullmatch(channel) is None:
        raise IpcChannelError(channel)
    return channel


def registry_root() -> Path:
    """The directory holding one sub-directory per channel, private to this user."""
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    if runtime:
        return Path(runtime) / "pvt-ipc"
    return Path("/dev/shm") / f"pvt-ipc-{os.getuid()}"


def channel_directory(channel: str) -> Path:
    """The registry directory of `channel` (not created)."""
    return registry_root() / validate_channel(channel)


def _make_private_dir(path: Path) -> None:
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    owner = path.stat().st_uid
    if owner != os.getuid():  # /dev/shm is shared: someone else's directory must not steer our frames
        raise can.CanInitializationError(f"ipc registry {path} belongs to uid {owner}, not to us ({os.getuid()})")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # someone else's process: alive
    return True


class IpcBus(can.BusABC):
    """One node on an `ipc` channel.

    A channel is a bus name ("pvt0"). Every instance binds its own UDP socket to 127.0.0.1:0 and registers
    in the channel's directory (`$XDG_RUNTIME_DIR/pvt-ipc/<channel>/`, or `/dev/shm/pvt-ipc-<uid>/<channel>/`)
    as an empty file `<pid>-<port>`. `send` stamps the frame (`time.time()`, its time on the wire) and sends
    one datagram to every other registered instance (and to itself with `receive_own_messages`). Peers are
    re-read when the directory's mtime changes (checked at most every `RESCAN_CHECK_S`; a listing taken
    within `RACY_S` of that mtime is re-taken, as a change in the same clock tick keeps the mtime), when a
    peer refuses a datagram (ECONNREFUSED, the port named through IP_RECVERR: its stale file is removed),
    and dead pids' files are removed. `shutdown()` removes its own file (and the empty channel directory)
    before closing its socket.

    Datagram: a 28-byte header (magic b"PVTC", version, flags, dlc, the sender's random instance id, its
    sequence number, arbitration id, sender stamp float64) and the data. On receive `msg.timestamp` is the
    sender's stamp, so a starved receiver still sees when each frame was on the wire; `msg.is_rx` is False
    only for own frames received back.

    Guarantees:
    - per-sender order: one socket per sender, loopback delivery, and a send holds the lock from numbering to
      the last peer; a datagram arriving after a later one of its sender is dropped and counted
      (`stats.rx_late`) rather than delivered out of order;
    - with `receive_own_messages` an own frame is queued back before any peer is sent it, so an answer never
      precedes its frame's echo (the master attributes TPDOs to the newest SYNC echo, bus/network.py);
    - frames of different senders are ordered by their stamps (one machine, one clock); `recv` order differs
      from stamp order only within one sender's stamp-to-sendto time, as on python-can's `virtual`;
    - loss only when a socket buffer is full (4 MiB asked for; the kernel caps at net.core.rmem_max/wmem_max):
      receivers count sequence gaps (`stats.rx_lost`), senders what the kernel would not take
      (`stats.tx_dropped`); one warning each, `dropped` sums them. Sends never block.
    """

    def __init__(
        self,
        channel: Any = None,
        receive_own_messages: bool = False,
        bitrate: int | None = None,
        can_filters: can.typechecking.CanFilters | None = None,
        **kwargs: Any,
    ) -> None:
        self.channel_name = validate_channel(channel)
        self.receive_own_messages = bool(receive_own_messages)
        self.bitrate = bitrate
        self.stats = IpcStats()
        self.directory = channel_directory(self.channel_name)
        self._pid = os.getpid()
        self._sender_id = secrets.randbits(32)
        self._seq = 0
        self._send_lock = threading.Lock()
        self._peers: dict[int, str] = {}  # port -> registry file name
        self._known_mtime_ns = -1
        self._next_check = 0.0
        self._racy = True
        self._refused: set[int] = set()
        self._refused_lock = threading.Lock()
        self._expected: dict[tuple[int, int], int] = {}  # (sender id, port) -> next sequence number
        self._warned: set[str] = set()
        self._entry: Path | None = None
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            for option in (socket.SO_RCVBUF, socket.SO_SNDBUF):
                self._sock.setsockopt(socket.SOL_SOCKET, option, BUFFER_BYTES)
            self._sock.setsockopt(socket.IPPROTO_IP, IP_RECVERR, 1)
            self._sock.bind((HOST, 0))
            self._sock.setblocking(False)
            self._port: int = self._sock.getsockname()[1]
            self.rcvbuf_bytes = self._sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
            self.sndbuf_bytes = self._sock.getsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF)
            entry = self.directory / f"{self._pid}-{self._port}"
            for attempt in range(REGISTER_ATTEMPTS):
                _make_private_dir(self.directory)
                try:
                    os.close(os.open(entry, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))
                    break
                except FileNotFoundError:  # the channel's last instance removed the empty directory just now
                    if attempt == REGISTER_ATTEMPTS - 1:
                        raise
            self._entry = entry
            self._rescan()
        except BaseException:
            if self._entry is not None:
                with contextlib.suppress(OSError):
                    os.unlink(self._entry)
            self._sock.close()
            raise
        self.channel_info = f"ipc channel {self.channel_name!r} (udp {HOST}:{self._port})"
        super().__init__(channel=self.channel_name, can_filters=can_filters, **kwargs)

    # -- registry --------------------------------------------------------------------------------------

    @property
    def port(self) -> int:
        return self._port

    @property
    def peers(self) -> list[int]:
        """The UDP ports of the other instances this one sends to (as of its last look at the directory)."""
        return sorted(self._peers)

    @property
    def dropped(self) -> int:
        """Frames lost on this instance's account: not taken by a peer, or never/too late arrived here."""
        s = self.stats
        return s.tx_dropped + s.rx_lost + s.rx_late

    def _rescan(self) -> None:
        """Re-read the directory: the other live instances of the channel. Caller holds the send lock (or
        is the constructor)."""
        started_ns = time.time_ns()
        try:
            mtime_ns = os.stat(self.directory).st_mtime_ns
            names = os.listdir(self.directory)
        except FileNotFoundError:  # someone removed the channel directory: we have no peers, and no entry
            self._peers = {}
            self._known_mtime_ns = -1
            self._racy = True
            return
        own = self._entry.name if self._entry is not None else None
        peers: dict[int, str] = {}
        for name in names:
            parsed = ENTRY_RE.fullmatch(name)
            if parsed is None or name == own:
                continue
            pid, port = int(parsed.group(1)), int(parsed.group(2))
            if not _pid_alive(pid):
                self._remove_entry(name)
                continue
            peers[port] = name
        self._peers = peers
        self._known_mtime_ns = mtime_ns
        self._racy = started_ns - mtime_ns < RACY_S * 1e9

    def _remove_entry(self, name: str) -> None:
        try:
            os.unlink(self.directory / name)
        except FileNotFoundError:
            return  # another instance cleaned it up first
        self.stats.peers_dropped += 1
        LOG.info("ipc %s: removed the stale registry entry %s", self.channel_name, name)

    def _maybe_rescan(self) -> None:
        now = time.monotonic()
        if now < self._next_check:
            return
        self._next_check = now + RESCAN_CHECK_S
        try:
            mtime_ns = os.stat(self.directory).st_mtime_ns
        except FileNotFoundError:
            mtime_ns = -1
        if self._racy or mtime_ns != self._known_mtime_ns:
            self._rescan()

    def _collect_refusals(self) -> None:
        """Read the socket's error queue (IP_RECVERR): the ports that refused a datagram (nothing bound)."""
        refused: set[int] = set()
        while True:
            try:
                _, _, _, address = self._sock.recvmsg(HEADER.size + MAX_DATA, 256, MSG_ERRQUEUE)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                break  # the socket was closed under us (shutdown from another thread)
            if isinstance(address, tuple) and len(address) >= 2:
                refused.add(int(address[1]))
        if refused:
            with self._refused_lock:
                self._refused |= refused

    def _drop_refused(self) -> None:
        """Forget the peers that refused, and remove their stale entries. Caller holds the send lock."""
        with self._refused_lock:
            refused, self._refused = self._refused, set()
        for port in refused:
            name = self._peers.pop(port, None)
            if name is not None:
                self._remove_entry(name)

    # -- python-can ----------------------------------------------------------------------------------

    def fileno(self) -> int:
        return self._sock.fileno()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send `msg` to every other instance on the channel (and back to this one with
        receive_own_messages). Never blocks; `timeout` is accepted for python-can and ignored. `msg.timestamp`
        is set to the stamp the frame carries, its time on the wire as every receiver sees it (the sender
        may be preempted between the stamp and its last datagram: a time taken after `send` returns can be
        later)."""
        if self._is_shutdown:
            raise can.CanOperationError(f"{self.channel_info} is shut down")
        data = bytes(msg.data or b"")
        if len(data) > MAX_DATA:
            raise can.CanOperationError(f"ipc frames carry at most {MAX_DATA} data bytes, got {len(data)}")
        flags = ((FLAG_EXTENDED if msg.is_extended_id else 0) | (FLAG_REMOTE if msg.is_remote_frame else 0)
                 | (FLAG_ERROR if msg.is_error_frame else 0) | (FLAG_FD if msg.is_fd else 0)
                 | (FLAG_BRS if msg.bitrate_switch else 0) | (FLAG_ESI if msg.error_state_indicator else 0))
        dlc = msg.dlc if msg.is_remote_frame else len(data)
        with self._send_lock:
            if self._refused:
                self._drop_refused()
            self._maybe_rescan()
            seq = self._seq
            self._seq = (seq + 1) % SEQ_MOD
            stamp = time.time()
            datagram = HEADER.pack(MAGIC, VERSION, flags, dlc & 0xFF, 0, self._sender_id, seq,
                                   msg.arbitration_id & 0xFFFFFFFF, stamp) + data
            if self.receive_own_messages:  # first: no peer's reply to this frame can overtake its echo
                self._send_to(datagram, self._port)
            for port in list(self._peers):
                self._send_to(datagram, port)
            self.stats.sent += 1
            if self._refused:
                self._drop_refused()
        msg.timestamp = stamp

    def _send_to(self, datagram: bytes, port: int) -> None:
        for _ in range(3):  # a refusal reported here belongs to an earlier datagram: retry
            try:
                self._sock.sendto(datagram, (HOST, port))
                return
            except (BlockingIOError, InterruptedError):
                break
            except ConnectionRefusedError:
                # an earlier datagram (to any port) was refused; this one was not sent: learn which, retry
                self._collect_refusals()
                continue
            except OSError as e:
                if e.errno != errno.ENOBUFS:
                    raise can.CanOperationError(f"{self.channel_info}: cannot send to port {port}: {e}") from e
                break
        self.stats.tx_dropped += 1
        self._warn_once("tx", "ipc %s: a peer (port %d) cannot take frames (buffer full): frames for it are dropped "
                              "and counted in stats.tx_dropped", self.channel_name, port)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            try:
                datagram, address = self._sock.recvfrom(HEADER.size + MAX_DATA + 1)
            except (BlockingIOError, InterruptedError):
                self._collect_refusals()  # an error queue entry also wakes select: read it, or select spins
                remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
                if self._is_shutdown:
                    raise can.CanOperationError(f"{self.channel_info} is shut down") from None
                try:
                    readable, _, _ = select.select([self._sock], [], [], remaining)
                except (OSError, ValueError) as e:  # closed by shutdown() from another thread
                    raise can.CanOperationError(f"{self.channel_info}: receive failed: {e}") from e
                if not readable:
                    return None, False
                continue
            except ConnectionRefusedError:
                self._collect_refusals()
                continue
            except OSError as e:
                raise can.CanOperationError(f"{self.channel_info}: receive failed: {e}") from e
            msg = self._decode(datagram, address[1])
            if msg is not None:
                self.stats.received += 1
                return msg, False

    def _decode(self, datagram: bytes, port: int) -> can.Message | None:
        """The frame in `datagram`, or None (counted) for one that is malformed or late."""
        if len(datagram) < HEADER.size or len(datagram) > HEADER.size + MAX_DATA:
            self.stats.malformed += 1
            self._warn_once("malformed", "ipc %s: ignored a datagram of %d bytes from port %d that is not a frame",
                            self.channel_name, len(datagram), port)
            return None
        magic, version, flags, dlc, _, sender_id, seq, arbitration_id, stamp = HEADER.unpack_from(datagram)
        if magic != MAGIC or version != VERSION:
            self.stats.malformed += 1
            self._warn_once("malformed", "ipc %s: ignored a datagram from port %d with magic %r version %d",
                            self.channel_name, port, magic, version)
            return None
        key = (sender_id, port)
        expected = self._expected.get(key)
        if expected is not None and seq != expected:
            ahead = (seq - expected) % SEQ_MOD
            if ahead >= SEQ_HALF:
                self.stats.rx_late += 1
                self._warn_once("late", "ipc %s: a frame from port %d arrived after a later one: dropped, counted "
                                        "in stats.rx_late", self.channel_name, port)
                return None
            self.stats.rx_lost += ahead
            self._warn_once("lost", "ipc %s: %d frame(s) from port %d never arrived (this receiver's buffer was "
                                    "full): counted in stats.rx_lost", self.channel_name, ahead, port)
        elif expected is None and len(self._expected) >= MAX_SENDERS_TRACKED:
            self._expected.clear()
        self._expected[key] = (seq + 1) % SEQ_MOD
        is_remote = bool(flags & FLAG_REMOTE)
        return can.Message(
            timestamp=stamp,
            arbitration_id=arbitration_id,
            is_extended_id=bool(flags & FLAG_EXTENDED),
            is_remote_frame=is_remote,
            is_error_frame=bool(flags & FLAG_ERROR),
            is_fd=bool(flags & FLAG_FD),
            bitrate_switch=bool(flags & FLAG_BRS),
            error_state_indicator=bool(flags & FLAG_ESI),
            dlc=dlc,
            data=None if is_remote else datagram[HEADER.size:],
            channel=self.channel_name,
            is_rx=sender_id != self._sender_id or port != self._port,
            check=False,
        )

    def _warn_once(self, kind: str, fmt: str, *args: object) -> None:
        if kind not in self._warned:
            self._warned.add(kind)
            LOG.warning(fmt, *args)

    def shutdown(self) -> None:
        """Leave the channel: remove the registry entry (peers stop sending here), then close the socket."""
        if self._is_shutdown:
            return
        super().shutdown()
        with self._send_lock:
            if self._entry is not None:
                with contextlib.suppress(FileNotFoundError):  # removed by someone who thought we were gone
                    os.unlink(self._entry)
                self._entry = None
                with contextlib.suppress(OSError):  # the last one out removes the channel (ENOTEMPTY otherwise)
                    os.rmdir(self.directory)
            self._sock.close()

    @staticmethod
    def _detect_available_configs() -> list[AutoDetectedConfig]:
        """The channels that have a registry directory (some may have no live instance left)."""
        root = registry_root()
        try:
            names = sorted(p.name for p in root.iterdir() if p.is_dir() and CHANNEL_RE.fullmatch(p.name))
        except FileNotFoundError:
            return []
        return [{"interface": INTERFACE, "channel": name} for name in names]


register()
